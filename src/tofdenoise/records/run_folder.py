"""A run folder: the names of its records, reading them back, and whether the run has finished.

Every reader of run folders goes through here (the grids' runner, the training job, the grid table, the results
page, the report); ``tofdenoise.callbacks.run_outputs.RunOutputs`` writes the records, ``write_run_info`` writes a
``run_info.json`` for a run that has no trainer (the classical row).
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tofdenoise.atomic import atomic_write_text
from tofdenoise.records.metrics_json import METRIC_KEYS, metric_sets, read_metrics_json

__all__ = [
    "BEST_CHECKPOINT",
    "LAST_CHECKPOINT",
    "METRICS_NAME",
    "PER_IMAGE_DIR",
    "RUN_INFO_NAME",
    "TRUTH_NAME",
    "REGIONS_NAME",
    "RESULT_RECORDS",
    "RecordError",
    "FITTED",
    "INTERRUPTED",
    "UNREADABLE",
    "training_state",
    "fit_best_checkpoints",
    "read_record",
    "remove_results",
    "load_metrics",
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
#: where a Hydra run's checkpoint callback (``callbacks.checkpointing.BestAndLastCheckpoint``, ``paths.checkpoint_dir``
#: = ``<run_dir>/checkpoints``) writes the lowest-validation-MAE and the newest checkpoint, relative to the run folder
BEST_CHECKPOINT = "checkpoints/best.ckpt"
LAST_CHECKPOINT = "checkpoints/last.ckpt"
#: a run's real-set predictions scored against a simulated capture set's rendered truth, when the set has one
#: (``tofdenoise.inference.capture_eval.evaluate_checkpoint``'s JSON; written by ``tofdenoise reproduce`` for each
#: finished run, or by hand with ``tofdenoise evaluate --ckpt``): the results page's ``truth_`` columns
TRUTH_NAME = "real_vs_truth.json"
#: a run's own test sets (synthetic, simulator-noised) scored again with the depth-edge pixels apart from the rest
#: (``tofdenoise.inference.run_eval.evaluate_run`` with ``edge_jump_mm``; written by ``tofdenoise reproduce`` for each
#: finished run, or by hand with ``tofdenoise evaluate --run RUN --edge-jump-mm 50``): the results page's "where the
#: error sits" section
REGIONS_NAME = "regions.json"


class RecordError(ValueError):
    """A record file exists but cannot be used; the message names the file."""


#: how a Gaussian baseline's variance is matched to hetero's (``ToFDataModule``, in a run_info.json's
#: ``prepared_data.noise_record.weights``): each training pixel weighted by the share of random training crops that
#: cover it. A record of a matched baseline without it was matched on whole maps, where a map's border (darker and
#: noisier under vignetting) counts as much as its centre although the crops cover it less often
VARIANCE_MATCH_WEIGHTS = "crop_coverage"


def matched_on_whole_maps(run_info: Mapping[str, Any] | None) -> bool:
    """Whether a run's training noise is a Gaussian baseline (fixed, range) variance-matched without the training
    crops' coverage: its ``noise_record`` has a scale but not ``weights`` = :data:`VARIANCE_MATCH_WEIGHTS`."""
    data = (run_info or {}).get("prepared_data")
    record = data.get("noise_record") if isinstance(data, Mapping) else None
    if not isinstance(record, Mapping) or "scale" not in record or record.get("noise") not in ("fixed", "range"):
        return False
    return record.get("weights") != VARIANCE_MATCH_WEIGHTS


def read_record(path: str | Path) -> dict[str, Any] | None:
    """The JSON object of a record file (``run_info.json``, ``metrics.json``, a figure's JSON); ``None`` when the file
    does not exist; :class:`RecordError` naming the file when it cannot be read or holds no JSON object."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise RecordError(f"{path}: the record cannot be read ({exc})") from None
    if not isinstance(data, dict):
        raise RecordError(f"{path}: the record is not a JSON object (got {type(data).__name__})")
    return data


def load_metrics(path: str | Path) -> dict[str, Any]:
    """A ``metrics.json`` read and checked against its schema (``read_metrics_json``); :class:`RecordError` naming
    the file when it is missing, unreadable or off the schema."""
    try:
        return read_metrics_json(path)
    except (OSError, ValueError) as exc:
        raise RecordError(f"{path}: the record cannot be read ({exc})") from None


#: the test set every run of the tables is scored on (the synthetic test split: ``datamodule.test_set_names``
#: always starts with it); ``real`` is there only for runs with a real set
REQUIRED_SET = "synthetic"


def load_scored_metrics(path: str | Path) -> dict[str, Any]:
    """A finished run's ``metrics.json`` as a table of runs uses it (the results page, the grid table):
    :func:`load_metrics`, with its ``synthetic`` set and no ``null`` or NaN metric (values a table cannot use: the
    run would drop out of a row's mean and an ordering silently). :class:`RecordError` naming the file otherwise."""
    path = Path(path)
    data = load_metrics(path)
    sets = metric_sets(data)
    if REQUIRED_SET not in sets:
        raise RecordError(
            f"{path}: no '{REQUIRED_SET}' section (it has {', '.join(repr(s) for s in sets) or 'none'}): every run "
            f"of the tables is scored on the synthetic test split; expected '{REQUIRED_SET}' with "
            f"{', '.join(METRIC_KEYS)}"
        )
    for set_name, entry in sets.items():
        for where, block in ((set_name, entry), (f"{set_name}.raw", entry.get("raw") or {})):
            for key in METRIC_KEYS:
                value = block.get(key)
                if key in block and value is None:
                    raise RecordError(f"{path}: '{where}.{key}' is null: the run has no value for it")
                if isinstance(value, float) and math.isnan(value):
                    raise RecordError(
                        f"{path}: '{where}.{key}' is NaN: expected a number (metrics.json writes a missing value "
                        "as null, never NaN)"
                    )
    return data


#: the results of a run folder, which a new attempt there (a fresh start, a test of another checkpoint) replaces:
#: the test metrics, the per-image CSVs and the two per-scene records ``tofdenoise reproduce`` adds
RESULT_RECORDS = (METRICS_NAME, PER_IMAGE_DIR, TRUTH_NAME, REGIONS_NAME)


#: :func:`training_state` of a folder whose fit ended (its ``run_info.json`` records optimiser steps or a training
#: time), of one whose fit stopped before its end (a ``last.ckpt`` without them), of one whose ``run_info.json``
#: cannot be read
FITTED, INTERRUPTED, UNREADABLE = "fitted", "interrupted", "unreadable"


def training_state(run_dir: str | Path) -> str | None:
    """What training the folder holds: :data:`FITTED` (``run_info.json`` records the fit's optimiser steps or
    training time, written when the fit ended), :data:`INTERRUPTED` (a ``checkpoints/last.ckpt`` without them),
    :data:`UNREADABLE` (a ``run_info.json`` that cannot be read), or None (no training: an empty or new folder, or
    a test-only run's records). A test-only attempt there would write its records over the training run's."""
    folder = Path(run_dir)
    try:
        info = read_record(folder / RUN_INFO_NAME)
    except RecordError:
        return UNREADABLE
    steps = (info or {}).get("global_step")
    if info and ((isinstance(steps, int | float) and steps > 0) or info.get("train_seconds") is not None):
        return FITTED
    return INTERRUPTED if (folder / LAST_CHECKPOINT).is_file() else None


def fit_best_checkpoints(run_dir: str | Path) -> set[Path]:
    """The best checkpoint of the fit recorded in ``run_dir``, resolved: ``<run_dir>/checkpoints/best.ckpt`` and the
    ``best_ckpt`` its ``run_info.json`` names (the checkpoint callback's folder may lie elsewhere). A test of one of
    them tests that run."""
    folder = Path(run_dir)
    found = {(folder / BEST_CHECKPOINT).resolve()}
    try:
        named = (read_record(folder / RUN_INFO_NAME) or {}).get("best_ckpt")
    except RecordError:
        named = None
    if named:
        found.add(Path(str(named)).expanduser().resolve())
    return found


def remove_results(run_dir: str | Path) -> list[str]:
    """Remove the :data:`RESULT_RECORDS` of an earlier attempt from ``run_dir`` (``metrics.json`` first, so that the
    folder never reads as a finished run with another attempt's files); the names removed."""
    removed = []
    for name in RESULT_RECORDS:
        path = Path(run_dir) / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
        else:
            continue
        removed.append(name)
    return removed


def read_run(run_dir: str | Path) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """``(run_info, metrics)`` of a run folder; ``None`` for a file that is missing or unusable (a runner deciding
    what to run; :func:`unreadable_records` says which existing files are broken)."""
    out: list[dict[str, Any] | None] = []
    for name in (RUN_INFO_NAME, METRICS_NAME):
        try:
            out.append(read_record(Path(run_dir) / name))
        except RecordError:
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
            try:
                read_record(Path(run_dir) / name)
            except RecordError as exc:
                bad.append(str(exc))
    return bad


def write_scene_record(path: str | Path, body: Mapping[str, Any]) -> Path:
    """Write a record of per-image or per-scene metrics (``TRUTH_NAME``, ``REGIONS_NAME``) atomically, as strict JSON
    with one value per line and no indentation or spaces: the same numbers as an indented file in about two thirds
    of the bytes (a 200-scene ``real_vs_truth.json`` 162 against 236 kB), since the repository carries one per run."""
    text = json.dumps(dict(body), indent=0, separators=(",", ":"), allow_nan=False) + "\n"
    return atomic_write_text(Path(path), text)


def write_run_info(run_dir: str | Path, info: Mapping[str, Any]) -> Path:
    """Write ``<run_dir>/run_info.json`` atomically (sorted keys, two-space indent)."""
    path = Path(run_dir) / RUN_INFO_NAME
    return atomic_write_text(path, json.dumps(dict(info), indent=2, sort_keys=True, allow_nan=True) + "\n")
