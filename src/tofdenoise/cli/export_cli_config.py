"""Generate the LightningCLI YAMLs (``configs/cli/*.yaml``) from the composed Hydra config.

One source of truth: the Hydra groups under ``configs/`` define a run; this module turns a composed config
into a LightningCLI config (``_target_`` -> ``class_path`` + ``init_args``; trainer arguments, callbacks and
loggers under ``trainer:``). ``tests/cli/test_lightning_cli.py`` checks that the committed files equal what
this module generates, so edit the Hydra YAMLs and re-run::

    python -m tofdenoise.cli.export_cli_config            # writes configs/cli/{default,smoke,paper}.yaml
    python -m tofdenoise.cli.export_cli_config --check    # exit 1 when a committed file is stale
    python -m tofdenoise.cli.export_cli_config --name mine --override backbone=unet --override loss=l1

The run folder of an exported config is ``outputs/cli/<name>`` (relative to the working directory).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from tofdenoise.atomic import atomic_write_text
from tofdenoise.config import compose_config, config_dir

__all__ = ["PRESETS", "hydra_to_cli", "export_preset", "render_yaml", "main"]

#: file name under configs/cli -> Hydra overrides
PRESETS: dict[str, list[str]] = {
    "default": [],
    "smoke": ["experiment=smoke"],
    "paper": ["experiment=paper"],
}

HEADER = (
    "# GENERATED from the Hydra configs by `python -m tofdenoise.cli.export_cli_config` ({overrides}).\n"
    "# Do not edit: change configs/*.yaml and re-generate (tests check that the two agree).\n"
    "# Usage: tofdenoise fit --config configs/cli/{name}.yaml  "
    "(then: tofdenoise test --config configs/cli/{name}.yaml --ckpt_path {run_dir}/checkpoints/best.ckpt)\n"
)


def _class_node(node: dict[str, Any], where: str) -> dict[str, Any]:
    if "_target_" not in node:
        raise ValueError(f"{where}: expected a node with _target_, got keys {sorted(node)}")
    args = {k: v for k, v in node.items() if not k.startswith("_")}
    return {"class_path": node["_target_"], "init_args": args}


def _class_list(group: dict[str, Any] | None, where: str) -> list[dict[str, Any]]:
    return [
        _class_node(sub, f"{where}.{key}")
        for key, sub in (group or {}).items()
        if isinstance(sub, dict) and "_target_" in sub
    ]


def hydra_to_cli(cfg: DictConfig) -> dict[str, Any]:
    """LightningCLI config dict (``seed_everything``, ``model``, ``data``, ``trainer``) of a composed config."""
    c = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(c, dict)
    trainer = {k: v for k, v in c["trainer"].items() if not k.startswith("_")}
    callbacks = _class_list(c.get("callbacks"), "callbacks")
    loggers = _class_list(c.get("logger"), "logger")
    trainer["callbacks"] = callbacks
    trainer["logger"] = loggers if loggers else False
    return {
        "seed_everything": int(c["seed"]),
        "model": _class_node(c["model"], "model"),
        "data": _class_node(c["data"], "data"),
        "trainer": trainer,
    }


def render_yaml(cli_cfg: dict[str, Any], name: str, overrides: list[str], run_dir: str) -> str:
    header = HEADER.format(overrides=" ".join(overrides) or "no overrides", name=name, run_dir=run_dir)
    return header + yaml.safe_dump(cli_cfg, sort_keys=False, default_flow_style=False)


def export_preset(name: str, overrides: list[str]) -> str:
    """YAML text of one preset (the run folder is ``outputs/cli/<name>``)."""
    run_dir = f"outputs/cli/{name}"
    cfg = compose_config([*overrides, f"paths.run_dir={run_dir}"])
    return render_yaml(hydra_to_cli(cfg), name, overrides, run_dir)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tofdenoise.cli.export_cli_config",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: configs/cli)")
    ap.add_argument("--check", action="store_true", help="only compare with the files on disk; exit 1 if stale")
    ap.add_argument("--name", default=None, help="export one config under this name instead of the presets")
    ap.add_argument("--override", action="append", default=[], help="Hydra override (repeatable; with --name)")
    args = ap.parse_args(argv)
    out = args.out or (config_dir() / "cli")
    presets = {args.name: args.override} if args.name else PRESETS
    stale = []
    for name, overrides in presets.items():
        text = export_preset(name, overrides)
        path = out / f"{name}.yaml"
        if args.check:
            if not path.is_file() or path.read_text() != text:
                stale.append(str(path))
            continue
        atomic_write_text(path, text)
        print(f"wrote {path}")
    if stale:
        print(
            "stale LightningCLI configs (re-run python -m tofdenoise.cli.export_cli_config): " + ", ".join(stale),
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
