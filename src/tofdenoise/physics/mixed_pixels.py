"""Mixed pixels: a pixel whose footprint sees several surfaces integrates all their returns.

At a depth discontinuity the light reaching one pixel comes from two (or more) surfaces. Every tap integrates
the sum of the returns, so the expected photo-electrons of tap n are (paper Eq. 3-4, summed over surfaces k)

    lambda_n = sum_k w_k a_k c(psi(D_k) - theta_n),     sum_k w_k = 1,

with w_k the share of the footprint that sees surface k, a_k its returned signal [e-] and psi(D_k) its phase.
The camera demodulates this sum as if it came from one surface, so the decoded depth lies between the
surfaces (a "flying pixel") and the amplitude drops: for a sinusoidal c (c0 + c1 cos x) the first DFT bin is
proportional to sum_k w_k a_k exp(i psi_k), e.g. two surfaces of equal signal and weight give the circular
mean phase (psi_1 + psi_2) / 2 and amplitude |cos((psi_2 - psi_1) / 2)| times that of one surface.

The WLS noise model (and the training synthesis) has one surface per pixel: mixed pixels are what a real
camera adds at every depth edge. ``footprint_tap_means_e`` renders them from a scene sampled on a finer grid
(``factor`` x ``factor`` sub-pixels per pixel, each an equal share of the footprint); the capture simulator
(``tofdenoise.physics.simulator.simulate_tap_mean_frames``) turns the mixed tap means into noisy frames.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.physics.fixed_pattern import camera_pattern, column_phase_depth_mm
from tofdenoise.physics.uncertainty import tap_responses


def mixed_tap_means_e(depth_mm: Any, signal_e: Any, weights: Any, calib: SensorCalibration) -> torch.Tensor:
    """Expected signal photo-electrons per tap (N, ...) of pixels that see K surfaces.

    depth_mm, signal_e, weights: (K, ...) with the surfaces on axis 0 (numpy or torch); weights are the
    footprint shares (each pixel's weights should sum to 1). A surface with an invalid depth or signal
    (not finite, <= 0) returns nothing (it contributes 0, e.g. a sub-pixel that sees no surface).
    Returns lambda_n = sum_k w_k a_k c(psi(D_k) - theta_n) as float32, the dark offset excluded.
    """
    d = torch.as_tensor(depth_mm, dtype=torch.float32)
    a = torch.as_tensor(signal_e, dtype=torch.float32)
    w = torch.as_tensor(weights, dtype=torch.float32)
    if d.shape != a.shape or d.shape != w.shape or d.ndim < 1:
        raise ValueError(
            f"depth_mm {tuple(d.shape)}, signal_e {tuple(a.shape)} and weights {tuple(w.shape)} must "
            "have the same shape (K, ...) with the surfaces on axis 0"
        )
    ok = torch.isfinite(d) & torch.isfinite(a) & (d > 0) & (a > 0) & torch.isfinite(w)
    r, _ = tap_responses(torch.where(ok, d, torch.ones_like(d)), calib)  # (K, ..., N)
    share = torch.where(ok, a * w, torch.zeros_like(a))
    return (share.unsqueeze(-1) * r).sum(dim=0).movedim(-1, 0).contiguous()


def footprint_tap_means_e(depth_mm: Any, signal_e: Any, calib: SensorCalibration, factor: int) -> torch.Tensor:
    """Tap means (N, H, W) of pixels whose footprint is ``factor`` x ``factor`` samples of a finer grid.

    depth_mm, signal_e: (factor H, factor W) samples (e.g. a scene ray-cast at ``factor`` times the
    resolution); pixel (i, j) integrates samples [factor i, factor (i + 1)) x [factor j, factor (j + 1)), each
    with weight 1 / factor^2 (``mixed_tap_means_e``). factor = 1 is the one-surface model. A camera with a
    fixed pattern (``calib.fixed_pattern``) gets its column phase offsets here; its PRNU and tap offsets are added
    by ``simulate_tap_mean_frames``.
    """
    d = torch.as_tensor(depth_mm, dtype=torch.float32)
    a = torch.as_tensor(signal_e, dtype=torch.float32)
    s = int(factor)
    if s != factor or s < 1:
        raise ValueError(f"factor must be a positive integer, got {factor!r}")
    if d.ndim != 2 or d.shape != a.shape or d.shape[0] % s or d.shape[1] % s:
        raise ValueError(
            f"depth_mm {tuple(d.shape)} and signal_e {tuple(a.shape)} must be one (H, W) grid with "
            f"sides divisible by factor {s}"
        )
    h, w = d.shape[0] // s, d.shape[1] // s

    pattern = camera_pattern(calib, h, w)
    if pattern is not None:  # the camera's column phase offsets (its fixed pattern) shift psi of every sub-pixel
        shift = torch.from_numpy(column_phase_depth_mm(pattern, calib, s))
        d = torch.where(torch.isfinite(d) & (d > 0), d + shift, d)

    def surfaces(x: torch.Tensor) -> torch.Tensor:  # (sH, sW) -> (s*s, H, W): the samples of each footprint
        return x.reshape(h, s, w, s).permute(1, 3, 0, 2).reshape(s * s, h, w)

    weights = torch.full((s * s, h, w), 1.0 / (s * s), dtype=torch.float32)
    return mixed_tap_means_e(surfaces(d), surfaces(a), weights, calib)


def mixed_pixel_map(depth_mm: Any, factor: int, rel_jump: float = 0.05) -> np.ndarray:
    """Boolean (H, W) map of the pixels whose ``factor`` x ``factor`` samples span a depth jump larger than
    ``rel_jump`` x their nearest depth (or mix valid and invalid samples): where mixing changes the pixel."""
    d = np.asarray(depth_mm, dtype=np.float64)
    s = int(factor)
    h, w = d.shape[0] // s, d.shape[1] // s
    blocks = d[: h * s, : w * s].reshape(h, s, w, s).transpose(0, 2, 1, 3).reshape(h, w, s * s)
    ok = np.isfinite(blocks) & (blocks > 0)
    lo = np.where(ok, blocks, np.inf).min(axis=-1)
    hi = np.where(ok, blocks, -np.inf).max(axis=-1)
    with np.errstate(invalid="ignore"):
        return (ok.any(axis=-1) & ~ok.all(axis=-1)) | (ok.all(axis=-1) & (hi - lo > rel_jump * lo))


__all__ = ["footprint_tap_means_e", "mixed_pixel_map", "mixed_tap_means_e"]
