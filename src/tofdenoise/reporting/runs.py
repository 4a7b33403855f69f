"""Run folders for the report: which folders are runs, and what the report reads from one.

A run is any folder (searched recursively) that holds a ``metrics.json`` (``tofdenoise.records``).
:func:`load_run` reads from it:

- ``metrics.json``: final test metrics per set (``synthetic``, ``real``) with the ``raw`` (noisy input) block,
  and the learned guard's run-level fields (``learned``, ``learned_reason``, ``trained_steps``, ...);
- ``run_info.json`` ``{"backbone", "noise", "loss", "run_name"}`` (optional ``"method"`` label), else
  ``.hydra/config.yaml`` (``backbone.name``, ``noise.name``, ``loss.name``, ``run_name``), else the folder name;
- every ``metrics.csv`` below the run (Lightning's CSVLogger) for learning curves;
- ``panels/*.png`` (``ImagePanelLogger``): the latest validation panel (highest epoch number in the name).
"""

from __future__ import annotations

import csv
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from tofdenoise.records import METRICS_NAME, RUN_INFO_NAME, metric_sets, read_metrics_json, read_record, run_fields

__all__ = ["Run", "find_runs", "load_run", "load_runs"]

#: folders of a run that hold no run of their own
_SKIP_DIRS = {"wandb", "checkpoints", "panels", ".hydra", "csv", "tensorboard", "predictions", "__pycache__"}


@dataclass
class Run:
    """One run folder as the report reads it (:func:`load_run`)."""

    path: Path
    name: str
    method: str
    noise: str
    loss: str
    metrics: dict[str, Any]
    curves: list[dict[str, Any]] = field(default_factory=list)
    panel: Path | None = None
    #: the learned guard's run-level fields of metrics.json
    learned: dict[str, Any] = field(default_factory=dict)


def find_runs(roots: Sequence[str | Path]) -> list[Path]:
    """Run folders (holding ``metrics.json``) under ``roots``, sorted, without duplicates."""
    found: set[Path] = set()
    for root in roots:
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"runs folder not found: {root}")
        for mj in root.rglob(METRICS_NAME):
            rel = mj.relative_to(root).parts[:-1]
            if any(p in _SKIP_DIRS or p.startswith(".") for p in rel[-1:]):
                continue
            found.add(mj.parent.resolve())
    return sorted(found)


def _hydra_info(path: Path) -> dict[str, Any]:
    """backbone/noise/loss names and run_name from a saved Hydra config (interpolations resolved if possible)."""

    try:
        cfg = OmegaConf.load(path)
    except Exception as exc:  # noqa: BLE001 - any YAML/OmegaConf error: report the file
        raise ValueError(f"{path}: not a readable config ({exc})") from None

    def pick(key: str) -> Any:
        try:
            value = OmegaConf.select(cfg, key, default=None)
        except Exception:  # noqa: BLE001 - unresolvable interpolation (e.g. a resolver not registered here)
            return None
        return value if isinstance(value, (str, int, float)) else None

    return {
        "backbone": pick("backbone.name"),
        "noise": pick("noise.name"),
        "loss": pick("loss.name"),
        "run_name": pick("run_name"),
    }


def _read_info(run_dir: Path) -> dict[str, str]:
    info: dict[str, Any] | None = read_record(run_dir / RUN_INFO_NAME)
    if info is None:
        info = {}
        hydra_cfg = run_dir / ".hydra" / "config.yaml"
        if hydra_cfg.is_file():
            info = _hydra_info(hydra_cfg)
    out = {k: str(v) for k, v in info.items() if v is not None and not isinstance(v, (dict, list))}
    out.setdefault("run_name", run_dir.name)
    return out


def _read_curves(run_dir: Path) -> list[dict[str, Any]]:
    """Rows of every ``metrics.csv`` below the run (numbers as float; empty cells dropped)."""
    rows: list[dict[str, Any]] = []
    for csv_path in sorted(run_dir.rglob("metrics.csv")):
        with open(csv_path, newline="", encoding="utf-8") as fh:
            for rec in csv.DictReader(fh):
                row: dict[str, Any] = {}
                for k, v in rec.items():
                    if k is None or v in (None, ""):
                        continue
                    try:
                        row[k] = float(v)
                    except ValueError:
                        continue
                if row:
                    rows.append(row)
    return rows


def _epoch_order(path: Path) -> tuple[int, str]:
    """Sort key: the last number in the file name (epoch_999 < epoch_1000), then the name."""
    numbers = re.findall(r"\d+", path.stem)
    return (int(numbers[-1]) if numbers else -1, path.name)


def load_run(run_dir: str | Path) -> Run:
    """Read one run folder (raises ValueError/FileNotFoundError naming the bad file)."""
    run_dir = Path(run_dir)
    data = read_metrics_json(run_dir / METRICS_NAME)
    metrics, learned = metric_sets(data), run_fields(data)
    info = _read_info(run_dir)
    panels = sorted((run_dir / "panels").glob("*.png"), key=_epoch_order) if (run_dir / "panels").is_dir() else []
    return Run(
        path=run_dir,
        name=info["run_name"],
        method=info.get("method", info.get("backbone", info["run_name"])),
        noise=info.get("noise", "?"),
        loss=info.get("loss", "?"),
        metrics=metrics,
        curves=_read_curves(run_dir),
        panel=panels[-1] if panels else None,
        learned=learned,
    )


def load_runs(run_dirs: Sequence[str | Path]) -> tuple[list[Run], list[tuple[Path, str]]]:
    """Every run of ``run_dirs`` that can be read, sorted by name, and the others with the reason (what the report
    lists instead of stopping)."""
    runs: list[Run] = []
    skipped: list[tuple[Path, str]] = []
    for d in run_dirs:
        try:
            runs.append(load_run(d))
        except (OSError, ValueError) as exc:
            skipped.append((Path(d), str(exc)))
    return sorted(runs, key=lambda r: r.name), skipped
