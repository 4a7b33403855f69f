"""Per-sample sensor maps from a clean sample: signal a(p), sigma_D(p) and the valid mask (paper Sec. III-A/C).

Two signal routes turn the source's amplitude into the returned signal a(p) [e-] (docs/physics.md, "Signal
routes"): ``linear``, the paper's mapping a_min + (a_max - a_min) A~ into the calibration's interval, and
``physical``, a = K t A V (``tofdenoise.physics.photometry``) from a radiometric amplitude (procedural scenes):
dark far surfaces get a few hundred e-, white near ones saturate.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tofdenoise.data_modules.cache import SampleMaps
from tofdenoise.data_modules.sources.base import RawSample, depth_validity
from tofdenoise.physics.photometry import field_cosine, physical_signal_e, saturated
from tofdenoise.physics.simulator import default_min_amplitude_e
from tofdenoise.physics.uncertainty import amplitude_to_signal_e, sigma_depth_mm

SIGNAL_ROUTES = ("linear", "physical")


def check_signal_route(route: str, source: Any, calib: Any) -> str:
    """The route name, lower-cased; ValueError naming ``data.signal_route`` when it is unknown or cannot apply."""
    name = str(route).lower()
    if name not in SIGNAL_ROUTES:
        raise ValueError(f"unknown data.signal_route {route!r}; valid: {', '.join(SIGNAL_ROUTES)}")
    if name == "physical":
        if not getattr(source, "radiometric_amplitude", False):
            raise ValueError(
                f"data.signal_route=physical needs a source with a radiometric amplitude (rho cos(theta) / r^2, the "
                f"procedural scenes); the {getattr(source, 'name', source)!r} source's amplitude is in arbitrary "
                "units: use data.signal_route=linear (the paper's mapping)"
            )
        if getattr(calib, "signal_at_1m_e", None) is None:
            raise ValueError(
                "data.signal_route=physical needs the calibration field 'signal_at_1m_e' (returned signal of a white "
                "target at 1 m); the calibration has none: add it or use data.signal_route=linear"
            )
    return name


def measurable(depth_mm: np.ndarray, signal_e: np.ndarray, calib: Any) -> np.ndarray:
    """Pixels a camera can measure at all: expected amplitude a |C1| at or above its validity threshold (the
    capture simulator's) and the brightest expected tap below the full well."""
    c1 = calib.tap_response.first_harmonic_amplitude
    with np.errstate(invalid="ignore"):
        bright_enough = signal_e * c1 >= default_min_amplitude_e(calib)
    return bright_enough & ~saturated(np.where(bright_enough, depth_mm, 0.0), signal_e, calib)


def signal_from_amplitude_e(
    amplitude: np.ndarray,
    valid: np.ndarray,
    calib: Any,
    signal_route: str = "linear",
    cos_field: Any = None,
    lower_percentile: float | None = None,
    upper_percentile: float | None = None,
) -> np.ndarray:
    """The returned signal a(p) [e-] of a scene's valid pixels, 0 elsewhere (float32): the one place a source's
    amplitude becomes signal, for the training maps and the capture simulator alike.

    ``physical``: a = K t A V (``physics.photometry.physical_signal_e``; ``cos_field`` the cosine of each pixel's
    field angle, for the vignetting V). ``linear``: the paper's mapping into [a_min, a_max] with per-image
    percentiles (``physics.uncertainty.amplitude_to_signal_e``); an amplitude of 0 at a valid pixel is a
    legitimate dark measurement and maps to the lowest level."""
    if signal_route == "physical":
        signal = physical_signal_e(np.where(valid, amplitude, 0.0), calib, cos_field)
        return np.where(valid, signal, 0.0).astype(np.float32)
    kwargs = {}
    if lower_percentile is not None:
        kwargs["lower_percentile"] = float(lower_percentile)
    if upper_percentile is not None:
        kwargs["upper_percentile"] = float(upper_percentile)
    signal = amplitude_to_signal_e(
        np.where(valid, np.maximum(amplitude, 1e-12), 0.0), calib, valid=valid, fill_value=0.0, **kwargs
    )
    return np.asarray(signal, dtype=np.float32)


def scene_signal_e(raw: RawSample, calib: Any, hfov_deg: float) -> np.ndarray:
    """The returned signal of a rendered scene as a camera collects it: the physical route when the camera has a
    photometric gain ``signal_at_1m_e``, else the paper's linear mapping into its signal interval; 0 where the
    scene has no surface (:func:`signal_from_amplitude_e`)."""
    if getattr(calib, "signal_at_1m_e", None) is not None:
        cos_field = field_cosine(*raw.depth_mm.shape, hfov_deg)
        return signal_from_amplitude_e(raw.amplitude, raw.valid, calib, "physical", cos_field)
    return signal_from_amplitude_e(raw.amplitude, raw.valid, calib, "linear")


def compute_sample_maps(
    raw: RawSample,
    calib: Any,
    lower_percentile: float | None = None,
    upper_percentile: float | None = None,
    signal_route: str = "linear",
    cos_field: Any = None,
) -> SampleMaps:
    """Signal map from the amplitude by ``signal_route`` (``linear``: calibration interval and per-image
    percentiles; ``physical``: K t A V with ``cos_field`` for the vignetting), sigma_D from the WLS model.

    Invalid pixels (NaN/inf/<=0 depth, source mask, non-finite amplitude, non-finite sigma) are 0 in every map
    and False in ``mask``.
    """
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
    signal = signal_from_amplitude_e(
        amplitude, valid, calib, signal_route, cos_field, lower_percentile, upper_percentile
    )
    if signal_route == "physical":
        # what the camera can never measure is not in the maps: a pixel whose expected amplitude a |C1| is below
        # the camera's threshold, or whose brightest expected tap reaches the full well. Such a pixel is a hole in
        # every frame; kept in the maps, its sigma_D (hundreds of mm at a few e-) would enter the hetero mean
        # variance that the fixed and range-aware Gaussians are matched to (RMS sigma_D 108.5 mm with them against
        # 25.8 mm without, on 30 default scenes) and make those baselines ~4x too strong. Pixels near the
        # threshold stay; the hole model drops them at random (``HoleModel.physical_signal``).
        valid = valid & measurable(depth, signal, calib)
        signal = np.where(valid, signal, 0.0).astype(np.float32)
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
