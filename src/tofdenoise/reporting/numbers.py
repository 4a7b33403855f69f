"""The numbers every rendered table shares: the metric columns, how a number is written, how a number is read back
from a ``metrics.json``.

- :data:`METRIC_COLUMNS`: the four metrics of a test set (``training.results.METRIC_KEYS``), each with its HTML and
  text header, its decimals and whether higher is better. ``tofdenoise report``'s table and page, the results page
  (``docs/results.md``) and the paper's tables (``experiments.tables``) all take them from here.
- :func:`format_number`: one number as text (missing -> a dash, infinities written out).
- :func:`read_number`: a metric value as ``metrics.json`` stores it (a number, ``null``, or ``"inf"`` / ``"-inf"``,
  see ``training.results.json_number``) as a float, or None.

It imports only ``training.results`` (the schema): the experiments and every renderer can use it.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

from tofdenoise.records import json_number

__all__ = ["MetricColumn", "METRIC_COLUMNS", "METRICS_BY_KEY", "format_number", "read_number"]


class MetricColumn(NamedTuple):
    """One metric: its ``metrics.json`` key, HTML and text headers, decimals shown, and whether higher is better."""

    key: str
    html: str
    text: str
    decimals: int
    higher: bool


METRIC_COLUMNS: tuple[MetricColumn, ...] = (
    MetricColumn("psnr_db", "PSNR (dB)&uarr;", "PSNR (dB)↑", 2, True),
    MetricColumn("ssim", "SSIM&uarr;", "SSIM↑", 4, True),
    MetricColumn("mse_mm2", "MSE (mm&sup2;)&darr;", "MSE (mm²)↓", 2, False),
    MetricColumn("mae_mm", "MAE (mm)&darr;", "MAE (mm)↓", 2, False),
)
#: the same columns by metric key
METRICS_BY_KEY: dict[str, MetricColumn] = {c.key: c for c in METRIC_COLUMNS}


def format_number(v: Any, decimals: int = 2, missing: str = "-") -> str:
    """``v`` with ``decimals`` decimals; ``missing`` for None and NaN; ``inf`` / ``-inf`` for the infinities (what
    ``metrics.json`` stores for them: ``training.results.json_number``)."""
    stored = json_number(v)
    if stored is None:
        return missing
    if isinstance(stored, str):
        return stored
    return f"{stored:.{decimals}f}"


def read_number(v: Any) -> float | None:
    """A stored metric value as a float (``"inf"`` / ``"-inf"`` -> the infinities); None when absent or not a
    number."""
    if v is None:
        return None
    if v == "inf":
        return math.inf
    if v == "-inf":
        return -math.inf
    try:
        return float(v)
    except (TypeError, ValueError):
        return None
