"""The test-set side of a paired step (tofdenoise.reporting.intervals), against hand-computed cases."""

from __future__ import annotations

import math
import statistics

import numpy as np
import pytest

from tofdenoise.reporting.intervals import (
    bootstrap_mean_interval,
    seed_averaged_steps,
    share_holding,
    step_interval,
)


def test_all_equal_differences_give_a_zero_width_interval_at_them():
    assert bootstrap_mean_interval([0.3] * 20) == (0.3, 0.3)
    assert bootstrap_mean_interval([-1.25]) == (-1.25, -1.25)


def test_a_shift_gives_the_shift():
    """Every image moves by the same 0.4 mm between the two runs: the step is 0.4 mm with no test-set spread,
    whatever the images' own values."""
    first = [{"a": 1.0, "b": 7.5, "c": 3.0}]
    got = step_interval(first, [{k: v + 0.4 for k, v in first[0].items()}])
    assert got.mean == pytest.approx(0.4) and got.low == pytest.approx(0.4) and got.high == pytest.approx(0.4)
    assert got.share == 1.0 and got.units == 3


def test_two_values_hand_computed():
    """Resampling two values, the mean is the smaller with probability 1/4, the midpoint 1/2, the larger 1/4: the
    central 95 % interval runs from the smaller to the larger."""
    assert bootstrap_mean_interval([-0.2, 1.0]) == pytest.approx((-0.2, 1.0))


def test_the_interval_is_the_standard_error_wide_for_many_images_and_reproducible():
    values = np.random.default_rng(5).normal(0.3, 1.0, 400)
    low, high = bootstrap_mean_interval(values)
    half = 1.96 * statistics.stdev(values) / math.sqrt(len(values))
    assert low < values.mean() < high
    assert (high - low) / 2 == pytest.approx(half, rel=0.1)
    assert bootstrap_mean_interval(values) == (low, high)  # a fixed generator seed
    assert bootstrap_mean_interval(values, seed=1) != (low, high)


def test_share_counts_the_units_where_the_step_holds():
    assert share_holding([0.5, -0.1, 0.0, 2.0]) == 0.5  # a tie does not hold
    assert share_holding([1.0]) == 1.0
    assert math.isnan(share_holding([]))


def test_seeds_are_averaged_per_unit_and_only_units_every_run_scored_count():
    this = [{"a": 1.0, "b": 2.0, "c": 5.0}, {"a": 1.5, "b": 2.0}]
    following = [{"a": 2.0, "b": 1.0, "c": 9.0}, {"a": 1.5, "b": 3.0}]
    # a: (1.0 + 0.0) / 2, b: (-1.0 + 1.0) / 2; c is missing in seed 1
    assert seed_averaged_steps(this, following) == {"a": 0.5, "b": 0.0}
    got = step_interval(this, following)
    assert got.mean == pytest.approx(0.25) and got.share == 0.5 and got.units == 2
    assert got.low == pytest.approx(0.0) and got.high == pytest.approx(0.5)
    assert step_interval([{"a": 1.0}], [{"b": 1.0}]) is None
    with pytest.raises(ValueError, match="seeds"):
        seed_averaged_steps(this, following[:1])


def test_bad_values_are_refused():
    with pytest.raises(ValueError, match="at least one"):
        bootstrap_mean_interval([])
    with pytest.raises(ValueError, match="finite"):
        bootstrap_mean_interval([1.0, math.nan])
