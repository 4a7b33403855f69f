"""The robustness grid's table (``tofdenoise grid``): rows from ``tofdenoise.experiments.grids.robustness_rows``."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from tofdenoise.experiments.grids import ROBUSTNESS_MIN_REDUCTION
from tofdenoise.reporting.numbers import format_number

__all__ = ["robustness_table"]


def robustness_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown: one line per (backbone, sensor, noise, loss) with the per-seed reductions, then a summary."""
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["backbone"], r["sensor"], r["noise"], r["loss"]), []).append(r)
    lines = [
        "| backbone | sensor | noise | loss | raw val MAE (mm) | best val MAE (mm) per seed | "
        "reduction per seed | status |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (b, s, n, loss), rs in groups.items():
        raw = [r["raw_val_mae_mm"] for r in rs if math.isfinite(r["raw_val_mae_mm"])]
        best = " / ".join(format_number(r["best_val_mae_mm"]) for r in rs)
        red = " / ".join(
            format_number(100 * r["reduction"], 0) + ("%" if math.isfinite(r["reduction"]) else "") for r in rs
        )
        statuses = {r["status"] for r in rs}
        status = "FAIL" if "FAIL" in statuses else ("incomplete" if "missing" in statuses else "pass")
        lines.append(
            f"| {b} | {s} | {n} | {loss} | {format_number(raw[0]) if raw else '-'} | {best} | {red} | {status} |"
        )
    done = [r for r in rows if r["status"] != "missing"]
    failed = [r for r in done if r["status"] == "FAIL"]
    lines.append("")
    lines.append(
        f"{len(done)} of {len(rows)} runs finished; {len(done) - len(failed)} pass "
        f"(>= {100 * ROBUSTNESS_MIN_REDUCTION:.0f} % below the raw validation MAE), {len(failed)} fail"
        + (": " + ", ".join(r["name"] for r in failed) if failed else "")
        + "."
    )
    return "\n".join(lines)
