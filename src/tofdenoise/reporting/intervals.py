"""How far a paired step of the results page can be trusted over the test images or scenes (issue 39).

The ± of a step on the results page is over training seeds only: every run shares one data seed, one split, one
synthetic test split (48 images at the CPU profile) and one stand-in capture set (24 scenes), so it says nothing
about which images happened to be drawn. This module adds the test-set side, from the per-image records:

- the **unit step**: per test image (synthetic, ``per_image/synthetic.csv``) or per scene (real set,
  ``per_image/real.csv``; against the stand-in's truth, ``real_vs_truth.json``), the step from one row of an
  ordering to the next (``value(next) - value(this)``, positive = the step holds), paired on the same image or
  scene within a seed and then averaged over the seeds (:func:`seed_averaged_steps`). Seeds are pooled this way
  because every seed scores the same images: the mean over images of the seed-averaged step is the page's
  seed-paired step exactly;
- a **percentile bootstrap** of the mean of those unit steps: units resampled with replacement
  (:data:`RESAMPLES` times, generator seeded with :data:`BOOTSTRAP_SEED`, so the page is reproducible), the
  central :data:`LEVEL` interval (:func:`bootstrap_mean_interval`, ``scipy.stats.bootstrap``);
- the **share** of units in which the step holds (its seed-averaged unit step > 0; a tie does not hold,
  :func:`share_holding`).

All functions are pure: plain numbers in, numbers out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats

__all__ = [
    "BOOTSTRAP_SEED",
    "LEVEL",
    "RESAMPLES",
    "StepInterval",
    "bootstrap_mean_interval",
    "seed_averaged_steps",
    "share_holding",
    "step_interval",
]

#: bootstrap resamples of the test units per step
RESAMPLES = 10_000
#: seed of the bootstrap's generator (a fixed seed: the page is rebuilt bit for bit from the records)
BOOTSTRAP_SEED = 0
#: the interval's coverage
LEVEL = 0.95


class StepInterval(NamedTuple):
    """One step over the test units: the mean of the seed-averaged unit steps, its bootstrap interval, the share
    of units in which it holds, and how many units."""

    mean: float
    low: float
    high: float
    share: float
    units: int


def bootstrap_mean_interval(
    values: Sequence[float], *, resamples: int = RESAMPLES, level: float = LEVEL, seed: int = BOOTSTRAP_SEED
) -> tuple[float, float]:
    """The percentile-bootstrap ``level`` interval of the mean of ``values`` (resampled with replacement,
    ``resamples`` times, ``numpy.random.default_rng(seed)``). One value, or all equal: a zero-width interval at
    it. A ``ValueError`` for no values or a non-finite one."""
    data = np.asarray(values, dtype=np.float64)
    if data.ndim != 1 or data.size == 0:
        raise ValueError("bootstrap_mean_interval: expected at least one value")
    if not np.all(np.isfinite(data)):
        raise ValueError("bootstrap_mean_interval: every value must be finite")
    if np.all(data == data[0]):  # every resample's mean is that value (summing it could round it)
        return float(data[0]), float(data[0])
    result = stats.bootstrap(
        (data,),
        np.mean,
        n_resamples=int(resamples),
        confidence_level=float(level),
        method="percentile",
        vectorized=True,
        rng=np.random.default_rng(int(seed)),
    )
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def share_holding(steps: Sequence[float]) -> float:
    """The fraction of ``steps`` that are > 0 (the step holds there); NaN for none."""
    if len(steps) == 0:
        return math.nan
    return sum(1 for s in steps if s > 0) / len(steps)


def seed_averaged_steps(
    this: Sequence[Mapping[str, float]], following: Sequence[Mapping[str, float]]
) -> dict[str, float]:
    """Per unit (image or scene name), ``following[s][unit] - this[s][unit]`` averaged over the seeds ``s``
    (``this[s]`` / ``following[s]``: the two rows' per-unit values in seed ``s``, paired by position). Only units
    that every run scored count; sorted by name. A ``ValueError`` when the two rows have a different number of
    seeds or none."""
    if len(this) != len(following) or not this:
        raise ValueError(f"seed_averaged_steps: {len(this)} and {len(following)} seeds; expected the same, >= 1")
    units = set(this[0])
    for values in (*this, *following):
        units &= set(values)
    return {u: sum(b[u] - a[u] for a, b in zip(this, following)) / len(this) for u in sorted(units)}


def step_interval(
    this: Sequence[Mapping[str, float]],
    following: Sequence[Mapping[str, float]],
    *,
    resamples: int = RESAMPLES,
    level: float = LEVEL,
    seed: int = BOOTSTRAP_SEED,
) -> StepInterval | None:
    """The step from ``this`` row to ``following`` over the test units (module docstring); None when no unit was
    scored by every run."""
    steps = list(seed_averaged_steps(this, following).values())
    if not steps:
        return None
    low, high = bootstrap_mean_interval(steps, resamples=resamples, level=level, seed=seed)
    return StepInterval(float(np.mean(steps)), low, high, share_holding(steps), len(steps))
