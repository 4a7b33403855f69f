"""The restore path adds no structure of its own (issue 42): no 16-pixel grid, no depth edge at hole borders.

The restored depth is ``offset + depth_scale_mm x net((filled - offset) / depth_scale_mm)``. Whatever the network
does to its input, the fill and the offset decide what it is given. These tests run the whole path of
``tofdenoise denoise`` (``restore_frame``: fill, centring, tiles, offset added back, holes masked) with a network
that smooths its input the same way at every pixel (a Gaussian of sigma 1.5 px, as a trained denoiser does to
first order on a smooth surface): any structure tied to the pixel grid or to the holes comes from the path.

- **Grid.** The block offset (``centering="local"``) is piecewise linear with kinks on its block centres
  (7.5 mod 16), so on a curved surface the network is given cusps on a 16-pixel grid and smooths them: the
  change at rows and columns 7-8 mod 16 stands out. On the bowl below it did by 10-12 standard errors of a class
  mean (3 seeds); the Gaussian offset (``centering="gaussian"``, the default) leaves 1.8-2.5, what 32 class means
  of a change without period-16 structure give (the largest of 32 normal deviations exceeds 3 in about 8 % of
  frames, 4 in 0.2 %): the test asks for less than 4.
- **Hole borders.** The pull-push fill (``fill="pullpush"``) is off by about one pixel's worth of slope at a
  hole's border: on a floor seen at a grazing angle (5 mm/px) with the noise of a camera like the Kinect (the
  default calibration's sigma_D x 0.3: the change far from holes is 0.7 mm, as on the Kinect frame of issue 42),
  pixels next to holes changed 1.6-1.9x as much as pixels far from them (6 seeds). The harmonic fill (the
  default) is continuous with the valid pixels: 0.8-1.1x. The test asks for at most 1.5x, the issue's bound.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import nn

from tofdenoise.data_modules.holes import blob_holes
from tofdenoise.inference.denoise import restore_frame
from tofdenoise.physics.calibration import default_calibration
from tofdenoise.physics.uncertainty import sigma_depth_mm
from tofdenoise.training.module import DepthRestorer

H, W = 192, 224
#: frame margin left out of the statistics (the offset and the fill are one-sided there)
MARGIN_PX = 16


class SmoothingNet(nn.Module):
    """A shift-invariant denoiser: a Gaussian of ``sigma_px`` over the (centred) depth channel, reflect padding."""

    def __init__(self, sigma_px: float = 1.5) -> None:
        super().__init__()
        self.radius = math.ceil(3 * sigma_px)
        taps = torch.arange(-self.radius, self.radius + 1, dtype=torch.float32)
        kernel = torch.exp(-0.5 * (taps / sigma_px) ** 2)
        self.register_buffer("kernel", kernel / kernel.sum())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r, k = self.radius, self.kernel
        x = F.conv2d(F.pad(x[:, :1], (r, r, 0, 0), mode="reflect"), k.view(1, 1, 1, -1))
        return F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), k.view(1, 1, -1, 1))


def restorer(centering: str | None = None, fill: str | None = None) -> DepthRestorer:
    """A DepthRestorer (today's defaults unless given) whose network is :class:`SmoothingNet`."""
    conditioning = {k: v for k, v in (("centering", centering), ("fill", fill)) if v is not None}
    model = DepthRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 1}, conditioning=conditioning)
    model.backbone = SmoothingNet()
    return model.eval()


def with_camera_noise(depth_mm: np.ndarray, seed: int, noise_scale: float = 1.0) -> np.ndarray:
    """``depth_mm`` plus the hetero noise of the default calibration (a grey surface, reflectance 0.8, frontal)."""
    calib = default_calibration()
    signal_e = calib.signal_at_1m_e * 0.8 * (1000.0 / depth_mm) ** 2
    sigma = np.asarray(sigma_depth_mm(depth_mm.astype(np.float32), signal_e.astype(np.float32), calib), np.float64)
    return depth_mm + noise_scale * sigma * np.random.default_rng(seed).standard_normal(depth_mm.shape)


def period16_deviation(change: np.ndarray) -> float:
    """The largest deviation of a row or column class mean (index mod 16) of ``change`` from its overall mean, in
    standard errors of a class mean (frame margin left out)."""
    inner = change[MARGIN_PX:-MARGIN_PX, MARGIN_PX:-MARGIN_PX]
    rows = [inner[r::16].mean() for r in range(16)]
    cols = [inner[:, c::16].mean() for c in range(16)]
    standard_error = inner.std() / math.sqrt(inner.size / 16)
    return float(np.max(np.abs(np.r_[rows, cols] - inner.mean())) / standard_error)


def bowl_mm() -> np.ndarray:
    """A smooth curved surface: a tilted bowl of curvature 0.1 mm/px^2, 0.9-2.1 m."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return 800.0 + 1.0 * xx + 0.05 * ((xx - 112.0) ** 2 + (yy - 96.0) ** 2)


@pytest.mark.parametrize("tile", [None, 96])
def test_the_restored_change_of_a_smooth_frame_has_no_period_16_component(tile):
    model = restorer()
    clean = bowl_mm()
    valid = np.ones((H, W), dtype=bool)
    for seed in (0, 1):
        noisy = with_camera_noise(clean, seed).astype(np.float32)
        restored = restore_frame(model, noisy, valid, tile=tile, precision="fp32")
        assert period16_deviation(restored - noisy) < 4.0


def test_the_block_offset_of_older_checkpoints_shows_the_grid():
    """The same measurement sees the grid where it is: the block offset (checkpoints before 2026-11-27)."""
    noisy = with_camera_noise(bowl_mm(), 0).astype(np.float32)
    restored = restore_frame(restorer("local", "pullpush"), noisy, np.ones((H, W), bool), precision="fp32")
    assert period16_deviation(restored - noisy) > 6.0


def floor_with_holes(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A floor seen at a grazing angle (5 mm/px down the frame, 1 mm/px across; 0.8-1.9 m) with the project's
    dropout blobs (radius 5-20 px), Kinect-like noise; returns (depth mm with 0 at holes, valid)."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    noisy = with_camera_noise(800.0 + 5.0 * yy + 1.0 * xx, seed, noise_scale=0.3)
    holes = blob_holes((H, W), 3.0, (5.0, 20.0), torch.Generator().manual_seed(seed)).numpy()
    return np.where(holes, 0.0, noisy).astype(np.float32), ~holes


def near_far_change_ratio(noisy: np.ndarray, valid: np.ndarray, restored: np.ndarray) -> float:
    """Mean |change| of the valid pixels next to a hole (8-neighbours) over that of the valid pixels more than
    8 px from any hole (frame margin of 8 px left out of both)."""
    change = np.abs(restored - noisy)
    distance = ndimage.distance_transform_edt(valid)
    inner = np.zeros_like(valid)
    inner[8:-8, 8:-8] = True
    near = valid & inner & (distance <= 1.5)
    far = valid & inner & (distance > 8)
    return float(change[near].mean() / change[far].mean())


@pytest.mark.parametrize("seed", [0, 3])
def test_pixels_next_to_holes_change_no_more_than_pixels_far_from_them(seed):
    noisy, valid = floor_with_holes(seed)
    model = restorer()
    restored = restore_frame(model, noisy, valid, precision="fp32")
    assert near_far_change_ratio(noisy, valid, restored) <= 1.5
    # holes stay holes: no depth is invented inside them
    assert np.all(restored[~valid] == 0.0)
    # and with fill_holes the fill continues the floor (within 3 sigma of the noise at its depth, ~10 mm)
    filled = restore_frame(model, noisy, valid, fill_holes=True, precision="fp32")
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    floor = 800.0 + 5.0 * yy + 1.0 * xx
    inner_holes = ~valid
    inner_holes[:MARGIN_PX] = inner_holes[-MARGIN_PX:] = False
    inner_holes[:, :MARGIN_PX] = inner_holes[:, -MARGIN_PX:] = False
    assert np.median(np.abs(filled - floor)[inner_holes]) < 10.0


def test_the_pull_push_fill_of_older_checkpoints_shows_the_border_change():
    noisy, valid = floor_with_holes(3)
    restored = restore_frame(restorer("local", "pullpush"), noisy, valid, precision="fp32")
    assert near_far_change_ratio(noisy, valid, restored) > 1.5
