"""Per-pixel iToF depth uncertainty from tap statistics (paper Sec. III-A/B, Eqs. 1-15).

Model (per pixel, N taps): r_n(D) = c(psi(D) - theta_n), mu_n = a r_n + mu_dark,
sigma_n^2 = a r_n + sigma_dark^2, J = [d mu / dD, d mu / da] with
d mu_n / dD = a c'(psi - theta_n) 4 pi f / c_light and d mu_n / da = r_n.
sigma_D^2 = e_D^T (J^T Sigma^-1 J)^-1 e_D.

Closed form of the 2x2 information matrix (w_n = 1 / sigma_n^2, g_n = d mu_n / dD):
    I_DD = sum w g^2, I_aa = sum w r^2, I_Da = sum w g r,
    sigma_D^2 = I_aa / (I_DD I_aa - I_Da^2) = 1 / (I_DD - I_Da^2 / I_aa).
The denominator I_DD - I_Da^2 / I_aa is evaluated as the weighted residual sum
sum_n w_n (g_n - beta r_n)^2 with beta = I_Da / I_aa (the depth sensitivity left after projecting out the
signal-level direction): a sum of non-negative terms, so float32 does not suffer the cancellation of
I_DD I_aa - I_Da^2. Everything is vectorised over pixels and the N taps; numpy or torch, any shape.

The three sigma_D routes. They give the same numbers (tests/physics/test_uncertainty.py checks each against
route 1); their speeds are in docs/benchmarks.md ("Sensor physics").

  route                                    form; where it is the one to use             called by
  1 information_matrix (here)              THE REFERENCE: Eq. 15 as written, from the   tests, benchmarks
                                           (..., N) Jacobian; numpy or torch; slowest
  2 sigma_kernels.variance_two_pass        two-pass residual form sum w (g - beta r)^2: depth_variance_mm2 for
                                           no cancellation, stable in float32; the      tensors off the CPU; route 3
                                           route on a GPU                               for pixels with rho^2 > 0.75
  3 uncertainty_numpy.variance_block       single pass over the taps, tap pairs         depth_variance_mm2 on the
                                           (n, n + N/2) share their harmonics; numpy    CPU: data_modules, inference,
                                           arrays and CPU tensors (zero-copy), blocks   physics.validation,
                                           on threads; the fast CPU route               cli.sensor_physics

A fourth form, the same sums fused into one ``torch.compile`` kernel, is benchmark code
(``benchmarks/sigma_compiled.py``): faster once compiled, but no command computes enough maps per calibration
to pay its compile time.

The public ``depth_variance_mm2`` / ``sigma_depth_mm`` pick the route by where the data lives: route 3 on the
CPU, route 2 on other devices.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from tofdenoise.physics import _backend as arrays
from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.physics.sigma_kernels import harmonics, lincomb, variance_two_pass
from tofdenoise.physics.uncertainty_numpy import depth_variance_numpy


def _prepare(depth_mm: Any, signal_e: Any) -> tuple[Any, Any, Any, Any]:
    """Convert to a common floating array family/dtype, broadcast, and compute the validity mask."""
    xp = arrays.namespace(depth_mm, signal_e)
    like = depth_mm if isinstance(depth_mm, torch.Tensor) else signal_e if isinstance(signal_e, torch.Tensor) else None
    d = arrays.as_float_array(depth_mm, like)
    a = arrays.as_float_array(signal_e, like if like is not None else None)
    dtype = arrays.result_dtype(d, a)
    d, a = arrays.cast(d, dtype), arrays.cast(a, dtype)
    if xp is torch:
        d, a = torch.broadcast_tensors(d, a)
    else:
        d, a = np.broadcast_arrays(d, a)
    valid = xp.isfinite(d) & xp.isfinite(a) & (d > 0) & (a > 0)
    return xp, d, a, valid


def tap_phase_rad(depth_mm: Any, calib: SensorCalibration) -> Any:
    """psi(D) = 4 pi f D / c_light (paper Eq. 2), D in mm."""
    return depth_mm * calib.phase_per_mm


def tap_planes(depth_mm: Any, calib: SensorCalibration) -> tuple[list[Any], list[Any]]:
    """Per-tap arrays ([r_n], [c'(psi - theta_n)]), n = 0..N-1, each shaped like depth_mm (paper Eq. 3).

    c(psi - theta_n) = c0 + sum_k A_nk cos(k psi) + B_nk sin(k psi) with constant A, B (TapResponse.tap_matrices),
    so only cos(psi), sin(psi) are transcendental per pixel.
    """
    R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
    feats = harmonics(tap_phase_rad(depth_mm, calib), calib.tap_response.num_harmonics)
    c0 = calib.tap_response.c0
    r_list = [lincomb(feats, R[:, n], c0) for n in range(calib.num_taps)]
    g_list = [lincomb(feats, G[:, n], 0.0) for n in range(calib.num_taps)]
    return r_list, g_list


def tap_responses(depth_mm: Any, calib: SensorCalibration) -> tuple[Any, Any]:
    """(r_n, c'(psi - theta_n)) with the taps on a new last axis of length N (paper Eq. 3)."""
    r_list, g_list = tap_planes(depth_mm, calib)
    return arrays.stack_last(r_list), arrays.stack_last(g_list)


def tap_mean_e(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> Any:
    """mu_n(D, a) = a r_n(D) + mu_dark (paper Eq. 4), taps on the last axis."""
    r, _ = tap_responses(depth_mm, calib)
    return signal_e[..., None] * r + calib.dark_mean_e


def tap_variance_e2(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> Any:
    """sigma_n^2 = a r_n(D) + sigma_dark^2 (paper Eq. 6), taps on the last axis."""
    r, _ = tap_responses(depth_mm, calib)
    return signal_e[..., None] * r + calib.dark_std_e**2


def tap_jacobian(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> tuple[Any, Any]:
    """(d mu_n / dD [e-/mm], d mu_n / da [1]) (paper Eqs. 13-14), taps on the last axis."""
    r, dr = tap_responses(depth_mm, calib)
    return signal_e[..., None] * dr * calib.phase_per_mm, r


def information_matrix(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> tuple[Any, Any, Any]:
    """(I_DD, I_Da, I_aa): the entries of J^T Sigma^-1 J (paper Eq. 15's inverse), per pixel."""
    g, r = tap_jacobian(depth_mm, signal_e, calib)
    w = 1.0 / (signal_e[..., None] * r + calib.dark_std_e**2)
    return (w * g * g).sum(-1), (w * g * r).sum(-1), (w * r * r).sum(-1)


def depth_variance_mm2(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> Any:
    """sigma_D^2 [mm^2] = e_D^T (J^T Sigma^-1 J)^-1 e_D (paper Eq. 16), closed form, NaN where invalid.

    On the CPU the map is evaluated in blocks of BLOCK_PIXELS pixels (cache-sized temporaries, through numpy,
    zero-copy for torch tensors); on other devices in one pass with torch.

    Args:
        depth_mm: depth [mm]; a numpy array, a torch tensor or a scalar, of any shape that broadcasts with
            ``signal_e``.
        signal_e: the returned signal a(p) per tap [e-] (``amplitude_to_signal_e`` makes it from an amplitude).
        calib: the sensor calibration.

    Returns:
        The variance [mm^2] in the broadcast shape, numpy or torch like the inputs, with their floating dtype
        (float64 if either is float64) and on their device. Invalid pixels (depth <= 0, signal <= 0, NaN or inf
        in either) give NaN and never raise.
    """
    is_t = isinstance(depth_mm, torch.Tensor) or isinstance(signal_e, torch.Tensor)
    device = None
    if is_t:
        like = depth_mm if isinstance(depth_mm, torch.Tensor) else signal_e
        device = like.device
    if is_t and device is not None and device.type != "cpu":
        xp, d, a, valid = _prepare(depth_mm, signal_e)
        R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
        var = variance_two_pass(torch.where(valid, d, 1.0), torch.where(valid, a, 1.0), calib, R, G)
        return torch.where(valid, var, torch.full_like(var, math.nan))
    if is_t:
        dt = torch.as_tensor(depth_mm, device=device)
        at = torch.as_tensor(signal_e, device=device)
        dtype = torch.float64 if torch.float64 in (dt.dtype, at.dtype) else torch.float32
        dt, at = torch.broadcast_tensors(dt.detach().to(dtype), at.detach().to(dtype))
        var = depth_variance_numpy(dt.contiguous().numpy(), at.contiguous().numpy(), calib)
        return torch.from_numpy(var)
    d = np.asarray(depth_mm)
    a = np.asarray(signal_e)
    both_f32 = all(x.dtype in (np.float32, np.float16) for x in (d, a))
    dtype = np.float32 if both_f32 else np.float64
    d, a = np.broadcast_arrays(d.astype(dtype, copy=False), a.astype(dtype, copy=False))
    return depth_variance_numpy(d, a, calib)


def sigma_depth_mm(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> Any:
    """sigma_D(p) = sqrt(sigma_D^2(p)) [mm], the per-pixel depth uncertainty (paper Eq. 17).

    ``tofdenoise sensor sigma`` prints it for a few depths and signals.

    Args:
        depth_mm: depth [mm]; a numpy array, a torch tensor or a scalar, of any shape that broadcasts with
            ``signal_e``.
        signal_e: the returned signal a(p) per tap [e-] (``amplitude_to_signal_e`` makes it from an amplitude).
        calib: the sensor calibration.

    Returns:
        sigma_D [mm] as ``depth_variance_mm2`` returns the variance: the broadcast shape, numpy or torch like
        the inputs, their dtype and device; NaN at invalid pixels (depth <= 0, signal <= 0, NaN or inf).
    """
    var = depth_variance_mm2(depth_mm, signal_e, calib)
    return var.sqrt() if isinstance(var, torch.Tensor) else np.sqrt(var)


def amplitude_to_signal_e(
    amplitude: Any,
    calib: SensorCalibration,
    valid: Any = None,
    lower_percentile: float = 1.0,
    upper_percentile: float = 99.0,
    fill_value: float = math.nan,
) -> Any:
    """Map a ToF amplitude image to the returned-signal level a(p) = a_min + (a_max - a_min) A~(p).

    Paper Sec. III-A: the valid amplitude is normalised robustly, A~ = clip((A - P_lo) / (P_hi - P_lo),
    0, 1) with P_lo / P_hi the ``lower_percentile`` / ``upper_percentile`` of the valid amplitudes (so a few
    outliers cannot stretch the scale), then mapped to [signal_min_e, signal_max_e] of the calibration.
    Percentiles are taken over ALL valid pixels of the array (pass one image at a time for per-image
    normalisation). If P_hi == P_lo the valid pixels map to the middle of the interval.

    Args:
        amplitude: the amplitude image (numpy or torch, any shape, any positive scale).
        calib: the sensor calibration, whose [signal_min_e, signal_max_e] is the target interval.
        valid: bool mask of the pixels to use, same shape; always combined with finite amplitudes > 0.
        lower_percentile: P_lo's percentile, in [0, 100).
        upper_percentile: P_hi's percentile, above ``lower_percentile`` and at most 100.
        fill_value: what invalid pixels get.

    Returns:
        a(p) [e-], numpy or torch like ``amplitude``, same shape.

    Raises:
        ValueError: the percentiles are not 0 <= lower < upper <= 100.
    """
    if not (0.0 <= lower_percentile < upper_percentile <= 100.0):
        raise ValueError(
            f"need 0 <= lower_percentile < upper_percentile <= 100, got {lower_percentile}, {upper_percentile}"
        )
    xp = arrays.namespace(amplitude)
    amp = arrays.as_float_array(amplitude)
    if xp is np and amp.dtype not in (np.float32, np.float64):
        amp = amp.astype(np.float64)
    ok = xp.isfinite(amp) & (amp > 0)
    if valid is not None:
        v = valid if xp is np else torch.as_tensor(valid, device=amp.device)
        v = v.astype(bool) if xp is np else v.bool()
        ok = ok & v
    a_min, a_max = calib.signal_min_e, calib.signal_max_e
    if xp is torch:
        vals = amp[ok]
        if vals.numel() == 0:
            return torch.full_like(amp, fill_value)
        q = torch.tensor([lower_percentile / 100.0, upper_percentile / 100.0], dtype=vals.dtype, device=vals.device)
        vals_q = vals if vals.numel() <= 8_000_000 else vals[:: int(math.ceil(vals.numel() / 8_000_000))]
        lo, hi = torch.quantile(vals_q, q).tolist()
    else:
        vals = amp[ok]
        if vals.size == 0:
            return np.full_like(amp, fill_value)
        lo, hi = (float(v) for v in np.percentile(vals, [lower_percentile, upper_percentile]))
    if hi > lo:
        norm = (amp - lo) / (hi - lo)
        norm = norm.clamp(0.0, 1.0) if xp is torch else np.clip(norm, 0.0, 1.0)
    else:
        norm = arrays.full_like(amp, 0.5)
    signal = a_min + (a_max - a_min) * norm
    return arrays.where(ok, signal, arrays.full_like(signal, fill_value))


__all__ = [
    "amplitude_to_signal_e",
    "depth_variance_mm2",
    "information_matrix",
    "sigma_depth_mm",
    "tap_jacobian",
    "tap_mean_e",
    "tap_phase_rad",
    "tap_planes",
    "tap_responses",
    "tap_variance_e2",
]
