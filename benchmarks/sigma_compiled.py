"""sigma_D as ONE fused per-pixel kernel (torch.compile / Inductor): benchmark code, not part of the package.

No command computes enough sigma_D maps per calibration to pay its compile time (~20 s), so the package keeps the
three routes it uses (:mod:`tofdenoise.physics.uncertainty`) and this kernel lives with the benchmarks that
measure it (bench_physics.py, bench_gpu.py; tests/benchmarks/test_sigma_compiled.py keeps it equal to them).

The same quantity as :func:`tofdenoise.physics.uncertainty.depth_variance_mm2` (paper Eqs. 13-17). Per pixel,
with r_n = c(psi - theta_n), r'_n = c'(psi - theta_n), w_n = 1 / (a r_n + sigma_dark^2) and
g_n = d mu_n / dD = a k r'_n (k = 4 pi f / c_light), the factor a k comes out of every sum:

    S_dd = sum_n w_n r'_n^2,  S_dr = sum_n w_n r'_n r_n,  S_rr = sum_n w_n r_n^2,
    sigma_D^2 = I_aa / (I_DD I_aa - I_Da^2) = S_rr / ((S_dd S_rr - S_dr^2) (a k)^2).

The numpy path evaluates this as a chain of array operations (each one a pass over memory); here the chain,
the validity mask and the square root are compiled into one loop over pixels. Only cos(psi) and sin(psi) are
transcendental. The tap response of every tap is expanded once, at kernel-build time, into constants times
cos(k psi) and sin(k psi) (angle addition with the tap shift theta_n = 2 pi n / N); coefficients that vanish
(|x| < 1e-12 of the largest, e.g. cos(pi / 2) for N = 4) are dropped, so a 4-tap sensor with a first and third
harmonic costs two multiply-adds per tap for r_n and two for r'_n. One kernel is compiled per calibration
(cached by its fingerprint).

Pixels whose information matrix is ill-conditioned (rho^2 = S_dr^2 / (S_dd S_rr) > 0.75, where the determinant
loses more than two bits) are recomputed with the reference path, so the result matches it everywhere; the
kernel reports whether there are any in the same pass. Compilation runs on the first call per calibration
(its time and the kernel's speed: docs/benchmarks.md, "Sensor physics") and needs a C++ compiler on CPU; when
compilation is not possible the reference path is used with a warning. Use :func:`sigma_depth_mm` for small
inputs and numpy arrays.
"""

from __future__ import annotations

import math
import threading
import warnings
from collections.abc import Callable

import torch

from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.physics.uncertainty import depth_variance_mm2
from tofdenoise.physics.uncertainty_numpy import RHO2_SINGLE_PASS_MAX

__all__ = ["depth_variance_mm2_compiled", "sigma_depth_mm_compiled", "tap_expansion"]

#: rho^2 above which a pixel is recomputed through ``depth_variance_mm2`` (the bound of the numpy single pass)
ILL_CONDITIONED_RHO2 = RHO2_SINGLE_PASS_MAX
#: expansion coefficients smaller than this fraction of the largest one are exact zeros in disguise
_ZERO_RTOL = 1e-12

_KERNELS: dict[str, Callable[..., tuple[torch.Tensor, torch.Tensor]]] = {}
_FAILED: set[str] = set()
_LOCK = threading.Lock()

Term = tuple[float, int, str]  # (coefficient, harmonic k, "cos" | "sin"): coefficient * cos(k psi) or sin(k psi)


def tap_expansion(calib: SensorCalibration) -> list[tuple[list[Term], list[Term]]]:
    """Per tap n, r_n - c0 and r'_n as sums of coefficient * {cos, sin}(k psi).

    With c(x) = c0 + sum_k C_k cos(kx) + S_k sin(kx) and x = psi - theta_n:
    cos(k(psi - theta)) = cos(k psi) cos(k theta) + sin(k psi) sin(k theta),
    sin(k(psi - theta)) = sin(k psi) cos(k theta) - cos(k psi) sin(k theta), and
    c'(x) = sum_k k (S_k cos(kx) - C_k sin(kx)). Vanishing coefficients are dropped.
    """
    cos_k = [float(c) for c in calib.tap_response.cos]
    sin_k = [float(s) for s in calib.tap_response.sin]
    n_taps = calib.num_taps
    raw: list[tuple[list[Term], list[Term]]] = []
    for n in range(n_taps):
        theta = 2.0 * math.pi * n / n_taps
        r_terms: list[Term] = []
        dr_terms: list[Term] = []
        for k, (ck, sk) in enumerate(zip(cos_k, sin_k), start=1):
            ct, st = math.cos(k * theta), math.sin(k * theta)
            # C cos(k(psi-theta)) + S sin(k(psi-theta)) = (C ct - S st) cos k psi + (C st + S ct) sin k psi
            r_terms += [(ck * ct - sk * st, k, "cos"), (ck * st + sk * ct, k, "sin")]
            # k (S cos(k(psi-theta)) - C sin(k(psi-theta))) = k (S ct + C st) cos k psi + k (S st - C ct) sin k psi
            dr_terms += [(k * (sk * ct + ck * st), k, "cos"), (k * (sk * st - ck * ct), k, "sin")]
        raw.append((r_terms, dr_terms))
    scale = max([abs(c) for r, d in raw for c, _, _ in r + d] + [0.0])
    tol = _ZERO_RTOL * scale
    return [([t for t in r if abs(t[0]) > tol], [t for t in d if abs(t[0]) > tol]) for r, d in raw]


# Cody-Waite split of pi/2 (the first two parts are exact in float32, so q * part is exact for |q| < 2^12)
_PIO2_1, _PIO2_2, _PIO2_3 = 1.5703125, 4.837512969970703125e-4, 7.54978995489188216e-8
# minimax polynomials of sin and cos on [-pi/4, pi/4] (the Cephes single-precision coefficients)
_SIN = (-1.9515295891e-4, 8.3321608736e-3, -1.6666654611e-1)
_COS = (2.443315711809948e-5, -1.388731625493765e-3, 4.166664568298827e-2)


def _cos_sin_f32(psi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """cos(psi), sin(psi) for float32 in plain arithmetic, so that Inductor fuses them into the kernel
    (~2x cheaper than two library calls). Absolute error < 1e-7 for |psi| < 2^12 rad (depths below ~2 km at
    50 MHz) and < 1e-6 up to 1e5 rad (~48 km); far beyond any iToF range, float32 psi itself is the limit. Quadrant
    reduction psi = q pi/2 + x, |x| <= pi/4, then the two polynomials and the quadrant's
    swap and signs: (cos, sin)(psi) = (c, s), (-s, c), (-c, -s), (s, -c) for q mod 4 = 0, 1, 2, 3."""
    q = torch.round(psi * (2.0 / math.pi))
    x = ((psi - q * _PIO2_1) - q * _PIO2_2) - q * _PIO2_3
    z = x * x
    s = x + x * z * ((_SIN[0] * z + _SIN[1]) * z + _SIN[2])
    c = 1.0 - 0.5 * z + z * z * ((_COS[0] * z + _COS[1]) * z + _COS[2])
    j = q - 4.0 * torch.floor(q * 0.25)  # q mod 4 in {0, 1, 2, 3}
    odd = (j == 1.0) | (j == 3.0)
    cos_psi = torch.where(odd, s, c)
    sin_psi = torch.where(odd, c, s)
    cos_psi = torch.where((j == 1.0) | (j == 2.0), -cos_psi, cos_psi)
    sin_psi = torch.where(j >= 2.0, -sin_psi, sin_psi)
    return cos_psi, sin_psi


def _make_kernel(calib: SensorCalibration) -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """The fused kernel for one calibration: (depth, signal, rho2_max) -> (sigma_D [mm], any_ill), sigma_D NaN
    where invalid and -1 where the information matrix is ill-conditioned; ``any_ill`` is a 0-d bool. One pass
    over memory."""
    c0 = float(calib.tap_response.c0)
    k_d = calib.phase_per_mm  # d psi / d D [rad/mm]
    var0 = float(calib.dark_std_e) ** 2
    taps = tap_expansion(calib)
    k_max = max([k for r, d in taps for _, k, _ in r + d] + [1])

    def lincomb(const: float | None, terms: list[Term], basis: dict[tuple[int, str], torch.Tensor], like):
        acc = None if const is None else torch.full_like(like, const)
        for coef, k, kind in terms:
            acc = coef * basis[k, kind] if acc is None else acc + coef * basis[k, kind]
        return torch.zeros_like(like) if acc is None else acc

    def kernel(d_in: torch.Tensor, a_in: torch.Tensor, rho2_max: float) -> tuple[torch.Tensor, torch.Tensor]:
        # d < inf is False for NaN and +inf: with d > 0 that is "finite and positive" in two comparisons
        valid = (d_in > 0) & (d_in < math.inf) & (a_in > 0) & (a_in < math.inf)
        d = torch.where(valid, d_in, 1.0)
        a = torch.where(valid, a_in, 1.0)
        psi = d * k_d
        c1, s1 = _cos_sin_f32(psi) if psi.dtype == torch.float32 else (torch.cos(psi), torch.sin(psi))
        basis = {(1, "cos"): c1, (1, "sin"): s1}
        for k in range(2, k_max + 1):  # angle addition: cos(k psi) = cos((k-1) psi) cos psi - sin((k-1) psi) sin psi
            cp, sp = basis[k - 1, "cos"], basis[k - 1, "sin"]
            basis[k, "cos"], basis[k, "sin"] = cp * c1 - sp * s1, sp * c1 + cp * s1
        s_dd = s_dr = s_rr = None
        for r_terms, dr_terms in taps:
            r = lincomb(c0, r_terms, basis, d)
            dr = lincomb(None, dr_terms, basis, d)
            w = 1.0 / (a * r + var0)
            wdr, wr = w * dr, w * r
            if s_dd is None:
                s_dd, s_dr, s_rr = wdr * dr, wdr * r, wr * r
            else:
                s_dd, s_dr, s_rr = s_dd + wdr * dr, s_dr + wdr * r, s_rr + wr * r
        ak = a * k_d
        var = s_rr / ((s_dd * s_rr - s_dr * s_dr) * (ak * ak))
        # ill-conditioned pixels get the sentinel -1 (sigma is positive)
        well = (s_dr * s_dr) <= rho2_max * (s_dd * s_rr)
        out = torch.where(valid, torch.where(well, torch.sqrt(var), -1.0), math.nan)
        return out, (valid & ~well).any()

    return kernel


def _compiled_kernel(calib: SensorCalibration):
    key = calib.fingerprint()
    with _LOCK:
        if key not in _KERNELS:
            _KERNELS[key] = torch.compile(_make_kernel(calib), dynamic=None)
        return _KERNELS[key], key


def sigma_depth_mm_compiled(depth_mm: torch.Tensor, signal_e: torch.Tensor, calib: SensorCalibration) -> torch.Tensor:
    """sigma_D(p) [mm] (paper Eq. 17) through the fused kernel, square root included. Same contract as
    ``sigma_depth_mm`` for torch tensors: broadcasting, NaN where depth <= 0, signal <= 0, NaN or inf; float64
    if either input is float64."""
    if not isinstance(depth_mm, torch.Tensor) or not isinstance(signal_e, torch.Tensor):
        raise TypeError(
            "the fused sigma_D kernel takes torch tensors; use sigma_depth_mm / depth_variance_mm2 for numpy arrays"
        )
    dtype = torch.float64 if torch.float64 in (depth_mm.dtype, signal_e.dtype) else torch.float32
    d, a = torch.broadcast_tensors(depth_mm.detach().to(dtype), signal_e.detach().to(dtype))

    def reference(dd: torch.Tensor, aa: torch.Tensor) -> torch.Tensor:
        return depth_variance_mm2(dd, aa, calib).sqrt()

    kernel, key = _compiled_kernel(calib)
    if key in _FAILED:
        return reference(d, a)
    try:
        out, any_ill = kernel(d.contiguous(), a.contiguous(), ILL_CONDITIONED_RHO2)
    except Exception as exc:  # no C++ compiler, unsupported backend, ...
        _FAILED.add(key)
        warnings.warn(
            f"sigma_D: torch.compile of the fused kernel failed ({type(exc).__name__}: {exc}); "
            "using the reference path",
            RuntimeWarning,
            stacklevel=2,
        )
        return reference(d, a)
    if bool(any_ill):
        ill = out < 0
        out[ill] = reference(d[ill], a[ill]).to(out.dtype)
    return out


def depth_variance_mm2_compiled(
    depth_mm: torch.Tensor, signal_e: torch.Tensor, calib: SensorCalibration
) -> torch.Tensor:
    """sigma_D^2 [mm^2]: the square of ``sigma_depth_mm_compiled`` (one compiled kernel serves both)."""
    return sigma_depth_mm_compiled(depth_mm, signal_e, calib).square()
