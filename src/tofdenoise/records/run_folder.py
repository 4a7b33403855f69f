"""A run folder: the names of its records, reading them back, and whether the run has finished.

Every reader of run folders goes through here (the grids' runner, the training job, the grid table, the results
page, the report); ``tofdenoise.callbacks.run_outputs.RunOutputs`` writes the records, ``write_run_info`` writes a
``run_info.json`` for a run that has no trainer (the classical row).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tofdenoise.atomic import atomic_write_text

__all__ = [
    "METRICS_NAME",
    "PER_IMAGE_DIR",
    "RUN_INFO_NAME",
    "read_run",
    "run_finished",
    "unreadable_records",
    "write_run_info",
]

#: the records of a run folder (written by ``tofdenoise.callbacks.run_outputs.RunOutputs``): the test metrics,
#: the run's description (``backbone``, ``noise``, ``loss``, ``run_name``, ``started``, ``finished``, ...) and the
#: folder of the per-image CSVs (``per_image/<set>.csv``)
METRICS_NAME = "metrics.json"
RUN_INFO_NAME = "run_info.json"
PER_IMAGE_DIR = "per_image"


def read_run(run_dir: str | Path) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """``(run_info, metrics)`` of a run folder; ``None`` for a file that is missing or does not parse."""
    out: list[dict[str, Any] | None] = []
    for name in (RUN_INFO_NAME, METRICS_NAME):
        try:
            out.append(json.loads((Path(run_dir) / name).read_text()))
        except (OSError, ValueError):
            out.append(None)
    return out[0], out[1]


def run_finished(run_dir: str | Path) -> bool:
    """True when the run folder holds a finished run: ``run_info.json`` with ``finished`` and a ``metrics.json``
    (``finished`` is written after ``metrics.json``, at the end of the test)."""
    info, metrics = read_run(run_dir)
    return bool(info and info.get("finished")) and metrics is not None


def unreadable_records(run_dirs: Sequence[str | Path]) -> list[str]:
    """``"<file>: <why>"`` for each record (``run_info.json``, ``metrics.json``) of the run folders that exists but
    is not a JSON object: a finished run whose record broke must not pass for an unfinished one in a table."""
    bad = []
    for run_dir in run_dirs:
        for name in (RUN_INFO_NAME, METRICS_NAME):
            path = Path(run_dir) / name
            if not path.is_file():
                continue
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError) as exc:
                bad.append(f"{path}: the record cannot be read ({exc})")
                continue
            if not isinstance(data, dict):
                bad.append(f"{path}: not a JSON object")
    return bad


def write_run_info(run_dir: str | Path, info: Mapping[str, Any]) -> Path:
    """Write ``<run_dir>/run_info.json`` atomically (sorted keys, two-space indent)."""
    path = Path(run_dir) / RUN_INFO_NAME
    return atomic_write_text(path, json.dumps(dict(info), indent=2, sort_keys=True, allow_nan=True) + "\n")
