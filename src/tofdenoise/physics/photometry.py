"""Returned signal as a camera sees it: the physical signal route (beside the paper's linear mapping).

The paper (Sec. III-A) maps a rendered amplitude linearly into a calibrated interval [a_min, a_max]. A camera's
returned signal is not bounded that way: a dark far surface returns a few hundred electrons and a white near one
saturates. For an emitter next to the lens and a Lambertian surface, the photo-electrons per tap are

    a(p) = K * t * rho(p) * cos(theta(p)) * (1 m / r(p))^2 * V(p)                         (inverse-square law)

K   ``signal_at_1m_e``: the camera's photometric gain, the returned signal per tap [e-] of a white (rho = 1)
    Lambertian target, frontal, at 1 m, at exposure 1. Emitter power, optics transmission, fill factor and
    quantum efficiency are folded into it; it is measured with one target at one distance.
t   the exposure relative to the calibrated one (emitter power x integration time).
rho reflectance at the emitter's wavelength; theta the incidence angle; r the range (ray length), not z.
V   lens fall-off (relative illumination) cos^k(field angle), k = ``vignetting_cos_power`` (4: natural
    vignetting of a thin lens; wide-angle ToF lenses are designed to 2-4).

Specular surfaces add a lobe rho_s cos^n(theta) (emitter and camera share the half vector, so the lobe peaks
at normal incidence); the procedural renderer folds it into its radiometric amplitude. Every function here is
pure and works on numpy arrays of any shape.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tofdenoise.physics.uncertainty import tap_responses

REFERENCE_RANGE_MM: float = 1000.0


def inverse_square_signal_e(
    reflectance: Any,
    cos_incidence: Any,
    range_mm: Any,
    signal_at_1m_e: float,
    exposure: float = 1.0,
) -> np.ndarray:
    """a = K t rho cos(theta) (1000 mm / r)^2 [e-] for a Lambertian surface at range r (mm)."""
    r = np.asarray(range_mm, dtype=np.float64)
    return (
        float(signal_at_1m_e)
        * float(exposure)
        * np.asarray(reflectance, dtype=np.float64)
        * np.asarray(cos_incidence, dtype=np.float64)
        * (REFERENCE_RANGE_MM / r) ** 2
    )


def field_cosine(height: int, width: int, hfov_deg: float) -> np.ndarray:
    """cos(field angle) of each pixel centre of a pinhole camera with horizontal field of view ``hfov_deg``:
    1 / sqrt(1 + x^2 + y^2) with (x, y) the normalised image coordinates. (H, W) float64."""
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    xs = (np.arange(width, dtype=np.float64) + 0.5 - width / 2.0) / f
    ys = (np.arange(height, dtype=np.float64) + 0.5 - height / 2.0) / f
    return 1.0 / np.sqrt(1.0 + xs[None, :] ** 2 + ys[:, None] ** 2)


def vignetting(cos_field: Any, cos_power: float | None) -> np.ndarray:
    """Relative illumination V = cos^k(field angle) (k None or 0: no fall-off)."""
    c = np.asarray(cos_field, dtype=np.float64)
    return np.ones_like(c) if not cos_power else c ** float(cos_power)


def physical_signal_e(
    radiometric_amplitude: Any,
    calib: Any,
    cos_field: Any = None,
    exposure: float = 1.0,
) -> np.ndarray:
    """Returned signal a(p) [e-] from a radiometric amplitude rho cos(theta) / r_m^2 [1/m^2] (what the procedural
    renderer writes): a = K t A V. Needs ``calib.signal_at_1m_e``; ``cos_field`` (broadcastable, e.g.
    ``field_cosine``) applies the calibration's vignetting. Non-finite or negative amplitudes give 0."""
    k = getattr(calib, "signal_at_1m_e", None)
    if k is None:
        raise ValueError(
            "the physical signal route needs the calibration field 'signal_at_1m_e' (returned signal of a white "
            "target at 1 m, docs/physics.md 'Signal routes'); this calibration has none"
        )
    amp = np.asarray(radiometric_amplitude, dtype=np.float64)
    amp = np.where(np.isfinite(amp) & (amp > 0), amp, 0.0)
    v = 1.0 if cos_field is None else vignetting(cos_field, getattr(calib, "vignetting_cos_power", None))
    return (float(k) * float(exposure)) * amp * v


def peak_tap_e(depth_mm: Any, signal_e: Any, calib: Any) -> np.ndarray:
    """Expected charge of the brightest tap, max_n a r_n(D) + mu_dark [e-] (paper Eq. 4); NaN where invalid."""
    d = np.asarray(depth_mm, dtype=np.float64)
    a = np.asarray(signal_e, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0) & np.isfinite(a) & (a >= 0)
    responses, _ = tap_responses(np.where(ok, d, 1.0), calib)
    peak = a * np.asarray(responses).max(axis=-1) + calib.dark_mean_e
    return np.where(ok, peak, np.nan)


def saturated(depth_mm: Any, signal_e: Any, calib: Any) -> np.ndarray:
    """Pixels whose brightest expected tap reaches the full well (the camera flags them invalid)."""
    with np.errstate(invalid="ignore"):
        return peak_tap_e(depth_mm, signal_e, calib) >= calib.full_well_e


__all__ = [
    "REFERENCE_RANGE_MM",
    "field_cosine",
    "inverse_square_signal_e",
    "peak_tap_e",
    "physical_signal_e",
    "saturated",
    "vignetting",
]
