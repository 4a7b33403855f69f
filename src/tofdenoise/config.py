"""The repository's Hydra configs (``configs/``): their folder and a composed config without running it.

``compose_config(overrides)`` gives what ``tofdenoise train <overrides>`` runs (tests, ``export_cli_config``,
notebooks); the folder is ``tofdenoise.paths.CONFIG_DIR``.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable, Mapping
from dataclasses import fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from tofdenoise.paths import CONFIG_DIR

if TYPE_CHECKING:  # omegaconf and Hydra are imported where they are used: `tofdenoise <verb> --help` stays light
    from omegaconf import DictConfig

T = TypeVar("T")

__all__ = ["config_dir", "compose_config", "ConfigError", "instantiate_node", "settings_group", "usage_text"]

#: Hydra's launcher plug-ins (the ``launchers`` extra): ``hydra/launcher=<name>`` -> the module that provides it
LAUNCHER_PLUGINS = {
    "joblib": "hydra_plugins.hydra_joblib_launcher",
    "submitit_local": "hydra_plugins.hydra_submitit_launcher",
    "submitit_slurm": "hydra_plugins.hydra_submitit_launcher",
}
#: folders of ``configs/`` that are not groups of the Hydra configs (configs/cli/: LightningCLI's YAMLs)
NOT_GROUPS = ("cli",)


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


class ConfigError(ValueError):
    """A config node that cannot be built: the key and the reason, in one line."""


def settings_group(cls: type[T], values: Any, where: str) -> T:
    """A group of settings (a dataclass ``cls``) from the plain mapping a config or a checkpoint holds:
    ``None`` = every default, an instance is returned as it is. A key the group does not have is a
    ``ConfigError`` naming ``<where>.<key>`` and the valid keys; a bad value is the class's own ``ValueError``."""
    if values is None:
        return cls()
    if isinstance(values, cls):
        return values
    if not isinstance(values, Mapping):
        raise ConfigError(f"{where}: expected a mapping of {cls.__name__} settings, got {type(values).__name__}")
    valid = [f.name for f in fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(str(k) for k in values if k not in valid)
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}: unknown setting; valid: {', '.join(valid)}")
    return cls(**{str(k): v for k, v in values.items()})


def instantiate_node(node: Any, key: str, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate(node, _convert_="all")``; a bad value of the node (the class raised ValueError,
    FileNotFoundError or TypeError) becomes a ``ConfigError`` naming ``key``, not Hydra's wrapped traceback."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        return instantiate(node, _convert_="all", **kwargs)
    except InstantiationException as exc:
        cause = exc.__cause__
        if isinstance(cause, (ValueError, FileNotFoundError, TypeError)):
            message = str(cause)  # a settings group names its own key (model.optim.lr): not said twice
            raise ConfigError(message if message.startswith(f"{key}.") else f"{key}: {message}") from None
        raise


def usage_text(prog: str, config_name: str, doc: str) -> str:
    """``<prog> --help``: the verb's own text (``doc``, its module docstring), then the choices of every config
    group read from the ``configs/`` folder and the installed launchers. Made without Hydra: Hydra's own help
    composes the config once per group option (seconds); ``--hydra-help`` still shows Hydra's."""
    root = config_dir()
    groups = {
        d.name: sorted(p.stem for p in d.glob("*.yaml"))
        for d in sorted(root.iterdir())
        if d.is_dir() and d.name not in NOT_GROUPS
    }
    launchers = ["basic"] + [n for n, m in LAUNCHER_PLUGINS.items() if importlib.util.find_spec(m) is not None]
    width = max(map(len, [*groups, "hydra/launcher"]))
    lines = [
        f"usage: {prog} [-m] [key=value ...] [group=option ...] [--cfg job] [--hydra-help]",
        "",
        doc.replace("``", "").replace("::\n", ":\n").strip(),
        "",
        f"config groups (configs/<group>/<option>.yaml; defaults: configs/{config_name}.yaml):",
        *(f"  {name:<{width}}  {', '.join(options)}" for name, options in groups.items()),
        f"  {'hydra/launcher':<{width}}  {', '.join(launchers)}   (-m: how a sweep's jobs run; docs/cluster.md)",
        "",
        f"{prog} [overrides] --cfg job   prints the composed config; --hydra-help: Hydra's own flags",
    ]
    return "\n".join(lines)


def hydra_console_script(
    config_name: str,
    job: Callable[[], tuple[Callable[[DictConfig], object], tuple[type[BaseException], ...]]],
    prog: str,
    doc: str = "",
) -> Callable[[], None]:
    """The ``main()`` of a Hydra console script: compose ``configs/<config_name>.yaml`` with the command line, set
    ``paths.run_dir`` to the folder Hydra created (it may contain ``${now:...}``: resolved once; in a multirun the
    job's folder), call the job's ``run`` and turn its ``errors`` into one ``<prog>: error: ...`` line and exit
    status 2 instead of a traceback. ``job()`` returns ``(run, errors)``; it is called only once Hydra has parsed the
    command line and composed the config, so ``--help``, ``--cfg job`` and a bad override import no torch or
    Lightning; ``-h`` / ``--help`` prints :func:`usage_text` (``doc``: the verb's own text) without Hydra. The
    function Hydra calls (``main.entry``) returns what ``run`` returns: the value a Hydra sweeper
    optimises (``tofdenoise train``: the run's lowest validation MAE)."""

    def entry(cfg: DictConfig) -> object:
        from hydra.core.hydra_config import HydraConfig
        from omegaconf import open_dict

        if HydraConfig.initialized():
            with open_dict(cfg):
                cfg.paths.run_dir = HydraConfig.get().runtime.output_dir
        from tofdenoise.run_lock import release_all

        try:
            run, errors = job()
            try:
                return run(cfg)
            except errors as exc:
                print(f"{prog}: error: {exc}", file=sys.stderr)
                raise SystemExit(2) from None
        except KeyboardInterrupt:  # Ctrl-C before the trainer's own handler (Lightning's, during fit) is in place
            print(f"{prog}: interrupted (Ctrl-C) before training started", file=sys.stderr)
            raise SystemExit(130) from None
        finally:
            release_all()  # the run folder's lock (taken by the Hydra callback): the run is over

    def main() -> None:
        if any(arg in ("-h", "--help") for arg in sys.argv[1:]):
            print(usage_text(prog, config_name, doc))
            return
        import hydra

        hydra.main(version_base="1.3", config_path=str(config_dir()), config_name=config_name)(entry)()

    main.entry = entry  # type: ignore[attr-defined]
    return main
