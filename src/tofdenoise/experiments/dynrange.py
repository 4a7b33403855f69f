"""The dynamic-range study (beyond the paper): where the physics-faithful training noise starts to pay.

For each backbone and world (a_max / a_min = 16, 64, 256 on the linear route, the physical route, and the physical
route at 4x the steps for U-Net), the gain of hetero training over fixed and over range-aware training is the
per-seed difference of test MAE, ``MAE(fixed) - MAE(hetero)`` and ``MAE(range) - MAE(hetero)`` (positive: hetero
is better), paired by seed: the runs of one seed share the data order and the initial weights, so the spread of
the difference is the noise a gain must clear. Only seeds in which all three runs finished count.

Its runs are the rows ``tables.TABLES["dynrange"]``; ``tofdenoise reproduce --study dynrange`` (``make reproduce
STUDY=dynrange``) runs them and draws the gains (``experiments.reproduce``).
"""

from __future__ import annotations

import io
import math
import statistics
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from .tables import DYNAMIC_RANGES, DYNRANGE_BACKBONES, LONG_SCHEDULE, TABLES, dynrange_key, metric_value, run_name

__all__ = ["Gain", "WORLDS", "gain_figure_png", "gains"]

#: the worlds of the study in plot order: (tag, label); "" is the physical route
WORLDS: tuple[tuple[str, str], ...] = (
    *((tag, label) for tag, (label, _) in DYNAMIC_RANGES.items()),
    (LONG_SCHEDULE[0], LONG_SCHEDULE[1]),
)


#: the figure's short x tick labels
TICKS = {"dr16": "16", "dr64": "64", "dr256": "256", "": "physical", LONG_SCHEDULE[0]: "physical,\n4x steps"}


@dataclass(frozen=True)
class Gain:
    """Hetero's paired gains in one world for one backbone (mm; mean, std over seeds; n seeds)."""

    backbone: str
    tag: str
    label: str
    n: int
    hetero_mae: float
    over_fixed: tuple[float, float]
    over_range: tuple[float, float]
    real_over_fixed: tuple[float, float]
    real_over_range: tuple[float, float]


def _mean_std(values: list[float]) -> tuple[float, float]:
    if not values:
        return math.nan, math.nan
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else math.nan


def _value(metrics: Mapping[str, Any] | None, test_set: str) -> float:
    """The run's test MAE on ``test_set`` ("synthetic" | "real"), read as the tables read it (NaN when absent)."""
    return metric_value(metrics, "mae_mm" if test_set == "synthetic" else "real_mae_mm")


def gains(metrics_of: Callable[[str], Mapping[str, Any] | None], seeds: list[int]) -> list[Gain]:
    """The paired gains of every (backbone, world) with at least one complete seed, in plot order."""
    rows = {r.key: r for r in TABLES["dynrange"]}
    out = []
    for backbone in DYNRANGE_BACKBONES:
        for tag, label in WORLDS:
            keys = {noise: dynrange_key(backbone, noise, tag) for noise in ("fixed", "range", "hetero")}
            if not all(k in rows for k in keys.values()):
                continue
            per = {"mae": [], "f": [], "r": [], "rf": [], "rr": []}
            for seed in seeds:
                syn = {n: _value(metrics_of(run_name(rows[k], seed)), "synthetic") for n, k in keys.items()}
                if not all(math.isfinite(v) for v in syn.values()):
                    continue
                real = {n: _value(metrics_of(run_name(rows[k], seed)), "real") for n, k in keys.items()}
                per["mae"].append(syn["hetero"])
                per["f"].append(syn["fixed"] - syn["hetero"])
                per["r"].append(syn["range"] - syn["hetero"])
                if all(math.isfinite(v) for v in real.values()):
                    per["rf"].append(real["fixed"] - real["hetero"])
                    per["rr"].append(real["range"] - real["hetero"])
            if per["mae"]:
                out.append(
                    Gain(
                        backbone,
                        tag,
                        label,
                        len(per["mae"]),
                        statistics.fmean(per["mae"]),
                        _mean_std(per["f"]),
                        _mean_std(per["r"]),
                        _mean_std(per["rf"]),
                        _mean_std(per["rr"]),
                    )
                )
    return out


def gain_figure_png(items: list[Gain]) -> bytes:
    """Two panels (gain over fixed, gain over range; synthetic MAE, mm) against the world, one line per backbone,
    error bars = the paired standard deviation over seeds. PNG bytes (no timestamp: the same gains, the same
    file)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    xs = {tag: i for i, (tag, _) in enumerate(WORLDS)}
    for ax, attr, title in (
        (axes[0], "over_fixed", "hetero's gain over fixed Gaussian"),
        (axes[1], "over_range", "hetero's gain over range-aware Gaussian"),
    ):
        for k, backbone in enumerate(DYNRANGE_BACKBONES):
            pts = [g for g in items if g.backbone == backbone]
            if not pts:
                continue
            x = [xs[g.tag] + (k - 0.5) * 0.12 for g in pts]
            y = [getattr(g, attr)[0] for g in pts]
            e = [0.0 if not math.isfinite(getattr(g, attr)[1]) else getattr(g, attr)[1] for g in pts]
            # one colour per backbone whichever are drawn, so that two profiles' figures read alike
            ax.errorbar(x, y, yerr=e, marker="o", capsize=3, color=f"C{k}", label=f"{DYNRANGE_BACKBONES[backbone]} "
                        f"(n per point: {'/'.join(str(g.n) for g in pts)})")  # fmt: skip
        ax.axhline(0.0, color="grey", lw=0.8)
        ax.set_xticks(range(len(WORLDS)), [TICKS.get(tag, tag) for tag, _ in WORLDS], fontsize=8)
        ax.set_xlabel("world: a_max / a_min of the linear route, or the physical route", fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("MAE(baseline) - MAE(hetero), mm\n(> 0: hetero better)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()
