"""The shared arithmetic of the sigma_D routes: harmonic features, linear combinations and the two-pass block.

Used by :mod:`tofdenoise.physics.uncertainty` (the reference and the device route) and by
:mod:`tofdenoise.physics.uncertainty_numpy` (the CPU route); it imports neither. Notation of the paper
(Sec. III-A/B): r_n = c(psi - theta_n), c'_n its derivative, w_n = 1 / sigma_n^2 = 1 / (a r_n + sigma_dark^2).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from tofdenoise.physics import _backend as arrays
from tofdenoise.physics.calibration import SensorCalibration

__all__ = ["axpy_", "harmonics", "lincomb", "variance_two_pass"]


def harmonics(psi: Any, num_harmonics: int) -> list[Any]:
    """[cos(psi) .. cos(K psi), sin(psi) .. sin(K psi)] by the Chebyshev recursion
    cos(k psi) = 2 cos(psi) cos((k-1) psi) - cos((k-2) psi) (same for sin): only cos(psi), sin(psi) are
    transcendental."""
    xp = arrays.namespace(psi)
    c1, s1 = xp.cos(psi), xp.sin(psi)
    cos_list, sin_list = [c1], [s1]
    if num_harmonics >= 2:
        two_c = c1 * 2.0
        cos_list.append(two_c * c1 - 1.0)
        sin_list.append(two_c * s1)
        for _ in range(2, num_harmonics):
            cos_list.append(two_c * cos_list[-1] - cos_list[-2])
            sin_list.append(two_c * sin_list[-1] - sin_list[-2])
    return cos_list + sin_list


def axpy_(y: Any, x: Any, alpha: float) -> Any:
    """y += alpha x in place (no temporary for torch)."""
    if isinstance(y, torch.Tensor):
        return y.add_(x, alpha=alpha)
    y += alpha * x
    return y


def lincomb(feats: list[Any], coefs: np.ndarray, const: float) -> Any:
    """const + sum_j coefs[j] feats[j], skipping zero coefficients."""
    out = None
    for f, c in zip(feats, coefs):
        if c == 0.0:
            continue
        out = f * float(c) if out is None else axpy_(out, f, float(c))
    if out is None:
        return arrays.full_like(feats[0], const)
    if const:
        out += const
    return out


def variance_two_pass(d: Any, a: Any, calib: SensorCalibration, R: np.ndarray, G: np.ndarray) -> Any:
    """sigma_D^2 [mm^2] of valid pixels (d > 0, a > 0, finite; numpy or torch) by the two-pass residual form.

    I_DD - I_Da^2 / I_aa is evaluated as sum_n w_n (c'_n - beta r_n)^2 with beta = I_Da / I_aa: a sum of
    non-negative terms, so float32 does not suffer the cancellation of I_DD I_aa - I_Da^2 (paper Eqs. 13-17;
    R, G are ``TapResponse.tap_matrices``)."""
    feats = harmonics(d * calib.phase_per_mm, calib.tap_response.num_harmonics)
    c0 = calib.tap_response.c0
    s2 = calib.dark_std_e**2
    planes = []
    s_rr = s_gr = None
    for n in range(calib.num_taps):
        r = lincomb(feats, R[:, n], c0)  # r_n = c(psi - theta_n)
        g = lincomb(feats, G[:, n], 0.0)  # c'(psi - theta_n)
        w = a * r
        w += s2
        w = 1.0 / w  # w_n = 1 / sigma_n^2 (paper Eq. 6)
        wr = w * r
        if s_rr is None:
            s_rr, s_gr = wr * r, wr * g
        else:
            s_rr += wr * r
            s_gr += wr * g
        planes.append((r, g, w))
    beta = s_gr / s_rr  # I_Da / I_aa (up to the common factor a k)
    i_eff = None  # (I_DD - I_Da^2 / I_aa) / (a k)^2 = sum_n w_n (c'_n - beta r_n)^2 >= 0
    for r, g, w in planes:
        res = g - beta * r
        res *= res
        res *= w
        if i_eff is None:
            i_eff = res
        else:
            i_eff += res
    k = calib.phase_per_mm
    i_eff *= a * a
    i_eff *= k * k
    return 1.0 / i_eff
