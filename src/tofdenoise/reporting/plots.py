"""The report's figures as PNG bytes (matplotlib, Agg, no display): learning curves of one run and the
validation MAE of all runs. From every ``metrics.csv`` of a run, the training loss (``train*loss*``) is drawn
against ``step``, validation values ending in ``mae_mm`` / ``psnr_db`` against ``epoch`` (``step`` when there
is no epoch column); raw (noisy-input) curves dashed.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from typing import Any

from tofdenoise.reporting.runs import Run

__all__ = ["learning_curves_png", "comparison_png"]


def _figure_png(draw, size=(9.0, 3.0), ncols: int = 1) -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=90)
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(1, ncols, i + 1) for i in range(ncols)]
    draw(axes)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def _series(rows: list[dict[str, Any]], key: str, x_pref: Sequence[str]) -> tuple[list[float], list[float], str]:
    for x in x_pref:
        pts = [(r[x], r[key]) for r in rows if key in r and x in r and math.isfinite(r[key])]
        if pts:
            pts.sort()
            # one value per x (Lightning may log a metric once per epoch on several rows)
            dedup: dict[float, float] = {}
            for xv, yv in pts:
                dedup[xv] = yv
            return list(dedup), list(dedup.values()), x
    return [], [], x_pref[-1]


def _curve_groups(rows: list[dict[str, Any]]) -> list[tuple[str, list[str], tuple[str, ...]]]:
    cols = sorted({k for r in rows for k in r} - {"step", "epoch"})
    groups = [
        ("training loss", [c for c in cols if c.startswith("train") and "loss" in c], ("step",)),
        ("validation MAE (mm)", [c for c in cols if c.startswith("val") and c.endswith("mae_mm")], ("epoch", "step")),
        ("validation PSNR (dB)", [c for c in cols if c.startswith("val") and c.endswith("psnr_db")], ("epoch", "step")),
    ]
    return [g for g in groups if g[1]]


def learning_curves_png(run: Run) -> bytes | None:
    """Learning curves of one run (training loss; validation MAE and PSNR, raw dashed), or None."""
    groups = _curve_groups(run.curves)
    if not groups:
        return None

    def draw(axes):
        for ax, (title, cols, xs) in zip(axes, groups):
            for c in cols:
                x, y, xname = _series(run.curves, c, xs)
                if x:
                    ax.plot(x, y, "--" if "raw" in c else "-", marker="o" if len(x) < 30 else None, ms=3, label=c)
                    ax.set_xlabel(xname)
            ax.set_title(title, fontsize=10)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)

    return _figure_png(draw, size=(4.0 * len(groups), 3.0), ncols=len(groups))


def comparison_png(runs: Sequence[Run]) -> bytes | None:
    """Validation MAE (mm) of all runs on one plot, or None when no run logged one."""
    series = []
    for r in runs:
        cols = [
            c
            for c in sorted({k for row in r.curves for k in row})
            if c.startswith("val") and c.endswith("mae_mm") and "raw" not in c and "pooled" not in c
        ]
        if cols:
            x, y, xname = _series(r.curves, cols[0], ("epoch", "step"))
            if x:
                series.append((r.name, x, y, xname))
    if not series:
        return None

    def draw(axes):
        ax = axes[0]
        for name, x, y, xname in series:
            ax.plot(x, y, marker="o" if len(x) < 30 else None, ms=3, label=name)
            ax.set_xlabel(xname)
        ax.set_ylabel("validation MAE (mm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)

    return _figure_png(draw, size=(7.0, 3.4))
