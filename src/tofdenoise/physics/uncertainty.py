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
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import Any

import numpy as np
import torch

from tofdenoise.physics import _backend as B
from tofdenoise.physics.calibration import SensorCalibration


def _prepare(depth_mm: Any, signal_e: Any) -> tuple[Any, Any, Any, Any]:
    """Convert to a common floating array family/dtype, broadcast, and compute the validity mask."""
    xp = B.namespace(depth_mm, signal_e)
    like = depth_mm if isinstance(depth_mm, torch.Tensor) else signal_e if isinstance(signal_e, torch.Tensor) else None
    d = B.as_float_array(depth_mm, like)
    a = B.as_float_array(signal_e, like if like is not None else None)
    dtype = B.result_dtype(d, a)
    d, a = B.cast(d, dtype), B.cast(a, dtype)
    if xp is torch:
        d, a = torch.broadcast_tensors(d, a)
    else:
        d, a = np.broadcast_arrays(d, a)
    valid = xp.isfinite(d) & xp.isfinite(a) & (d > 0) & (a > 0)
    return xp, d, a, valid


def tap_phase_rad(depth_mm: Any, calib: SensorCalibration) -> Any:
    """psi(D) = 4 pi f D / c_light (paper Eq. 2), D in mm."""
    return depth_mm * calib.phase_per_mm


def _harmonics(psi: Any, num_harmonics: int) -> list[Any]:
    """[cos(psi) .. cos(K psi), sin(psi) .. sin(K psi)] by the Chebyshev recursion
    cos(k psi) = 2 cos(psi) cos((k-1) psi) - cos((k-2) psi) (same for sin): only cos(psi), sin(psi) are
    transcendental."""
    xp = B.namespace(psi)
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


def _axpy_(y: Any, x: Any, alpha: float) -> Any:
    """y += alpha x in place (no temporary for torch)."""
    if isinstance(y, torch.Tensor):
        return y.add_(x, alpha=alpha)
    y += alpha * x
    return y


def _lincomb(feats: list[Any], coefs: np.ndarray, const: float) -> Any:
    """const + sum_j coefs[j] feats[j], skipping zero coefficients."""
    out = None
    for f, c in zip(feats, coefs):
        if c == 0.0:
            continue
        out = f * float(c) if out is None else _axpy_(out, f, float(c))
    if out is None:
        return B.full_like(feats[0], const)
    if const:
        out += const
    return out


def tap_planes(depth_mm: Any, calib: SensorCalibration) -> tuple[list[Any], list[Any]]:
    """Per-tap arrays ([r_n], [c'(psi - theta_n)]), n = 0..N-1, each shaped like depth_mm (paper Eq. 3).

    c(psi - theta_n) = c0 + sum_k A_nk cos(k psi) + B_nk sin(k psi) with constant A, B (TapResponse.tap_matrices),
    so only cos(psi), sin(psi) are transcendental per pixel.
    """
    R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
    feats = _harmonics(tap_phase_rad(depth_mm, calib), calib.tap_response.num_harmonics)
    c0 = calib.tap_response.c0
    r_list = [_lincomb(feats, R[:, n], c0) for n in range(calib.num_taps)]
    g_list = [_lincomb(feats, G[:, n], 0.0) for n in range(calib.num_taps)]
    return r_list, g_list


def tap_responses(depth_mm: Any, calib: SensorCalibration) -> tuple[Any, Any]:
    """(r_n, c'(psi - theta_n)) with the taps on a new last axis of length N (paper Eq. 3)."""
    r_list, g_list = tap_planes(depth_mm, calib)
    return B.stack_last(r_list), B.stack_last(g_list)


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


BLOCK_PIXELS = 32768  # pixels per CPU block: keeps the ~20 temporaries of a block in cache


def _variance_block(d: Any, a: Any, calib: SensorCalibration, R: np.ndarray, G: np.ndarray) -> Any:
    """sigma_D^2 for one block of valid (safe) pixels; see the module docstring for the stable form."""
    feats = _harmonics(d * calib.phase_per_mm, calib.tap_response.num_harmonics)
    c0 = calib.tap_response.c0
    s2 = calib.dark_std_e**2
    planes = []
    s_rr = s_gr = None
    for n in range(calib.num_taps):
        r = _lincomb(feats, R[:, n], c0)  # r_n = c(psi - theta_n)
        g = _lincomb(feats, G[:, n], 0.0)  # c'(psi - theta_n)
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


# Single-pass accumulation of I_DD I_aa - I_Da^2 loses about log2(1 / (1 - rho^2)) bits, rho^2 = I_Da^2 /
# (I_DD I_aa); pixels with rho^2 above this bound are recomputed with the two-pass residual form.
_RHO2_SINGLE_PASS_MAX = 0.75


@lru_cache(maxsize=64)
def _numpy_plan(calib: SensorCalibration) -> tuple[int, list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]]:
    """Constant coefficients for the numpy kernel: for each tap pair (n, n + N/2) (or single tap when N is
    odd) the even- and odd-harmonic coefficients of r_n and c'_n. Returns (K_eff, plan)."""
    R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
    K = calib.tap_response.num_harmonics
    nonzero = [k for k in range(1, K + 1) if calib.tap_response.harmonic(k) != (0.0, 0.0)]
    k_eff = max(nonzero)
    parity = np.array([(j % K) + 1 for j in range(2 * K)]) % 2  # 1 = odd harmonic
    n_taps = calib.num_taps
    half = n_taps // 2 if n_taps % 2 == 0 else None
    plan = []
    for n in range(half if half is not None else n_taps):
        r_odd = np.where(parity == 1, R[:, n], 0.0)
        r_even = np.where(parity == 0, R[:, n], 0.0)
        g_odd = np.where(parity == 1, G[:, n], 0.0)
        g_even = np.where(parity == 0, G[:, n], 0.0)
        plan.append((n, r_odd, r_even, g_odd, g_even))
    return k_eff, plan


def _variance_block_np(d: np.ndarray, a: np.ndarray, calib: SensorCalibration) -> np.ndarray:
    """Numpy kernel: sigma_D^2 for a block of valid pixels, single pass over the taps.

    For even N, tap n + N/2 is tap n shifted by pi: even harmonics keep their sign, odd ones flip, so each
    pair costs one harmonic combination. I_DD, I_Da, I_aa are accumulated (common factor a k dropped) and
    ill-conditioned pixels (rho^2 > 0.75) are recomputed with the two-pass residual form.
    """
    k_eff, plan = _numpy_plan(calib)
    K = calib.tap_response.num_harmonics
    feats = _harmonics(d * calib.phase_per_mm, k_eff)
    # pad to the 2K layout of tap_matrices (cos 1..K, sin 1..K)
    zeros = None
    if k_eff < K:
        zeros = np.zeros_like(d)
        feats = feats[:k_eff] + [zeros] * (K - k_eff) + feats[k_eff:] + [zeros] * (K - k_eff)
    c0 = calib.tap_response.c0
    s2 = calib.dark_std_e**2
    even_n = calib.num_taps % 2 == 0
    s_rr = np.zeros_like(d)
    s_gr = np.zeros_like(d)
    s_gg = np.zeros_like(d)

    def combo(coefs: np.ndarray) -> np.ndarray | None:
        out = None
        for f, c in zip(feats, coefs):
            if c != 0.0:
                out = f * float(c) if out is None else _axpy_(out, f, float(c))
        return out

    def accumulate(r: np.ndarray, g: np.ndarray | None) -> None:
        w = a * r
        w += s2
        np.reciprocal(w, out=w)
        wr = w * r
        wr_r = wr * r
        s_rr.__iadd__(wr_r)
        if g is not None:
            np.multiply(wr, g, out=wr)
            s_gr.__iadd__(wr)
            np.multiply(w, g, out=w)
            w *= g
            s_gg.__iadd__(w)

    for _, r_odd, r_even, g_odd, g_even in plan:
        ro, re_, go, ge = combo(r_odd), combo(r_even), combo(g_odd), combo(g_even)
        base_r = c0 if re_ is None else re_ + c0
        for sign in ((1.0, -1.0) if even_n else (1.0,)):
            if ro is None:
                r = np.broadcast_to(np.asarray(base_r, dtype=d.dtype), d.shape).copy() if re_ is None else base_r.copy()
            elif sign > 0:
                r = ro + base_r
            else:
                r = base_r - ro
            if go is None and ge is None:
                g = None
            elif go is None:
                g = ge
            elif ge is None:
                g = go if sign > 0 else -go
            else:
                g = ge + go if sign > 0 else ge - go
            accumulate(r, g)
    det = s_gg * s_rr
    cross = s_gr * s_gr
    det -= cross
    ill = cross > _RHO2_SINGLE_PASS_MAX * (s_gg * s_rr)
    k = calib.phase_per_mm
    scale = a * a
    scale *= k * k
    det *= scale
    var = np.divide(s_rr, det, out=det)
    if ill.any():
        R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
        var[ill] = _variance_block(d[ill], a[ill], calib, R, G)
    return var


def _variance_numpy(d: np.ndarray, a: np.ndarray, calib: SensorCalibration, workers: int | None = None) -> np.ndarray:
    """Blocked CPU evaluation (numpy): validity, safe values and sigma_D^2 per cache-sized block;
    blocks run on up to torch.get_num_threads() threads (numpy releases the GIL inside its loops)."""
    fd, fa = d.reshape(-1), a.reshape(-1)
    out = np.empty(fd.shape, dtype=fd.dtype)

    def run(start: int) -> None:
        db, ab = fd[start : start + BLOCK_PIXELS], fa[start : start + BLOCK_PIXELS]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            valid = np.isfinite(db) & np.isfinite(ab) & (db > 0) & (ab > 0)
            if valid.all():
                out[start : start + BLOCK_PIXELS] = _variance_block_np(db, ab, calib)
            else:
                one = db.dtype.type(1.0)
                v = _variance_block_np(np.where(valid, db, one), np.where(valid, ab, one), calib)
                v[~valid] = np.nan
                out[start : start + BLOCK_PIXELS] = v

    starts = list(range(0, fd.shape[0], BLOCK_PIXELS))
    workers = min(len(starts), max(1, torch.get_num_threads() if workers is None else workers))
    if workers > 1:
        list(_thread_pool(workers).map(run, starts))
    else:
        for st in starts:
            run(st)
    return out.reshape(d.shape)


_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}


def _thread_pool(workers: int) -> ThreadPoolExecutor:
    """A per-process pool (keyed by pid: threads do not survive fork, e.g. into DataLoader workers)."""
    key = (os.getpid(), workers)
    pool = _POOLS.get(key)
    if pool is None:
        pool = _POOLS[key] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="tofdenoise-sigma")
    return pool


def depth_variance_mm2(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> Any:
    """sigma_D^2 [mm^2] = e_D^T (J^T Sigma^-1 J)^-1 e_D (paper Eq. 16), closed form, NaN where invalid.

    depth_mm and signal_e broadcast together (numpy arrays, torch tensors or scalars; any shape).
    Invalid pixels (depth <= 0, signal <= 0, NaN or inf in either) give NaN and never raise. The result
    has the floating dtype of the inputs (float64 if either is float64) and lives on their device.
    On the CPU the map is evaluated in blocks of BLOCK_PIXELS pixels (cache-sized temporaries, through
    numpy, zero-copy for torch tensors); on other devices in one pass with torch.
    """
    is_t = isinstance(depth_mm, torch.Tensor) or isinstance(signal_e, torch.Tensor)
    device = None
    if is_t:
        like = depth_mm if isinstance(depth_mm, torch.Tensor) else signal_e
        device = like.device
    if is_t and device is not None and device.type != "cpu":
        xp, d, a, valid = _prepare(depth_mm, signal_e)
        R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
        var = _variance_block(torch.where(valid, d, 1.0), torch.where(valid, a, 1.0), calib, R, G)
        return torch.where(valid, var, torch.full_like(var, math.nan))
    if is_t:
        dt = torch.as_tensor(depth_mm, device=device)
        at = torch.as_tensor(signal_e, device=device)
        dtype = torch.float64 if torch.float64 in (dt.dtype, at.dtype) else torch.float32
        dt, at = torch.broadcast_tensors(dt.detach().to(dtype), at.detach().to(dtype))
        var = _variance_numpy(dt.contiguous().numpy(), at.contiguous().numpy(), calib)
        return torch.from_numpy(var)
    d = np.asarray(depth_mm)
    a = np.asarray(signal_e)
    both_f32 = all(x.dtype in (np.float32, np.float16) for x in (d, a))
    dtype = np.float32 if both_f32 else np.float64
    d, a = np.broadcast_arrays(d.astype(dtype, copy=False), a.astype(dtype, copy=False))
    return _variance_numpy(d, a, calib)


def sigma_depth_mm(depth_mm: Any, signal_e: Any, calib: SensorCalibration) -> Any:
    """sigma_D(p) = sqrt(sigma_D^2(p)) [mm] (paper Eq. 17); NaN where invalid. See depth_variance_mm2."""
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
    0, 1) with P_lo / P_hi the `lower_percentile` / `upper_percentile` of the valid amplitudes (so a few
    outliers cannot stretch the scale), then mapped to [signal_min_e, signal_max_e] of the calibration.
    `valid` defaults to finite amplitudes > 0. Percentiles are taken over ALL valid pixels of the array
    (pass one image at a time for per-image normalisation). If P_hi == P_lo the valid pixels map to the
    middle of the interval. Invalid pixels get `fill_value` (NaN by default).
    """
    if not (0.0 <= lower_percentile < upper_percentile <= 100.0):
        raise ValueError(
            f"need 0 <= lower_percentile < upper_percentile <= 100, got {lower_percentile}, {upper_percentile}"
        )
    xp = B.namespace(amplitude)
    amp = B.as_float_array(amplitude)
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
        norm = B.full_like(amp, 0.5)
    signal = a_min + (a_max - a_min) * norm
    return B.where(ok, signal, B.full_like(signal, fill_value))


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
