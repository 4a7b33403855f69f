"""The repository's Hydra configs (``configs/``): their folder and a composed config without running it.

``compose_config(overrides)`` gives what ``tofdenoise-train <overrides>`` runs (tests, ``export_cli_config``,
notebooks); the folder is ``tofdenoise.paths.CONFIG_DIR``.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from tofdenoise.paths import CONFIG_DIR

__all__ = ["config_dir", "compose_config"]


def config_dir() -> Path:
    """The repository's ``configs/`` folder (``tofdenoise.paths.CONFIG_DIR``)."""
    return Path(CONFIG_DIR)


def compose_config(overrides: list[str] | None = None, config_name: str = "train") -> DictConfig:
    """Compose the Hydra config without running it (tests, ``export_cli_config``, notebooks)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides or []))
