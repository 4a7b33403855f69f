"""sigma_D as ONE fused per-pixel kernel (torch.compile / Inductor), for large maps on CPU or GPU.

The same quantity as :func:`tofdenoise.physics.uncertainty.depth_variance_mm2` (paper Eqs. 13-17): per pixel,
with w_n = 1 / (a r_n + sigma_dark^2), g_n = a c'(psi - theta_n) 4 pi f / c_light,

    I_DD = sum_n w_n g_n^2,  I_aa = sum_n w_n r_n^2,  I_Da = sum_n w_n g_n r_n,
    sigma_D^2 = I_aa / (I_DD I_aa - I_Da^2).

The numpy path evaluates this as a chain of array operations (each one a pass over memory); here the whole
chain is compiled into one loop over pixels. Only cos(psi) and sin(psi) are transcendental: the tap shifts
theta_n use the angle-addition formula and the harmonics k >= 2 the recursion
cos(kx) = cos((k-1)x) cos x - sin((k-1)x) sin x. The calibration's coefficients are baked into the kernel as
constants, so one kernel is compiled per calibration (cached by its fingerprint).

Pixels whose information matrix is ill-conditioned (rho^2 = I_Da^2 / (I_DD I_aa) > 0.75, where the determinant
loses more than two bits) are recomputed with the reference path, so the result matches it everywhere.
Compilation takes ~20 s on the first call per calibration and needs a C++ compiler on CPU; when compilation is
not possible the reference path is used with a warning. Use :func:`sigma_depth_mm` (the reference) for small
inputs and numpy arrays.
"""

from __future__ import annotations

import math
import threading
import warnings
from typing import Callable

import torch

from tofdenoise.physics.calibration import C_LIGHT_MM_PER_S, SensorCalibration
from tofdenoise.physics.uncertainty import depth_variance_mm2

__all__ = ["depth_variance_mm2_compiled", "sigma_depth_mm_compiled"]

#: rho^2 above which a pixel is recomputed with the reference path
ILL_CONDITIONED_RHO2 = 0.75

_KERNELS: dict[str, Callable[..., torch.Tensor]] = {}
_FAILED: set[str] = set()
_LOCK = threading.Lock()


def _make_kernel(calib: SensorCalibration) -> Callable[..., torch.Tensor]:
    """The fused kernel for one calibration: (depth, signal) -> variance, NaN where invalid and -1 where the
    information matrix is ill-conditioned. Validity masking happens inside the kernel: one pass over memory."""
    n_taps = calib.num_taps
    c0 = float(calib.tap_response.c0)
    cos_k = [float(c) for c in calib.tap_response.cos]
    sin_k = [float(s) for s in calib.tap_response.sin]
    harmonics = len(cos_k)
    k_d = 4.0 * math.pi * calib.modulation_frequency_hz / C_LIGHT_MM_PER_S  # d psi / d D [rad/mm]
    var0 = float(calib.dark_std_e) ** 2
    shifts = [(math.cos(2 * math.pi * n / n_taps), math.sin(2 * math.pi * n / n_taps)) for n in range(n_taps)]

    def kernel(d_in: torch.Tensor, a_in: torch.Tensor, rho2_max: float) -> torch.Tensor:
        valid = (d_in > 0) & (a_in > 0) & torch.isfinite(d_in) & torch.isfinite(a_in)
        d = torch.where(valid, d_in, 1.0)
        a = torch.where(valid, a_in, 1.0)
        psi = d * k_d
        cp, sp = torch.cos(psi), torch.sin(psi)
        i_dd = torch.zeros_like(d)
        i_aa = torch.zeros_like(d)
        i_da = torch.zeros_like(d)
        for cth, sth in shifts:
            c1 = cp * cth + sp * sth  # cos(psi - theta_n)
            s1 = sp * cth - cp * sth  # sin(psi - theta_n)
            ck, sk = c1, s1
            r = torch.full_like(d, c0)  # r_n = c(psi - theta_n)
            dr = torch.zeros_like(d)  # c'(psi - theta_n)
            for k in range(1, harmonics + 1):
                if k > 1:
                    ck, sk = ck * c1 - sk * s1, sk * c1 + ck * s1
                if cos_k[k - 1] == 0.0 and sin_k[k - 1] == 0.0:
                    continue
                r = r + cos_k[k - 1] * ck + sin_k[k - 1] * sk
                dr = dr + k * (sin_k[k - 1] * ck - cos_k[k - 1] * sk)
            w = 1.0 / (a * r + var0)
            g = a * dr * k_d  # d mu_n / d D
            i_dd = i_dd + w * g * g
            i_aa = i_aa + w * r * r
            i_da = i_da + w * g * r
        det = i_dd * i_aa - i_da * i_da
        # ill-conditioned pixels are marked with the sentinel -1 (a variance is positive): a second, boolean
        # output would double the kernel's time
        well = (i_da * i_da) <= rho2_max * (i_dd * i_aa)
        return torch.where(valid, torch.where(well, i_aa / det, -1.0), math.nan)

    return kernel


def _compiled_kernel(calib: SensorCalibration):
    key = calib.fingerprint()
    with _LOCK:
        if key not in _KERNELS:
            _KERNELS[key] = torch.compile(_make_kernel(calib), dynamic=None)
        return _KERNELS[key], key


def depth_variance_mm2_compiled(depth_mm: torch.Tensor, signal_e: torch.Tensor, calib: SensorCalibration) -> torch.Tensor:
    """sigma_D^2 [mm^2] through the fused kernel; same contract as ``depth_variance_mm2`` for torch tensors
    (broadcasting, NaN where depth <= 0, signal <= 0, NaN or inf; float64 if either input is float64)."""
    if not isinstance(depth_mm, torch.Tensor) or not isinstance(signal_e, torch.Tensor):
        raise TypeError("depth_variance_mm2_compiled takes torch tensors; use depth_variance_mm2 for numpy arrays")
    dtype = torch.float64 if torch.float64 in (depth_mm.dtype, signal_e.dtype) else torch.float32
    d, a = torch.broadcast_tensors(depth_mm.detach().to(dtype), signal_e.detach().to(dtype))
    kernel, key = _compiled_kernel(calib)
    if key in _FAILED:
        return depth_variance_mm2(depth_mm, signal_e, calib)
    try:
        var = kernel(d.contiguous(), a.contiguous(), ILL_CONDITIONED_RHO2)
    except Exception as exc:  # no C++ compiler, unsupported backend, ...
        _FAILED.add(key)
        warnings.warn(f"sigma_D: torch.compile of the fused kernel failed ({type(exc).__name__}: {exc}); "
                      "using the reference path", RuntimeWarning, stacklevel=2)
        return depth_variance_mm2(depth_mm, signal_e, calib)
    ill = var < 0
    if bool(ill.any()):
        var[ill] = depth_variance_mm2(d[ill], a[ill], calib).to(var.dtype)
    return var


def sigma_depth_mm_compiled(depth_mm: torch.Tensor, signal_e: torch.Tensor, calib: SensorCalibration) -> torch.Tensor:
    """sigma_D(p) [mm] (paper Eq. 17) through the fused kernel; see depth_variance_mm2_compiled."""
    return depth_variance_mm2_compiled(depth_mm, signal_e, calib).sqrt()
