"""Tiled inference: exact for small receptive fields, seam-free on a real backbone."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from tofdenoise.models import build_backbone, tiled_forward
from tofdenoise.models.common import crop_to, pad_to_multiple
from tofdenoise.models.tiling import blend_window_1d, min_tile_px, model_multiple, tile_starts


def test_tile_starts_cover_the_image():
    assert tile_starts(100, 40, 16) == [0, 24, 48, 60]
    assert tile_starts(30, 40, 16) == [0]
    for size in (41, 97, 256, 257):
        starts = tile_starts(size, 40, 10)
        assert starts[0] == 0 and starts[-1] + 40 == size
        assert all(b - a <= 30 for a, b in zip(starts, starts[1:]))


def test_tile_starts_on_a_multiple():
    # stride (48 - 16) rounded down to 16 = 32; the last tile ends at the (padded) border
    assert tile_starts(112, 48, 16, 16) == [0, 32, 64]
    assert tile_starts(176, 64, 20, 16) == [0, 32, 64, 96, 112]  # stride 44 -> 32
    for size, tile, overlap, m in ((488, 128, 32, 8), (656, 128, 32, 16), (168, 64, 0, 8)):
        starts = tile_starts(size, tile, overlap, m)
        assert all(s % m == 0 for s in starts) and starts[0] == 0 and starts[-1] + tile == size
        assert all(tile - (b - a) >= overlap for a, b in zip(starts, starts[1:]))
    with pytest.raises(ValueError, match="multiples of multiple=8"):
        tile_starts(97, 64, 16, 8)
    with pytest.raises(ValueError, match="at least 48 px"):
        tile_starts(128, 32, 32, 16)
    assert min_tile_px(32, 16) == 48 and min_tile_px(32, 8) == 40 and min_tile_px(30, 16) == 48
    assert min_tile_px(0, 1) == 1 and min_tile_px(32) == 33


class _BlockNet(nn.Module):
    """Pads to a multiple of 8 as the backbones do, then mixes each 8 x 8 block (a stride-8 pooling grid) with a
    pixel-wise term: every output pixel depends on its block only, so tiles on the grid give the whole-frame result
    exactly, whatever the overlap; a tile off the grid, or a border tile padded on its own, does not."""

    multiple = 8

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xp, size = pad_to_multiple(x, self.multiple)
        block = nn.functional.interpolate(nn.functional.avg_pool2d(xp, 8), scale_factor=8, mode="nearest")
        return crop_to(torch.tanh(3 * block) + 0.5 * xp, size)


@pytest.mark.parametrize(
    "h, w, tile, overlap", [(97, 161, 64, 16), (97, 161, 64, 0), (81, 119, 48, 16), (130, 75, 56, 8), (97, 161, 60, 0)]
)
def test_tiled_equals_whole_exactly_on_the_padding_grid_at_odd_sizes(h, w, tile, overlap):
    torch.manual_seed(0)
    net = _BlockNet()
    x = torch.randn(2, 1, h, w)
    with torch.no_grad():
        whole = net(x)
    assert model_multiple(net) == 8
    tiled = tiled_forward(net, x, tile=tile, overlap=overlap, tile_batch=2)
    assert tiled.shape == whole.shape
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)
    # Tiles cut from the unpadded frame at size - tile (the placement before 2026-11-29) are off the grid: wrong by
    # a visible amount, so this test fails on that placement.
    off_grid = tiled_forward(net, x, tile=tile, overlap=overlap, multiple=1)
    assert (off_grid - whole).abs().max() > 0.1


def _smooth_frame(h: int, w: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(1)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    return (torch.sin(6 * xx) + torch.cos(4 * yy) + 0.1 * torch.randn(h, w, generator=g))[None, None]


def _random_head(name: str) -> nn.Module:
    torch.manual_seed(0)
    kwargs = {"unet": dict(width=4, stages=4), "dvss": dict(width=8, enc_blocks=[1, 1], bottleneck_blocks=1, d_state=4)}
    model = build_backbone(name, **kwargs[name]).eval()
    with torch.no_grad():
        model.head.weight.normal_(0, 0.5)
    return model


# max and mean of |tiled - whole| as fractions of the max and mean of |whole - x|. Measured at the sizes below:
# U-Net <= 0.0007 / 0.00005, DVSS 0.011-0.026 / 0.011-0.024 (its aligned control, 96 x 160: 0.018 / 0.018); the
# placement before 2026-11-29 (border tiles at size - tile, not padded): U-Net 0.63-0.66 / 0.028-0.037, DVSS 0.76-0.78 /
# 0.33-0.47.
ODD_SIZE_TOLERANCE = {"unet": (0.005, 0.001), "dvss": (0.05, 0.05)}


@pytest.mark.parametrize("name", ["unet", "dvss"])
@pytest.mark.parametrize("h, w, tile, overlap", [(97, 161, 64, 32), (81, 119, 48, 16), (97, 161, 80, 32)])
def test_tiled_backbone_is_close_to_whole_at_odd_sizes(name, h, w, tile, overlap):
    """H != W, sizes off the padding multiple (16 for this U-Net, 4 for this DVSS), tiles not dividing the size."""
    model = _random_head(name)
    x = _smooth_frame(h, w)
    with torch.no_grad():
        whole = model(x)
    residual = (whole - x).abs()
    max_tol, mean_tol = ODD_SIZE_TOLERANCE[name]

    def within(tiled: torch.Tensor) -> bool:
        err = (tiled - whole).abs()
        return bool(err.max() < max_tol * residual.max() and err.mean() < mean_tol * residual.mean())

    assert within(tiled_forward(model, x, tile=tile, overlap=overlap))
    assert not within(tiled_forward(model, x, tile=tile, overlap=overlap, multiple=1))  # the old placement fails


def test_restore_mm_tiles_on_the_backbone_multiple():
    """``DepthRestorer.restore_mm`` (validation/test with ``tiling.eval_tile_px``, ``denoise --tile``, tiles for
    memory) passes the network's multiple: at an odd size the tiled restore equals the whole one to 0.01 mm (measured
    0.0006 mm; tiles at size - tile, the placement before 2026-11-29: 7.35 mm)."""
    from tofdenoise.training.module import DepthRestorer

    torch.manual_seed(0)
    model = DepthRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 4}).eval()
    with torch.no_grad():
        model.backbone.head.weight.normal_(0, 5)
    depth = 1500 + 300 * _smooth_frame(97, 161)
    batch = {"noisy": depth, "mask": torch.ones_like(depth)}
    with torch.no_grad():
        whole = model.restore_mm(batch)
        tiled = model.restore_mm(batch, tile=64)
    assert (whole - depth).abs().max() > 20  # the network changes the frame by up to 23 mm
    assert (tiled - whole).abs().max() < 0.01


def test_blend_windows_are_a_partition_of_unity():
    tile, overlap, margin = 40, 16, 4
    left = blend_window_1d(tile, overlap, margin, False, True)
    right = blend_window_1d(tile, overlap, margin, True, False)
    stride = tile - overlap
    total = torch.zeros(tile + stride, dtype=torch.float64)
    total[:tile] += left.double()
    total[stride:] += right.double()
    torch.testing.assert_close(total, torch.ones_like(total), rtol=0, atol=1e-6)
    assert left[-margin:].abs().max() == 0 and right[:margin].abs().max() == 0
    # smooth: no jump larger than the raised-cosine's steepest step
    assert (left[1:] - left[:-1]).abs().max() < math.pi / (2 * (overlap - 2 * margin)) + 1e-6


def test_tiled_equals_whole_for_small_receptive_field():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Conv2d(2, 6, 3, padding=1), nn.GELU(), nn.Conv2d(6, 1, 5, padding=2))  # radius 3
    x = torch.randn(2, 2, 97, 131)
    with torch.no_grad():
        whole = net(x)
    tiled = tiled_forward(net, x, tile=48, overlap=16, tile_batch=3)  # margin 4 >= radius 3
    torch.testing.assert_close(tiled, whole, rtol=1e-5, atol=1e-5)
    # A margin smaller than the receptive field is visibly wrong near seams: the test can fail.
    bad = tiled_forward(net, x, tile=48, overlap=16, margin=0)
    assert (bad - whole).abs().max() > 1e-3


def test_tiled_unet_is_seam_free_and_close_to_whole():
    torch.manual_seed(0)
    model = build_backbone("unet", width=4, stages=2).eval()
    with torch.no_grad():
        model.head.weight.normal_(0, 0.5)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 96), torch.linspace(0, 1, 160), indexing="ij")
    x = (torch.sin(6 * xx) + torch.cos(4 * yy) + 0.1 * torch.randn(96, 160))[None, None]
    with torch.no_grad():
        whole = model(x)
    tiled = tiled_forward(model, x, tile=64, overlap=32)
    residual = whole - x
    err = (tiled - whole).abs()
    assert err.max() < 0.05 * residual.abs().max()
    assert err.mean() < 0.01 * residual.abs().mean() + 1e-6


def test_tiling_rejects_bad_arguments():
    net = nn.Identity()
    x = torch.zeros(1, 1, 300, 300)
    with pytest.raises(ValueError, match="overlap < tile"):
        tiled_forward(net, x, tile=32, overlap=32)
    with pytest.raises(ValueError, match="2 \\* margin < overlap"):
        tiled_forward(net, x, tile=64, overlap=16, margin=8)
    with pytest.raises(ValueError, match="B, C, H, W"):
        tiled_forward(net, torch.zeros(300, 300))
    with pytest.raises(ValueError, match="multiple of 16 px; use a tile of at least 48 px"):
        tiled_forward(net, x, tile=40, overlap=32, multiple=16)
