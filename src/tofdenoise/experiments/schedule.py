"""The long-schedule study (``tables.TABLES["schedule"]``): does hetero training's gain last with training length?

Its runs are DVSS trained with the fixed, range and hetero noise for ``tables.SCHEDULE_EPOCHS`` epochs; each run's
validation curve is its ``csv/metrics.csv`` (``val/mae_mm`` per validation step, every run of a seed validated on
identical inputs). The gap between two training noises along training is the paired difference of their curves at
the same validation step: ``gap = MAE(baseline) - MAE(hetero)`` (> 0: hetero better). :func:`gap_table` reads it at
the end of the short schedule (the ``gpu-short`` profile's 10 epochs) and at the end of the long one, so the page can
say whether the gap opens, holds or closes; :func:`curves_figure_png` draws the curves and the gaps.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

from tofdenoise.experiments.tables import TABLES, run_name

__all__ = [
    "CURVES_FIGURE",
    "Curve",
    "curves_figure_png",
    "gap_table",
    "read_val_curve",
    "schedule_curves",
]

#: the study's figure, under docs/results/<profile>/
CURVES_FIGURE = "schedule/curves.png"
#: the metric of the curves (a column of ``csv/metrics.csv``)
VAL_COLUMN = "val/mae_mm"
#: the short schedule the long one is compared with: the gpu-short profile's epochs
SHORT_EPOCHS = 10


@dataclass(frozen=True)
class Curve:
    """One run's validation curve: its training noise, seed, and (step, val MAE mm) pairs in step order."""

    noise: str
    seed: int
    points: tuple[tuple[int, float], ...]


def read_val_curve(path: Path) -> tuple[tuple[int, float], ...]:
    """``(step, val/mae_mm)`` of every validation row of a run's ``csv/metrics.csv``, by step (a resumed run logs each
    step once: ``callbacks.csv_log``); empty when the file or the column is missing. A row whose value is not a
    finite number is a ``ValueError`` naming the file."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        return ()
    points = {}
    for row in rows:
        value = (row.get(VAL_COLUMN) or "").strip()
        if not value:
            continue
        try:
            mae, step = float(value), int(row["step"])
        except (KeyError, ValueError):
            raise ValueError(f"{path}: a {VAL_COLUMN} row without a readable step and value: {row}") from None
        if not math.isfinite(mae):
            raise ValueError(f"{path}: {VAL_COLUMN} at step {step} is {value}, not a finite number")
        points[step] = mae
    return tuple(sorted(points.items()))


def schedule_curves(dest: Path, seeds: list[int]) -> list[Curve]:
    """The curves of the study's runs recorded under ``dest`` (``docs/results/<profile>``), for ``seeds``."""
    curves = []
    for seed in seeds:
        for row in TABLES["schedule"]:
            points = read_val_curve(dest / run_name(row, seed) / "csv" / "metrics.csv")
            if points:
                curves.append(Curve(row.noise, seed, points))
    return curves


def _paired_gap(base: Curve, hetero: Curve) -> dict[int, float]:
    """``MAE(base) - MAE(hetero)`` at the validation steps both curves have."""
    h = dict(hetero.points)
    return {step: mae - h[step] for step, mae in base.points if step in h}


def _at_or_before(gaps: dict[int, float], step: float) -> tuple[int, float] | None:
    """The gap at the last validation step at or before ``step``."""
    before = [s for s in gaps if s <= step]
    return (max(before), gaps[max(before)]) if before else None


def gap_table(curves: list[Curve], epochs: int) -> list[dict[str, object]]:
    """Per seed and baseline noise, the gap to hetero at the end of the short schedule (the last validation step within
    ``SHORT_EPOCHS / epochs`` of the run) and at the run's last validation step. Rows: ``seed``, ``baseline``,
    ``short_step``, ``short_gap_mm``, ``end_step``, ``end_gap_mm`` (None where a curve is missing)."""
    by = {(c.noise, c.seed): c for c in curves}
    rows: list[dict[str, object]] = []
    for seed in sorted({c.seed for c in curves}):
        hetero = by.get(("hetero", seed))
        for baseline in ("fixed", "range"):
            base = by.get((baseline, seed))
            if hetero is None or base is None:
                continue
            gaps = _paired_gap(base, hetero)
            if not gaps:
                continue
            end_step = max(gaps)
            # the run's steps per epoch from its last validation step (validation ends an epoch)
            short = _at_or_before(gaps, (end_step + 1) * SHORT_EPOCHS / epochs)
            rows.append(
                {
                    "seed": seed,
                    "baseline": baseline,
                    "short_step": None if short is None else short[0],
                    "short_gap_mm": None if short is None else short[1],
                    "end_step": end_step,
                    "end_gap_mm": gaps[end_step],
                }
            )
    return rows


def curves_figure_png(curves: list[Curve]) -> bytes:
    """Two panels: validation MAE along training per training noise (a line style per seed), and the paired gaps
    ``MAE(fixed) - MAE(hetero)`` and ``MAE(range) - MAE(hetero)`` along training. PNG bytes (no timestamp: the same
    curves, the same file)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"fixed": "tab:blue", "range": "tab:orange", "hetero": "tab:green"}
    styles = ["-", "--", ":", "-."]
    seeds = sorted({c.seed for c in curves})
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    for c in curves:
        steps, maes = zip(*c.points, strict=True)
        style = styles[seeds.index(c.seed) % len(styles)]
        left.plot(steps, maes, style, color=colours.get(c.noise), label=f"{c.noise}, seed {c.seed}")
    by = {(c.noise, c.seed): c for c in curves}
    for seed in seeds:
        for baseline in ("fixed", "range"):
            if (baseline, seed) in by and ("hetero", seed) in by:
                gaps = _paired_gap(by[(baseline, seed)], by[("hetero", seed)])
                style = styles[seeds.index(seed) % len(styles)]
                label = f"{baseline} - hetero, seed {seed}"
                right.plot(list(gaps), list(gaps.values()), style, color=colours[baseline], label=label)
    left.set_yscale("log")
    left.set_title("validation MAE along training", fontsize=10)
    left.set_ylabel("val MAE, mm")
    right.axhline(0.0, color="grey", lw=0.8)
    right.set_title("gap to hetero training (> 0: hetero better)", fontsize=10)
    right.set_ylabel("MAE(baseline) - MAE(hetero), mm")
    for ax in (left, right):
        ax.set_xlabel("optimiser step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()
