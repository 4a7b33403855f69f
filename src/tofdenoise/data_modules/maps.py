"""Per-sample sensor maps from a clean sample: signal a(p), sigma_D(p) and the valid mask (paper Sec. III-A/C)."""

from __future__ import annotations

from typing import Any

import numpy as np

from tofdenoise.data_modules.cache import SampleMaps
from tofdenoise.data_modules.sources.base import RawSample, depth_validity


def compute_sample_maps(
    raw: RawSample, calib: Any, lower_percentile: float | None = None, upper_percentile: float | None = None
) -> SampleMaps:
    """Signal map from the amplitude (calibration interval, per-image percentiles), sigma_D from the WLS model.

    Invalid pixels (NaN/inf/<=0 depth, source mask, non-finite amplitude, non-finite sigma) are 0 in every map
    and False in ``mask``.
    """
    from tofdenoise.physics.uncertainty import amplitude_to_signal_e, sigma_depth_mm

    depth = np.asarray(raw.depth_mm, dtype=np.float32)
    amplitude = np.asarray(raw.amplitude, dtype=np.float32)
    if depth.shape != amplitude.shape or depth.shape != raw.valid.shape:
        raise ValueError(
            f"sample {raw.name}: depth {depth.shape}, amplitude {amplitude.shape} and mask "
            f"{raw.valid.shape} must have the same shape"
        )
    with np.errstate(invalid="ignore"):
        valid = raw.valid.astype(bool) & depth_validity(depth) & np.isfinite(amplitude) & (amplitude >= 0)
    zeros = np.zeros(depth.shape, dtype=np.float32)
    if not valid.any():
        return SampleMaps(zeros, zeros.copy(), zeros.copy(), valid, zeros.copy())
    kwargs = {}
    if lower_percentile is not None:
        kwargs["lower_percentile"] = float(lower_percentile)
    if upper_percentile is not None:
        kwargs["upper_percentile"] = float(upper_percentile)
    # amplitude 0 at a valid depth pixel is a legitimate (dark) measurement: nudge it to the lowest level
    signal = np.asarray(
        amplitude_to_signal_e(np.where(valid, np.maximum(amplitude, 1e-12), 0.0), calib, valid=valid, **kwargs),
        dtype=np.float32,
    )
    safe_depth = np.where(valid, depth, 1.0).astype(np.float32)
    safe_signal = np.where(valid & np.isfinite(signal), signal, calib.signal_min_e).astype(np.float32)
    sigma = np.asarray(sigma_depth_mm(safe_depth, safe_signal, calib), dtype=np.float32)
    with np.errstate(invalid="ignore"):
        mask = valid & np.isfinite(signal) & np.isfinite(sigma) & (sigma > 0)
    return SampleMaps(
        depth_mm=np.where(mask, depth, 0.0).astype(np.float32),
        signal_e=np.where(mask, signal, 0.0).astype(np.float32),
        sigma_mm=np.where(mask, sigma, 0.0).astype(np.float32),
        mask=mask,
        amplitude=np.where(mask, amplitude, 0.0).astype(np.float32),
    )
