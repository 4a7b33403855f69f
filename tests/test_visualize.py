"""Colourisation, colour bars and sample panels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tofdenoise.visualize import (
    INVALID_RGB,
    add_title,
    colorbar,
    colorize,
    colorize_depth,
    compose_panel,
    prediction_preview,
    robust_range,
    sample_panel,
    stack_panels,
)


def _lut(colormap: int) -> np.ndarray:
    ramp = np.arange(256, dtype=np.uint8)[None, :]
    return cv2.cvtColor(cv2.applyColorMap(ramp, colormap), cv2.COLOR_BGR2RGB)[0]


def _scene(h: int = 40, w: int = 60):
    yy, xx = np.mgrid[:h, :w]
    clean = 700.0 + 5.0 * xx + 2.0 * yy
    sigma = 1.0 + 0.1 * xx
    rng = np.random.default_rng(0)
    noisy = clean + rng.normal(size=clean.shape) * sigma * 4
    restored = clean + rng.normal(size=clean.shape)
    mask = np.ones((h, w))
    mask[:5, :7] = 0
    return noisy, restored, clean, sigma, mask


def test_colorize_maps_limits_to_colormap_ends_and_invalid_to_grey():
    lut = _lut(cv2.COLORMAP_TURBO)
    values = np.array([[100.0, 200.0, 150.0], [50.0, np.nan, 999.0]])
    mask = np.array([[1, 1, 1], [1, 1, 0]], dtype=bool)
    rgb = colorize(values, 100.0, 200.0, cv2.COLORMAP_TURBO, mask)
    assert rgb.dtype == np.uint8 and rgb.shape == (2, 3, 3)
    assert tuple(rgb[0, 0]) == tuple(lut[0])
    assert tuple(rgb[0, 1]) == tuple(lut[255])
    assert tuple(rgb[0, 2]) == tuple(lut[128])
    assert tuple(rgb[1, 0]) == tuple(lut[0])  # below vmin clips
    assert tuple(rgb[1, 1]) == INVALID_RGB  # NaN
    assert tuple(rgb[1, 2]) == INVALID_RGB  # masked
    with pytest.raises(ValueError, match="vmax > vmin"):
        colorize(values, 1.0, 1.0)


def test_colorize_accepts_tensors_of_shape_b1hw():
    t = torch.linspace(0, 1, 12).reshape(1, 1, 3, 4)
    assert colorize_depth(t, 0.0, 1.0).shape == (3, 4, 3)
    with pytest.raises(ValueError, match="single 2-D map"):
        colorize_depth(torch.zeros(2, 1, 3, 4), 0.0, 1.0)


def test_robust_range_ignores_invalid_and_handles_flat_maps():
    v = np.arange(101, dtype=float)
    v[0] = 1e9
    mask = np.ones(101, dtype=bool)
    mask[0] = False
    lo, hi = robust_range(v, mask, (0.0, 100.0))
    assert (lo, hi) == (1.0, 100.0)
    assert robust_range(np.full((3, 3), 5.0)) == (5.0, 6.0)
    assert robust_range(np.full((3, 3), np.nan)) == (0.0, 1.0)


def test_colorbar_top_is_max_colour():
    bar = colorbar(120, 0.0, 10.0, cv2.COLORMAP_INFERNO)
    lut = _lut(cv2.COLORMAP_INFERNO)
    assert bar.shape[0] == 120
    assert np.abs(bar[14, 8].astype(int) - lut[255].astype(int)).max() <= 1
    assert np.abs(bar[120 - 9, 8].astype(int) - lut[0].astype(int)).max() <= 1


def test_sample_panel_shares_the_depth_scale_across_maps():
    noisy, restored, clean, sigma, mask = _scene()
    h, w = clean.shape
    panel = sample_panel(noisy, clean.copy(), clean, sigma, mask, max_tile=None)
    strip, gap = 20, 4
    tile = lambda k: panel[strip : strip + h, k * (w + gap) : k * (w + gap) + w]  # noqa: E731
    # restored == clean -> identical tiles; noisy differs but its invalid pixels are grey too
    assert np.array_equal(tile(1), tile(2))
    assert not np.array_equal(tile(0), tile(2))
    assert (tile(0)[:5, :7] == INVALID_RGB).all() and (tile(2)[:5, :7] == INVALID_RGB).all()
    # a pixel with the same depth value has the same colour in the noisy and the clean tile
    lo, hi = robust_range(clean, mask.astype(bool) & (clean > 0))
    expected = colorize_depth(np.array([[clean[20, 30]]]), lo, hi)[0, 0]
    assert tuple(tile(2)[20, 30]) == tuple(expected)
    # two rows: depth row and sigma/error row, each with a colour bar on the right
    assert panel.shape[0] == (strip + h) + 4 + (36 + h)  # row-2 titles have two lines
    assert panel.dtype == np.uint8 and panel.ndim == 3


def test_sample_panel_error_row_shows_mae_in_title_and_zero_error_is_darkest():
    noisy, restored, clean, sigma, mask = _scene()
    h, w = clean.shape
    panel = sample_panel(noisy, clean.copy(), clean, sigma, mask, max_tile=None)
    row2 = panel[20 + h + 4 + 36 :]
    err_tile = row2[:h, 2 * (w + 4) : 2 * (w + 4) + w]
    lut = _lut(cv2.COLORMAP_INFERNO)
    assert tuple(err_tile[30, 40]) == tuple(lut[0])


def test_panel_downscales_tiles_and_titles_fit():
    noisy, restored, clean, sigma, mask = _scene(200, 300)
    panel = sample_panel(noisy, restored, clean, sigma, mask, title="epoch 1", max_tile=100)
    assert panel.shape[0] == 20 + (20 + 67) + 4 + (36 + 67)
    assert add_title(np.zeros((10, 30, 3), np.uint8), "a very long title that does not fit").shape == (30, 30, 3)
    assert add_title(np.zeros((10, 30, 3), np.uint8), "two\nlines").shape == (46, 30, 3)


def test_small_maps_are_enlarged_by_an_integer_factor():
    noisy, restored, clean, sigma, mask = _scene(12, 16)
    panel = sample_panel(noisy, clean.copy(), clean, sigma, mask, max_tile=None, min_tile=64)
    h, w = 12 * 4, 16 * 4  # factor ceil(64 / 16) = 4, nearest neighbour
    assert panel.shape[0] == (20 + h) + 4 + (36 + h)
    tile = panel[20 : 20 + h, 0:w]
    assert np.array_equal(tile[::4, ::4], tile[3::4, 3::4])  # 4x4 blocks of one colour


def test_compose_panel_errors_and_prediction_preview_is_bgr():
    noisy, restored, clean, sigma, mask = _scene()
    with pytest.raises(ValueError, match="map 'restored' has shape"):
        compose_panel({"noisy": noisy, "restored": restored[:-1]})
    rgb = compose_panel({"noisy": noisy, "restored": restored, "clean": clean}, sigma, mask, max_tile=None)
    bgr = prediction_preview({"noisy": noisy, "restored": restored, "clean": clean}, sigma, mask)
    assert np.array_equal(rgb[..., ::-1], bgr)
    # without a reference there is no error row
    only = compose_panel({"restored": restored}, None, None, max_tile=None)
    assert only.shape[0] == 20 + clean.shape[0]


def test_stack_panels_pads_widths():
    out = stack_panels([np.zeros((5, 10, 3), np.uint8), np.zeros((7, 4, 3), np.uint8)], gap=2)
    assert out.shape == (14, 10, 3)
    with pytest.raises(ValueError):
        stack_panels([])


def test_batch_plane_takes_one_image_of_a_batch():
    import torch

    from tofdenoise.visualize import batch_plane

    maps = torch.arange(2 * 1 * 2 * 3, dtype=torch.float64).reshape(2, 1, 2, 3)
    out = batch_plane(maps, 1)
    assert out.dtype == np.float32 and out.shape == (2, 3)
    np.testing.assert_array_equal(out, np.arange(6, 12, dtype=np.float32).reshape(2, 3))
    np.testing.assert_array_equal(batch_plane(maps[:, 0].numpy(), 0), out - 6)
    with pytest.raises(ValueError, match="sigma"):
        batch_plane(torch.zeros(2, 3, 4, 4), 0, name="sigma")
