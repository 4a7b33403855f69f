"""sigma_D on the CPU through numpy: the single-pass block and its blocked, threaded driver.

The route :func:`tofdenoise.physics.uncertainty.depth_variance_mm2` takes for numpy arrays and CPU tensors (the
route map is in that module's docstring). Per pixel, with w_n = 1 / (a r_n + sigma_dark^2) and the common factor
a k (k = 4 pi f / c_light) taken out of the sums (paper Eqs. 13-17):

    S_gg = sum_n w_n r'_n^2,  S_gr = sum_n w_n r'_n r_n,  S_rr = sum_n w_n r_n^2,
    sigma_D^2 = S_rr / ((S_gg S_rr - S_gr^2) (a k)^2),

accumulated in ONE pass over the taps; for even N, tap n + N/2 is tap n shifted by pi, so each pair of taps
costs one harmonic combination (even harmonics keep their sign, odd ones flip). The determinant
S_gg S_rr - S_gr^2 loses about log2(1 / (1 - rho^2)) bits, rho^2 = S_gr^2 / (S_gg S_rr): pixels with
rho^2 > RHO2_SINGLE_PASS_MAX are recomputed with the two-pass residual form
(:func:`tofdenoise.physics.sigma_kernels.variance_two_pass`). Maps are cut into blocks of BLOCK_PIXELS pixels so
the ~20 temporaries of a block stay in cache; the blocks run on a per-process thread pool.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache

import numpy as np
import torch

from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.physics.sigma_kernels import axpy_, harmonics, variance_two_pass

__all__ = ["BLOCK_PIXELS", "RHO2_SINGLE_PASS_MAX", "depth_variance_numpy", "variance_block"]

BLOCK_PIXELS = 32768  # pixels per CPU block: keeps the ~20 temporaries of a block in cache

# Single-pass accumulation of I_DD I_aa - I_Da^2 loses about log2(1 / (1 - rho^2)) bits, rho^2 = I_Da^2 /
# (I_DD I_aa); pixels with rho^2 above this bound are recomputed with the two-pass residual form.
RHO2_SINGLE_PASS_MAX = 0.75


@lru_cache(maxsize=64)
def _numpy_plan(
    calib: SensorCalibration,
) -> tuple[int, list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]]:
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


def variance_block(d: np.ndarray, a: np.ndarray, calib: SensorCalibration) -> np.ndarray:
    """sigma_D^2 [mm^2] for a block of valid pixels (numpy), single pass over the taps.

    For even N, tap n + N/2 is tap n shifted by pi: even harmonics keep their sign, odd ones flip, so each
    pair costs one harmonic combination. I_DD, I_Da, I_aa are accumulated (common factor a k dropped) and
    ill-conditioned pixels (rho^2 > 0.75) are recomputed with the two-pass residual form.
    """
    k_eff, plan = _numpy_plan(calib)
    K = calib.tap_response.num_harmonics
    feats = harmonics(d * calib.phase_per_mm, k_eff)
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
                out = f * float(c) if out is None else axpy_(out, f, float(c))
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
        for sign in (1.0, -1.0) if even_n else (1.0,):
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
    ill = cross > RHO2_SINGLE_PASS_MAX * (s_gg * s_rr)
    k = calib.phase_per_mm
    scale = a * a
    scale *= k * k
    det *= scale
    var = np.divide(s_rr, det, out=det)
    if ill.any():
        R, G, _, _ = calib.tap_response.tap_matrices(calib.num_taps)
        var[ill] = variance_two_pass(d[ill], a[ill], calib, R, G)
    return var


def depth_variance_numpy(
    d: np.ndarray, a: np.ndarray, calib: SensorCalibration, workers: int | None = None
) -> np.ndarray:
    """sigma_D^2 [mm^2] of a numpy map (d, a of one shape and float dtype), NaN where invalid: validity, safe
    values and :func:`variance_block` per cache-sized block of BLOCK_PIXELS pixels; blocks run on up to
    ``workers`` (default torch.get_num_threads()) threads (numpy releases the GIL inside its loops)."""
    fd, fa = d.reshape(-1), a.reshape(-1)
    out = np.empty(fd.shape, dtype=fd.dtype)

    def run(start: int) -> None:
        db, ab = fd[start : start + BLOCK_PIXELS], fa[start : start + BLOCK_PIXELS]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            valid = np.isfinite(db) & np.isfinite(ab) & (db > 0) & (ab > 0)
            if valid.all():
                out[start : start + BLOCK_PIXELS] = variance_block(db, ab, calib)
            else:
                one = db.dtype.type(1.0)
                v = variance_block(np.where(valid, db, one), np.where(valid, ab, one), calib)
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
