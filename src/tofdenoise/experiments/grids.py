"""Named grids of runs and the rows of their tables (``tofdenoise.reporting.robustness`` renders them).

``robustness``: does the default recipe learn, whatever the backbone, noise model, loss, seed and camera?
U-Net, Restormer and a small DVSS x hetero/range/fixed x L1/L_full x 3 seeds x 2 calibrations (the default
sensor and ``configs/sensor/cam75.yaml``), each at the ``experiment=grid`` scale. A run passes when its best
validation MAE is at least 30 % below the raw (noisy-input) validation MAE.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tofdenoise.records import METRICS_NAME, load_scored_metrics, read_run, run_finished

from .runner import RunSpec

__all__ = [
    "ROBUSTNESS_BACKBONES",
    "ROBUSTNESS_MIN_REDUCTION",
    "robustness_specs",
    "robustness_rows",
]

#: backbone -> extra overrides ("small DVSS": width 16, one block per level)
ROBUSTNESS_BACKBONES: dict[str, tuple[str, ...]] = {
    "unet": (),
    "restormer": (),
    "dvss": ("backbone.kwargs.width=16", "backbone.kwargs.enc_blocks=[1,1,1]", "backbone.kwargs.bottleneck_blocks=1"),
}
ROBUSTNESS_NOISES = ("hetero", "range", "fixed")
ROBUSTNESS_LOSSES = ("l1", "full")
ROBUSTNESS_SENSORS = ("default", "cam75")
ROBUSTNESS_SEEDS = (0, 1, 2)
#: a run passes when 1 - best val MAE / raw val MAE >= this
ROBUSTNESS_MIN_REDUCTION = 0.30


def robustness_specs(
    backbones: Sequence[str] | None = None,
    noises: Sequence[str] = ROBUSTNESS_NOISES,
    losses: Sequence[str] = ROBUSTNESS_LOSSES,
    sensors: Sequence[str] = ROBUSTNESS_SENSORS,
    seeds: Sequence[int] = ROBUSTNESS_SEEDS,
    extra: Sequence[str] = (),
) -> list[RunSpec]:
    """The grid's runs, cheapest backbone first, named ``<backbone>-<sensor>-<noise>-<loss>-s<seed>``."""
    backbones = list(backbones) if backbones else list(ROBUSTNESS_BACKBONES)
    unknown = [b for b in backbones if b not in ROBUSTNESS_BACKBONES]
    if unknown:
        raise ValueError(f"robustness grid: unknown backbone(s) {unknown}; valid: {', '.join(ROBUSTNESS_BACKBONES)}")
    specs = []
    for b, s, n, loss, seed in itertools.product(backbones, sensors, noises, losses, seeds):
        overrides = (
            "experiment=grid",
            f"backbone={b}",
            f"noise={n}",
            f"loss={loss}",
            f"sensor={s}",
            f"seed={seed}",
            "logger=csv",
            *ROBUSTNESS_BACKBONES[b],
            *extra,
        )
        specs.append(
            RunSpec(
                f"{b}-{s}-{n}-{loss}-s{seed}",
                overrides,
                {"backbone": b, "sensor": s, "noise": n, "loss": loss, "seed": seed},
            )
        )
    return specs


def _val_maes(metrics: dict[str, Any] | None) -> tuple[float, float]:
    if not metrics:
        return math.nan, math.nan
    best = metrics.get("best_val_mae_mm", math.nan)  # run-level fields of the learned guard
    raw = metrics.get("raw_val_mae_mm", math.nan)
    return (math.nan if best is None else float(best)), (math.nan if raw is None else float(raw))


def robustness_rows(specs: Sequence[RunSpec], out_dir: Path | str) -> list[dict[str, Any]]:
    """One row per spec: its meta, best and raw validation MAE, reduction, test MAE, pass/fail/missing. A run's
    ``metrics.json`` that the table cannot use (no ``synthetic`` section, a ``null`` or NaN metric) is a
    ``RecordError`` naming it (``records.load_scored_metrics``, as on the results page), not a row without it."""
    rows = []
    for spec in specs:
        run_dir = Path(out_dir) / spec.name
        _, metrics = read_run(run_dir)
        if metrics is not None:
            metrics = load_scored_metrics(run_dir / METRICS_NAME)
        best, raw = _val_maes(metrics)
        reduction = 1.0 - best / raw if raw and math.isfinite(best) and math.isfinite(raw) else math.nan
        synthetic = (metrics or {}).get("synthetic") or {}
        finished = run_finished(run_dir)
        passed = (
            math.isfinite(best) and math.isfinite(raw) and best <= (1.0 - ROBUSTNESS_MIN_REDUCTION) * raw * (1 + 1e-12)
        )
        status = "missing" if not finished else ("pass" if passed else "FAIL")
        rows.append(
            {
                **spec.meta,
                "name": spec.name,
                "best_val_mae_mm": best,
                "raw_val_mae_mm": raw,
                "reduction": reduction,
                "test_mae_mm": synthetic.get("mae_mm"),
                "test_raw_mae_mm": (synthetic.get("raw") or {}).get("mae_mm"),
                "status": status,
            }
        )
    return rows
