"""The run-results schema and its I/O: per-image CSVs and ``metrics.json`` (all written atomically).

Functions for the LightningModule, the callbacks and the entry points (no Lightning import here):

- ``set_entry(restored, raw=None, counts=None) -> dict``: one test-set entry of ``metrics.json`` from
  ``DepthMetrics.compute()`` dicts (tensors or floats): ``{"psnr_db", "mae_mm", "mse_mm2", "ssim",
  ["mae_mm_pooled", "images", "skipped_images", "valid_px"], "raw": {same keys for the noisy input}}``.
- ``write_metrics_json(path, results, run)``: writes ``{"synthetic": entry, "real": entry}`` (whatever
  sets are given) atomically after validating the schema, plus the run-level fields ``run`` (below, all of
  ``RUN_KEYS``: every record carries the learned guard's verdict) at the top level; ``read_metrics_json(path)``
  reads and validates; ``metric_sets(data)`` keeps only the sets of a read file, ``run_fields(data)`` only the
  run-level fields.
- ``learned_verdict(trained_steps, best_val_mae_mm, raw_val_mae_mm, margin=0.05) -> dict``: the guard against
  runs that learned nothing (the one place its rule lives). The dict holds the run-level fields of
  ``metrics.json`` (``RUN_KEYS``): ``method_kind`` ("network"), ``trained_steps``, ``best_val_mae_mm``,
  ``raw_val_mae_mm``, ``learned_margin``, ``learned`` (bool) and ``learned_reason`` (plain words);
  ``classical_verdict(best_val_mae_mm, raw_val_mae_mm, margin)`` the same fields for a classical method.
- ``run_finished(run_dir)``: does a run folder hold a finished run (the one rule, used by the training job to
  return a finished run's records instead of training again and by the grids' runner to skip it);
  ``read_run(run_dir)`` gives its ``(run_info, metrics)``.
- ``write_per_image_csv(path, rows, raw_rows=None, names=None)``: rows from
  ``DepthMetrics.per_image_rows()``; columns ``index, name, valid_px, psnr_db, mae_mm, mse_mm2, ssim`` and,
  with ``raw_rows`` (matched by index), ``raw_psnr_db, raw_mae_mm, raw_mse_mm2, raw_ssim``. ``names`` maps an
  index to the image name (a dict or a sequence indexed by ``index``). ``read_per_image_csv(path)`` reads it.

File names of a run folder: ``METRICS_NAME`` (``metrics.json``), ``RUN_INFO_NAME`` (``run_info.json``) and
``PER_IMAGE_DIR`` (``per_image/``); ``tofdenoise.callbacks.run_outputs.RunOutputs`` writes them.

Every file is written through :mod:`tofdenoise.atomic` (temp file in the same folder + ``os.replace``: readers see
the old or the complete new file, never a partial one).

The learned rule: ``learned = trained_steps > 0 and best_val_mae_mm <= (1 - margin) x raw_val_mae_mm``, where
``best_val_mae_mm`` is the lowest validation MAE of the run (``val/mae_mm``, what the checkpoint callback picks
``best.ckpt`` by) and ``raw_val_mae_mm`` the MAE of the noisy input on the same validation images
(``val/raw/mae_mm``). A run without training steps is never learned ("not trained"); a run without a validation
result cannot be verified and is not learned either ("not verified"). The margin (default 5 %) is the
``DepthRestorer(learned_margin=...)`` setting.

``method_kind`` tells the two kinds of rows apart: ``"network"`` (the rule above) or ``"classical"`` (a filter
without trainable parameters, ``tofdenoise-classic``; ``classical_verdict``): 0 steps and ``learned`` False by
construction, reported as "classical", never as a failed run; its ``best_val_mae_mm`` is the validation MAE of
the parameters its grid search chose. A file without ``method_kind`` was written by a network run.

JSON numbers: NaN is written as ``null`` (e.g. a set where every image was skipped); an infinite PSNR (a
perfect image, MSE = 0) as the string ``"inf"``, so the file is strict JSON that any tool can parse.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tofdenoise.atomic import atomic_write_text
from tofdenoise.training.metrics import METRIC_KEYS

__all__ = [
    "METRIC_KEYS",
    "EXTRA_KEYS",
    "set_entry",
    "write_metrics_json",
    "read_metrics_json",
    "validate_metrics_results",
    "write_per_image_csv",
    "read_per_image_csv",
    "json_number",
    "RUN_KEYS",
    "DEFAULT_LEARNED_MARGIN",
    "learned_verdict",
    "classical_verdict",
    "learned_status",
    "METHOD_KINDS",
    "metric_sets",
    "run_fields",
    "METRICS_NAME",
    "RUN_INFO_NAME",
    "PER_IMAGE_DIR",
    "read_run",
    "run_finished",
]

EXTRA_KEYS = ("mae_mm_pooled", "images", "skipped_images", "valid_px")
CSV_COLUMNS = ("index", "name", "valid_px") + METRIC_KEYS
#: run-level (top-level, not per-set) fields of ``metrics.json``: the learned guard and the kind of method
RUN_KEYS = (
    "trained_steps",
    "best_val_mae_mm",
    "raw_val_mae_mm",
    "learned_margin",
    "learned",
    "learned_reason",
    "method_kind",
)
#: ``method_kind``: a trained network, or a classical filter whose few parameters were tuned on validation
METHOD_KINDS = ("network", "classical")
#: the records of a run folder (written by ``tofdenoise.callbacks.run_outputs.RunOutputs``): the test metrics,
#: the run's description (``backbone``, ``noise``, ``loss``, ``run_name``, ``started``, ``finished``, ...) and the
#: folder of the per-image CSVs (``per_image/<set>.csv``)
METRICS_NAME = "metrics.json"
RUN_INFO_NAME = "run_info.json"
PER_IMAGE_DIR = "per_image"
#: default margin of the learned guard: the best validation MAE must be at least 5 % below the raw MAE
DEFAULT_LEARNED_MARGIN = 0.05


def _finite_or_none(value: Any) -> float | None:
    if value is None:
        return None
    v = float(value.item() if hasattr(value, "item") else value)
    return v if math.isfinite(v) else None


def learned_verdict(
    trained_steps: int | None, best_val_mae_mm: Any, raw_val_mae_mm: Any, margin: float = DEFAULT_LEARNED_MARGIN
) -> dict[str, Any]:
    """Did the network learn? ``learned`` is True only when the run took at least one optimiser step and its
    best validation MAE is at most ``(1 - margin)`` times the raw (noisy input) validation MAE.

    Returns the run-level fields of ``metrics.json`` (``RUN_KEYS``); ``learned_reason`` says why in plain
    words (it starts with "not trained", "not verified", "did not learn" or "learned").
    """
    if not 0.0 <= float(margin) < 1.0:
        raise ValueError(f"learned margin must be in [0, 1), got {margin}")
    steps = int(trained_steps or 0)
    best, raw = _finite_or_none(best_val_mae_mm), _finite_or_none(raw_val_mae_mm)
    out: dict[str, Any] = {
        "method_kind": "network",
        "trained_steps": steps,
        "best_val_mae_mm": best,
        "raw_val_mae_mm": raw,
        "learned_margin": float(margin),
    }
    if steps <= 0:
        out["learned"] = False
        out["learned_reason"] = (
            "not trained: 0 optimiser steps (e.g. trainer.max_epochs=0); the metrics are those of the untrained network"
        )
        return out
    if best is None or raw is None:
        missing = " and ".join(n for n, v in (("best val MAE", best), ("raw val MAE", raw)) if v is None)
        out["learned"] = False
        out["learned_reason"] = (
            f"not verified: no {missing} was recorded (validation did not run), so nothing "
            "shows that the network learned"
        )
        return out
    needed = (1.0 - float(margin)) * raw
    out["learned"] = best <= needed
    if out["learned"]:
        out["learned_reason"] = (
            f"learned: best val MAE {best:.2f} mm <= {needed:.2f} mm (raw {raw:.2f} mm less {margin:.0%})"
        )
    else:
        out["learned_reason"] = (
            f"did not learn: best val MAE {best:.2f} mm vs raw {raw:.2f} mm "
            f"(needs <= {needed:.2f} mm, {margin:.0%} below raw)"
        )
    return out


def classical_verdict(
    best_val_mae_mm: Any, raw_val_mae_mm: Any, margin: float = DEFAULT_LEARNED_MARGIN
) -> dict[str, Any]:
    """The run-level fields of a classical (non-learned) method: ``method_kind`` "classical", 0 training steps,
    ``learned`` False (nothing was learned, and that is no failure: ``learned_status`` says "classical"), and
    as ``best_val_mae_mm`` the validation MAE of the parameters its tuning chose (``raw_val_mae_mm`` on the same
    images); ``learned_reason`` says whether that beat the raw input by ``margin``."""
    if not 0.0 <= float(margin) < 1.0:
        raise ValueError(f"learned margin must be in [0, 1), got {margin}")
    best, raw = _finite_or_none(best_val_mae_mm), _finite_or_none(raw_val_mae_mm)
    out: dict[str, Any] = {
        "method_kind": "classical",
        "trained_steps": 0,
        "best_val_mae_mm": best,
        "raw_val_mae_mm": raw,
        "learned_margin": float(margin),
        "learned": False,
    }
    base = "classical method: no trainable parameters, nothing learned"
    if best is None or raw is None:
        out["learned_reason"] = f"{base}; no validation result of its parameter tuning was recorded"
    else:
        needed = (1.0 - float(margin)) * raw
        verdict = "below" if best <= needed else "NOT below"
        out["learned_reason"] = (
            f"{base}; parameters tuned on the validation split: val MAE {best:.2f} mm vs raw "
            f"{raw:.2f} mm ({verdict} {needed:.2f} mm, {margin:.0%} below raw)"
        )
    return out


def learned_status(fields: Mapping[str, Any]) -> str:
    """One word-group for a verdict (``learned_verdict``, ``classical_verdict`` or the run fields of a
    ``metrics.json``): ``"learned"``, ``"not trained"``, ``"did not learn"``, ``"not verified"``,
    or ``"classical"`` (a non-learned method: not a failure)."""
    if fields.get("method_kind") == "classical":
        return "classical"
    if int(fields.get("trained_steps") or 0) <= 0:
        return "not trained"
    if fields["learned"] is True:
        return "learned"
    if fields.get("best_val_mae_mm") is None or fields.get("raw_val_mae_mm") is None:
        return "not verified"
    return "did not learn"


def metric_sets(data: Mapping[str, Any]) -> dict[str, Any]:
    """The test sets of a ``metrics.json`` (``{set: entry}``), without the run-level fields."""
    return {k: v for k, v in data.items() if k not in RUN_KEYS}


def run_fields(data: Mapping[str, Any]) -> dict[str, Any]:
    """The run-level fields (``RUN_KEYS``) of a ``metrics.json``."""
    return {k: data[k] for k in RUN_KEYS if k in data}


def json_number(value: Any) -> float | int | str | None:
    """A metric value as a strict-JSON scalar: tensors/numpy -> float, NaN -> None, +-inf -> "inf"/"-inf"."""
    if value is None:
        return None
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, bool):
        raise TypeError(f"expected a number, got bool {value!r}")
    if isinstance(value, int):
        return value
    v = float(value)
    if math.isnan(v):
        return None
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return v


def _metric_block(values: Mapping[str, Any], what: str) -> dict[str, Any]:
    missing = [k for k in METRIC_KEYS if k not in values]
    if missing:
        raise KeyError(f"{what}: missing metric key(s) {missing}; expected {list(METRIC_KEYS)}")
    out: dict[str, Any] = {k: json_number(values[k]) for k in METRIC_KEYS}
    for k in EXTRA_KEYS:
        if k in values:
            out[k] = json_number(values[k])
    return out


def set_entry(
    restored: Mapping[str, Any], raw: Mapping[str, Any] | None = None, counts: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """One set of ``metrics.json``: the restored metrics, optional counts, and ``raw`` (the noisy input)."""
    entry = _metric_block({**restored, **(counts or {})}, "restored metrics")
    if raw is not None:
        entry["raw"] = _metric_block(raw, "raw metrics")
    return entry


def _validate_run_fields(results: Mapping[str, Any], source: str) -> None:
    types: dict[str, tuple[type, ...]] = {
        "trained_steps": (int,),
        "best_val_mae_mm": (int, float, type(None)),
        "raw_val_mae_mm": (int, float, type(None)),
        "learned_margin": (int, float),
        "learned": (bool,),
        "learned_reason": (str,),
        "method_kind": (str,),
    }
    missing = [key for key in types if key not in results]
    if missing:
        raise ValueError(
            f"{source}: lacks the run-level field(s) {missing} (the learned guard's verdict; every metrics.json "
            "written by RunOutputs carries all of them)"
        )
    for key, allowed in types.items():
        v = results[key]
        if not isinstance(v, allowed) or (key != "learned" and isinstance(v, bool)):
            raise ValueError(f"{source}: '{key}' must be {' or '.join(t.__name__ for t in allowed)}, got {v!r}")
    if results["method_kind"] not in METHOD_KINDS:
        raise ValueError(f"{source}: 'method_kind' must be one of {list(METHOD_KINDS)}, got {results['method_kind']!r}")


def validate_metrics_results(results: Mapping[str, Any], source: str = "metrics") -> None:
    """Raise ValueError naming ``source`` and the set/key when ``results`` does not follow the schema (test
    sets ``{set: entry}`` plus the run-level fields ``RUN_KEYS``)."""
    if not isinstance(results, Mapping) or not metric_sets(results):
        raise ValueError(f"{source}: expected a non-empty object {{set name: metrics}}, got {type(results).__name__}")
    _validate_run_fields(results, source)
    for set_name, entry in metric_sets(results).items():
        if not isinstance(entry, Mapping):
            raise ValueError(f"{source}: set '{set_name}' must be an object, got {type(entry).__name__}")
        blocks = [(str(set_name), entry)]
        if "raw" in entry:
            if not isinstance(entry["raw"], Mapping):
                raise ValueError(f"{source}: '{set_name}.raw' must be an object")
            blocks.append((f"{set_name}.raw", entry["raw"]))
        for where, block in blocks:
            for key in METRIC_KEYS:
                if key not in block:
                    raise ValueError(f"{source}: '{where}' lacks '{key}' (expected keys {list(METRIC_KEYS)})")
                v = block[key]
                if v is not None and not isinstance(v, (int, float)) and v not in ("inf", "-inf"):
                    raise ValueError(f"{source}: '{where}.{key}' must be a number, null or \"inf\", got {v!r}")


def _normalise(results: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for set_name, entry in metric_sets(results).items():
        block = _metric_block(entry, f"set '{set_name}'")
        for k, v in entry.items():
            if k not in block and k != "raw":
                block[k] = v
        if entry.get("raw") is not None:
            block["raw"] = _metric_block(entry["raw"], f"set '{set_name}' raw")
        out[str(set_name)] = block
    return out


def write_metrics_json(path: str | Path, results: Mapping[str, Any], run: Mapping[str, Any]) -> Path:
    """Write ``{"synthetic": {...}, "real": {...}}`` to ``path`` atomically (strict JSON, sorted sets), with
    the run-level fields of ``run`` (``learned_verdict(...)`` or ``classical_verdict(...)``: all of ``RUN_KEYS``;
    other keys are refused)."""
    data = _normalise(results)
    fields = dict(run)
    unknown = sorted(set(fields) - set(RUN_KEYS))
    if unknown:
        raise KeyError(f"{path}: unknown run-level field(s) {unknown}; expected some of {list(RUN_KEYS)}")
    for key in RUN_KEYS:
        if key in fields:
            v = fields[key]
            data[key] = v if isinstance(v, (bool, str, int)) or v is None else json_number(v)
    validate_metrics_results(data, str(path))
    return atomic_write_text(path, json.dumps(data, indent=2, allow_nan=False) + "\n")


def read_metrics_json(path: str | Path) -> dict[str, Any]:
    """Read and validate a ``metrics.json``; errors name the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"metrics file not found: {path}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    validate_metrics_results(data, str(path))
    return data


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


def _name_for(names: Mapping[int, str] | Sequence[str] | None, index: int | None) -> str:
    if names is None or index is None:
        return ""
    if isinstance(names, Mapping):
        return str(names.get(index, ""))
    return str(names[index]) if 0 <= index < len(names) else ""


def _csv_value(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "nan" if math.isnan(v) else repr(v)
    return str(v)


def write_per_image_csv(
    path: str | Path,
    rows: Sequence[Mapping[str, Any]],
    raw_rows: Sequence[Mapping[str, Any]] | None = None,
    names: Mapping[int, str] | Sequence[str] | None = None,
) -> Path:
    """Write one CSV row per image (atomic). ``raw_rows`` are matched to ``rows`` by ``index``."""
    raw_by_index: dict[Any, Mapping[str, Any]] = {}
    if raw_rows is not None:
        raw_by_index = {r.get("index"): r for r in raw_rows}
        if len(raw_by_index) != len(raw_rows) or None in raw_by_index:
            raise ValueError(f"{path}: raw rows need distinct, non-empty 'index' values to be matched")
    columns = list(CSV_COLUMNS) + ([f"raw_{k}" for k in METRIC_KEYS] if raw_rows is not None else [])
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        idx = row.get("index")
        name = row.get("name") or _name_for(names, idx)
        values = [_csv_value(idx), name, _csv_value(row.get("valid_px"))]
        values += [_csv_value(row.get(k)) for k in METRIC_KEYS]
        if raw_rows is not None:
            raw = raw_by_index.get(idx)
            if raw is None:
                raise ValueError(f"{path}: no raw row for image index {idx}")
            values += [_csv_value(raw.get(k)) for k in METRIC_KEYS]
        writer.writerow(values)
    return atomic_write_text(path, buf.getvalue())


def read_per_image_csv(path: str | Path) -> list[dict[str, Any]]:
    """Read a per-image CSV back: numbers as float (``index``/``valid_px`` as int), empty cells as None."""
    out: list[dict[str, Any]] = []
    with open(path, newline="", encoding="utf-8") as fh:
        for rec in csv.DictReader(fh):
            row: dict[str, Any] = {}
            for k, v in rec.items():
                if k == "name":
                    row[k] = v
                elif v == "" or v is None:
                    row[k] = None
                elif k in ("index", "valid_px"):
                    row[k] = int(v)
                else:
                    row[k] = float(v)
            out.append(row)
    return out
