"""Training crops: the coverage of a uniformly random crop window, exact and as drawn."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tofdenoise.data_modules.transforms import crop_coverage, crop_window


@pytest.mark.parametrize(("height", "width", "crop"), [(7, 9, (3, 4)), (5, 5, (5, 5)), (6, 11, (1, 10)), (4, 4, None)])
def test_crop_coverage_is_the_share_of_windows_covering_each_pixel(height, width, crop):
    """Enumerating every window: a pixel's coverage is the number of windows holding it over the number of windows."""
    ch, cw = crop or (height, width)
    count = np.zeros((height, width))
    for top in range(height - ch + 1):
        for left in range(width - cw + 1):
            count[top : top + ch, left : left + cw] += 1
    expected = count / ((height - ch + 1) * (width - cw + 1))
    np.testing.assert_allclose(crop_coverage(height, width, crop), expected, rtol=0, atol=1e-15)


def test_crop_coverage_matches_the_windows_training_draws():
    """The drawn windows (``crop_window``, 20 000 draws) cover each pixel as often as the closed form says, and the
    coverage sums to the crop's area (a 64 x 64 crop of a 128 x 160 map: a corner 1 / (65 x 97), the centre
    64 / 65 x 64 / 97)."""
    height, width, crop = 20, 26, (8, 11)
    generator = torch.Generator().manual_seed(0)
    hits = np.zeros((height, width))
    draws = 20_000
    for _ in range(draws):
        top, left = crop_window(height, width, *crop, generator)
        hits[top : top + crop[0], left : left + crop[1]] += 1
    coverage = crop_coverage(height, width, crop)
    np.testing.assert_allclose(hits / draws, coverage, atol=0.012)
    assert coverage.sum() == pytest.approx(crop[0] * crop[1])
    big = crop_coverage(128, 160, (64, 64))
    assert big[0, 0] == pytest.approx(1 / (65 * 97)) and big[64, 80] == pytest.approx(64 / 65 * 64 / 97)
    with pytest.raises(ValueError, match="does not fit a 20x26 sample"):
        crop_coverage(height, width, (21, 4))
