"""Tiled inference: exact for small receptive fields, seam-free on a real backbone."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from tofdenoise.models import build_backbone, tiled_forward
from tofdenoise.models.tiling import blend_window_1d, tile_starts


def test_tile_starts_cover_the_image():
    assert tile_starts(100, 40, 16) == [0, 24, 48, 60]
    assert tile_starts(30, 40, 16) == [0]
    for size in (41, 97, 256, 257):
        starts = tile_starts(size, 40, 10)
        assert starts[0] == 0 and starts[-1] + 40 == size
        assert all(b - a <= 30 for a, b in zip(starts, starts[1:]))


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
