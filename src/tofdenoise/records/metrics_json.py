"""``metrics.json``: the schema of a run's test results, written and read atomically and validated.

JSON numbers: NaN is written as ``null`` (e.g. a set where every image was skipped); an infinite PSNR (a
perfect image, MSE = 0) as the string ``"inf"``, so the file is strict JSON that any tool can parse.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from tofdenoise.atomic import atomic_write_text

__all__ = [
    "CSV_COLUMNS",
    "EDGE_JUMP_MM",
    "EXTRA_KEYS",
    "METHOD_KINDS",
    "METRIC_KEYS",
    "RUN_KEYS",
    "TEST_SET_LABELS",
    "json_number",
    "metric_sets",
    "read_metrics_json",
    "run_fields",
    "set_entry",
    "validate_metrics_results",
    "write_metrics_json",
]

#: the four metrics of the paper, per image over its valid pixels (``tofdenoise.training.metrics``)
METRIC_KEYS: tuple[str, str, str, str] = ("psnr_db", "mae_mm", "mse_mm2", "ssim")
#: the depth step (mm) between neighbouring target pixels that makes both edge pixels
#: (``training.metrics.depth_edge_mask``): what a run's ``regions.json`` record and the results page's off-edge
#: columns use
EDGE_JUMP_MM: float = 50.0
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
#: what each test set of ``metrics.json`` is, in words (``datamodule.test_set_names``): the paper's protocol
#: synthesises the test inputs with the hetero model (the training generator of the proposed method); the
#: simulated set captures the same test scenes with the tap-level simulator; ``real`` is the capture set. A
#: ``metrics.json`` written before the simulated set existed has no ``simulated`` entry: readers treat it as absent
TEST_SET_LABELS: dict[str, str] = {
    "synthetic": "paper protocol (hetero-noised)",
    "simulated": "simulator-noised",
    "real": "capture set",
}


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
