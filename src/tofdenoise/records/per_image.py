"""Per-image CSVs of a run (``per_image/<set>.csv``): one row per test image, restored and raw metrics."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from tofdenoise.atomic import atomic_write_text
from tofdenoise.records.metrics_json import CSV_COLUMNS, METRIC_KEYS

__all__ = ["read_per_image_csv", "write_per_image_csv"]


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
