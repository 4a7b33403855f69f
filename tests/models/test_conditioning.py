"""Network-input conditioning: hole filling (pull-push), local offset, bf16 resolution of the centred input."""

from __future__ import annotations

import math

import pytest
import torch

from tofdenoise.models.conditioning import (
    RELAX_ITERS,
    InputConditioning,
    bf16_step_mm,
    fill_invalid_mm,
    gaussian_offset_mm,
    image_offset_mm,
    local_offset_mm,
    valid_input_mask,
)


def b1hw(x):
    return torch.as_tensor(x, dtype=torch.float32)[None, None]


def test_valid_input_mask_treats_zero_negative_nan_inf_as_holes():
    d = b1hw([[1000.0, 0.0, -5.0], [math.nan, math.inf, 1.0]])
    assert valid_input_mask(d)[0, 0].tolist() == [[True, False, False], [False, False, True]]


def test_fill_hand_computed_2x2():
    # one hole in a 2x2 image: level 1 is the mean of the three valid values, pushed back into the hole
    d = b1hw([[100.0, 0.0], [200.0, 300.0]])
    out = fill_invalid_mm(d)
    assert out[0, 0].tolist() == [[100.0, 200.0], [200.0, 300.0]]


def test_fill_keeps_valid_pixels_and_fills_every_hole():
    g = torch.Generator().manual_seed(0)
    d = 1000.0 + 10.0 * torch.randn(2, 1, 37, 53, generator=g)
    holes = torch.rand(d.shape, generator=g) < 0.3
    holes[0, 0, 5:20, 10:30] = True  # a large blob
    noisy = torch.where(holes, torch.zeros_like(d), d)
    noisy[1, 0, 0, 0] = math.nan
    out = fill_invalid_mm(noisy)
    valid = valid_input_mask(noisy)
    assert torch.equal(out[valid], noisy[valid])
    assert torch.isfinite(out).all() and (out > 900).all() and (out < 1100).all()


def test_fill_reproduces_constant_and_is_close_on_a_plane():
    holes = torch.zeros(1, 1, 40, 64, dtype=torch.bool)
    holes[..., 8:24, 20:44] = True
    const = torch.full(holes.shape, 1234.5)
    torch.testing.assert_close(fill_invalid_mm(torch.where(holes, 0.0, const)), const, rtol=1e-6, atol=0)
    yy, xx = torch.meshgrid(torch.arange(40.0), torch.arange(64.0), indexing="ij")
    plane = (800.0 + 2.0 * xx + 1.0 * yy)[None, None]
    filled = fill_invalid_mm(torch.where(holes, 0.0, plane))
    # a smooth surface continuing the plane: within a few slopes of the truth inside a 16 x 24 hole
    assert (filled - plane).abs().max() < 20.0


def test_fill_all_invalid_image_gives_zeros_not_nan():
    out = fill_invalid_mm(torch.zeros(1, 1, 9, 7))
    assert torch.equal(out, torch.zeros(1, 1, 9, 7))


def test_local_offset_reproduces_a_plane_away_from_border_blocks():
    yy, xx = torch.meshgrid(torch.arange(64.0), torch.arange(96.0), indexing="ij")
    plane = (1500.0 + 3.0 * xx - 2.0 * yy)[None, None]
    off = local_offset_mm(plane, 16)
    inner = (slice(None), slice(None), slice(8, 56), slice(8, 88))
    torch.testing.assert_close(off[inner], plane[inner], rtol=0, atol=1e-3)
    # constant images of any size (partial edge blocks) are reproduced everywhere
    const = torch.full((1, 1, 37, 41), 3210.0)
    torch.testing.assert_close(local_offset_mm(const, 16), const)


def test_image_offset_is_valid_median():
    d = b1hw([[1.0, 2.0, 100.0], [0.0, 0.0, 0.0]])
    assert image_offset_mm(d, valid_input_mask(d)).item() == 2.0


def test_bf16_step_formula():
    # 1 m / 1000 = 1.0 -> spacing 2^-7 -> 7.8125 mm; 100 mm -> 0.1 in [2^-4, 2^-3) -> 2^-11 -> 0.488 mm
    assert bf16_step_mm(1000.0, 1000.0).item() == pytest.approx(7.8125)
    assert bf16_step_mm(100.0, 1000.0).item() == pytest.approx(1000 * 2.0**-11)
    x = torch.tensor(1.0 + 2.0**-8)  # halfway between two bf16 numbers near 1: rounds off by 2^-8
    assert (x.to(torch.bfloat16).float() - x).abs().item() == pytest.approx(2.0**-8)


@pytest.mark.parametrize("depth_mm", [300.0, 1000.0, 1500.0, 2500.0, 4000.0])
@pytest.mark.parametrize("slope_mm_per_px", [0.0, 4.0])
def test_centred_input_resolves_half_a_millimetre_in_bf16(depth_mm, slope_mm_per_px):
    """Issue item 7: the network input's bf16 quantisation step is below 0.5 mm at every depth up to 4 m
    (smooth surfaces with 12 mm noise, holes included); raw depth / 1000 has a step of 2-16 mm there."""
    from tofdenoise.training.module import DepthRestorer

    g = torch.Generator().manual_seed(int(depth_mm))
    yy, xx = torch.meshgrid(torch.arange(96.0), torch.arange(128.0), indexing="ij")
    clean = depth_mm + slope_mm_per_px * (xx - 64.0)
    noisy = (clean + 12.0 * torch.randn(clean.shape, generator=g))[None, None]
    noisy[..., 40:50, 60:75] = 0.0
    model = DepthRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 2})
    x, offset = model.condition({"noisy": noisy, "mask": torch.ones_like(noisy)})
    err_mm = (x[:, :1].to(torch.bfloat16).float() - x[:, :1]).abs() * model.conditioning.depth_scale_mm
    assert err_mm.max().item() <= 0.25  # rounding error <= half the step: step <= 0.5 mm
    raw = DepthRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 2}, conditioning={"centering": "none"})
    x_raw, _ = raw.condition({"noisy": noisy, "mask": torch.ones_like(noisy)})
    raw_err = (x_raw.to(torch.bfloat16).float() - x_raw).abs() * raw.conditioning.depth_scale_mm
    if depth_mm >= 600:
        assert raw_err.max().item() > 1.0  # what the issue measured: the raw input is rounded to mm steps


def test_fill_works_on_a_single_row_and_column():
    row = b1hw([[0.0, 100.0, 0.0, 0.0, 300.0, 0.0, 0.0]])
    out = fill_invalid_mm(row)
    assert (out > 0).all() and out[0, 0, 0, 1] == 100.0 and out[0, 0, 0, 4] == 300.0
    col = row.transpose(2, 3)
    torch.testing.assert_close(fill_invalid_mm(col).transpose(2, 3), out)


@pytest.mark.parametrize("size", [(37, 53), (64, 64), (1, 7), (96, 130)])
def test_fixed_level_fill_of_the_export_equals_the_early_stopping_fill(size):
    """fill_invalid_mm(levels=16) (the ONNX graph: no data-dependent branch) gives the same values."""
    gen = torch.Generator().manual_seed(0)
    depth = 300.0 + 1000.0 * torch.rand(2, 1, *size, generator=gen)
    depth[torch.rand(depth.shape, generator=gen) < 0.3] = 0.0
    depth[1, :, : size[0] // 2] = float("nan")  # a large hole: many levels needed
    assert torch.equal(fill_invalid_mm(depth), fill_invalid_mm(depth, levels=16))
    assert torch.equal(fill_invalid_mm(torch.zeros(1, 1, 5, 6), levels=4), torch.zeros(1, 1, 5, 6))


def _sloped_plane_with_holes():
    yy, xx = torch.meshgrid(torch.arange(96.0), torch.arange(128.0), indexing="ij")
    plane = (800.0 + 5.0 * yy + 1.0 * xx)[None, None]  # a floor at a grazing angle: 5 mm/px
    holes = torch.zeros_like(plane, dtype=torch.bool)
    for cy, cx, r in ((30, 30, 5), (40, 90, 14), (70, 50, 20)):
        holes |= ((yy - cy) ** 2 + (xx - cx) ** 2 < r * r)[None, None]
    return plane, holes


def test_harmonic_fill_continues_a_sloped_plane_where_pull_push_leaves_a_step():
    """Issue 42: a partial block's mean sits at the centroid of its valid pixels, so pull-push is off by about one
    pixel's worth of slope at a hole's border (a step the network reads as a depth edge); the harmonic fill meets
    the valid pixels without a step and continues the plane."""
    plane, holes = _sloped_plane_with_holes()
    depth = torch.where(holes, 0.0, plane)
    ring = holes & (torch.nn.functional.max_pool2d((~holes).float(), 3, 1, 1) > 0)  # holes next to a valid pixel
    pull_push = fill_invalid_mm(depth)
    harmonic = fill_invalid_mm(depth, relax_iters=RELAX_ITERS)
    assert torch.equal(harmonic[~holes], plane[~holes])
    assert (pull_push - plane)[ring].abs().mean() > 2.0
    assert (harmonic - plane)[ring].abs().max() < 0.2
    assert (harmonic - plane)[holes].abs().max() < 1.0  # 20 px inside the largest hole (pull-push: 20+ mm off)
    assert (pull_push - plane)[holes].abs().max() > 10.0


@pytest.mark.parametrize("size", [(37, 53), (64, 64), (1, 7), (96, 130)])
def test_fixed_level_harmonic_fill_equals_the_early_stopping_fill(size):
    """The harmonic fill with the export's fixed levels gives the same values as the early-stopping one."""
    gen = torch.Generator().manual_seed(1)
    depth = 300.0 + 1000.0 * torch.rand(2, 1, *size, generator=gen)
    depth[torch.rand(depth.shape, generator=gen) < 0.3] = 0.0
    depth[1, :, : size[0] // 2] = float("nan")
    a = fill_invalid_mm(depth, relax_iters=RELAX_ITERS)
    b = fill_invalid_mm(depth, levels=16, relax_iters=RELAX_ITERS)
    torch.testing.assert_close(a, b, rtol=0, atol=1e-3)


def test_gaussian_offset_reproduces_a_plane_and_leaves_no_grid_on_a_curved_surface():
    yy, xx = torch.meshgrid(torch.arange(96.0), torch.arange(128.0), indexing="ij")
    plane = (1500.0 + 3.0 * xx - 2.0 * yy)[None, None]
    inner = (slice(None), slice(None), slice(24, 72), slice(24, 104))  # 3 sigma from the border
    torch.testing.assert_close(gaussian_offset_mm(plane, 16)[inner], plane[inner], rtol=0, atol=1e-2)
    const = torch.full((1, 1, 37, 41), 3210.0)
    torch.testing.assert_close(gaussian_offset_mm(const, 16), const, rtol=0, atol=1e-2)
    # a paraboloid: the centred depth is a constant (minus curvature x sigma^2) under the Gaussian offset, a
    # 16-pixel pattern under the block offset (kinks on the block centres, 7.5 mod 16)
    bowl = (1000.0 + 0.05 * ((xx - 64.0) ** 2 + (yy - 48.0) ** 2))[None, None]
    smooth = (bowl - gaussian_offset_mm(bowl, 16))[inner]
    blocks = (bowl - local_offset_mm(bowl, 16))[inner]
    assert smooth.max() - smooth.min() < 0.05
    assert blocks.max() - blocks.min() > 1.0


def test_conditioning_defaults_and_refusals():
    c = InputConditioning()
    assert (c.centering, c.fill) == ("gaussian", "harmonic")
    with pytest.raises(ValueError, match="conditioning.fill: unknown mode 'zero'"):
        InputConditioning(fill="zero")
