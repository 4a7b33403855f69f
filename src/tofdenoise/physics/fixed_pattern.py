"""Fixed-pattern noise of a simulated camera: per-pixel tap offsets, column phase offsets and PRNU.

The paper's WLS model (Sec. III-A) assumes "systematic phase nonlinearity and fixed-pattern bias are compensated
by the device-level calibration", and the training synthesis follows it. A real camera keeps a residual of them:
on a flat wall at 0.46 m a pmd pico flexx (80 MHz) shows a column-structured phase residual of ~0.016 rad
(~4.6 mm) that hardly changes with amplitude (shared/notes/real-cameras.md). The capture simulator adds three
terms, drawn once per camera (``FixedPatternNoise.seed``) and frame size, and the same in every frame:

- tap offset  o_n(p) ~ N(0, pixel_offset_e^2) [e-] added to tap n (dark-signal non-uniformity per tap). It does
  not cancel in the N-phase demodulation: its depth error ~ |O_1(p)| / (a |C1|) falls as 1 / signal, so the
  standard-exposure input and the high-exposure reference see it differently;
- column phase  delta(u) ~ N(0, column_phase_rad^2) [rad]: tap n of column u integrates
  c(psi(D) + delta(u) - theta_n), a depth offset delta / (4 pi f / c) that does not change with signal or exposure
  (it is in the reference too: what it tests is whether a denoiser keeps or smears the stripes);
- PRNU  g(p) = 1 + N(0, prnu^2) multiplies the returned signal of every tap of pixel p (the amplitude only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tofdenoise.physics.calibration import FixedPatternNoise, SensorCalibration


@dataclass(frozen=True)
class FixedPatternMaps:
    """One camera's pattern for one frame size: tap_offset_e (N, H, W), column_phase_rad (W,), gain (H, W)."""

    tap_offset_e: np.ndarray
    column_phase_rad: np.ndarray
    gain: np.ndarray


def fixed_pattern_maps(fpn: FixedPatternNoise, height: int, width: int, num_taps: int) -> FixedPatternMaps:
    """Draw the pattern of camera ``fpn`` for an (H, W) frame: the same arguments always give the same maps."""
    rng = np.random.default_rng([int(fpn.seed), int(height), int(width), int(num_taps)])
    offsets = rng.standard_normal((num_taps, height, width)) * fpn.pixel_offset_e
    columns = rng.standard_normal(width) * fpn.column_phase_rad
    gain = np.clip(1.0 + rng.standard_normal((height, width)) * fpn.prnu, 0.0, None)
    return FixedPatternMaps(offsets.astype(np.float32), columns.astype(np.float64), gain.astype(np.float32))


def camera_pattern(calib: SensorCalibration, height: int, width: int) -> FixedPatternMaps | None:
    """The calibration's fixed pattern for an (H, W) frame, or None when it has none (or an all-zero one)."""
    fpn = getattr(calib, "fixed_pattern", None)
    if fpn is None or fpn.is_zero:
        return None
    return fixed_pattern_maps(fpn, height, width, calib.num_taps)


def column_phase_depth_mm(maps: FixedPatternMaps, calib: SensorCalibration, factor: int = 1) -> np.ndarray:
    """The column phase as a depth shift delta(u) / (4 pi f / c) [mm], (1, W * factor): each of the ``factor``
    sub-columns of a column shares its offset (a supersampled scene, ``tofdenoise.physics.mixed_pixels``)."""
    shift = np.repeat(maps.column_phase_rad / calib.phase_per_mm, int(factor))
    return shift[None, :].astype(np.float32)


__all__ = ["FixedPatternMaps", "camera_pattern", "column_phase_depth_mm", "fixed_pattern_maps"]
