"""Sensor calibration from captures (paper Sec. III-A and IV).

- Tap response c(x): phase sweep of a uniform planar target; at every phase step psi_s the repeated
  frames are averaged (and over the ROI), the dark offset removed, and a Fourier series of K harmonics is fitted
  by least squares to the points (x = psi_s - theta_n, y = tap_n), convention c0 = 1. A sweep of a target at a
  fixed distance (steps given by ``phase_rad``, e.g. an emitter delay) returns the same signal a at every step:
  one common amplitude, y = a c(x), which recovers every harmonic. A sweep that moves the target (steps given by
  ``distance_mm``) changes the signal from step to step: each step is normalised by its own level
  a_s = mean_n(tap) instead, y = tap_n / a_s, which divides out the harmonics of c at multiples of N
  (``tap_sum_ripple`` measures what it cannot tell apart).
- Dark offset mu_dark and residual noise sigma_dark from emitter-off frames (the paper uses 100):
  mu_dark = mean of all values; sigma_dark^2 = mean over pixels and taps of the temporal variance.
- Signal interval [a_min, a_max]: lower/upper percentiles of the valid per-pixel returned signal (valid: not
  clipped, and above the camera's amplitude threshold in the frame, as the camera itself decides)
  (temporal mean of the DC bin, (mean_n y_n - mu_dark) / c0) of the captured tap stacks.
- Range-aware baseline: sigma(D) = alpha0 + alpha1 D + alpha2 D^2 fitted by least squares to the
  ROI-averaged temporal depth std of an independent planar distance sequence (circular std modulo the
  unambiguous range U: ``circular_depth_stats_mm``).
- Photometric gain ``signal_at_1m_e`` (the physical signal route), when the distance stacks name their target's
  reflectance (``target_reflectance``): the median over valid pixels of a (D / 1 m)^2 / rho. Vignetting is not
  measured (a flat-field capture would be needed): the calibration has none unless it is added by hand.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tofdenoise.physics.calibration import (
    C_LIGHT_MM_PER_S,
    SensorCalibration,
    TapResponse,
    check_calibration_out,
    save_calibration,
)
from tofdenoise.physics.capture_io import INDEX_NAME, CaptureFormatError, clipped_samples, load_stack, read_index
from tofdenoise.physics.simulator import default_min_amplitude_e, demodulate
from tofdenoise.physics.uncertainty import sigma_depth_mm


def _design(x: np.ndarray, num_harmonics: int) -> np.ndarray:
    k = np.arange(1, num_harmonics + 1)
    return np.concatenate([np.ones((x.size, 1)), np.cos(np.outer(x, k)), np.sin(np.outer(x, k))], axis=1)


def fit_tap_response(
    phase_rad: Sequence[float] | np.ndarray,
    mean_taps_e: np.ndarray,
    dark_mean_e: float,
    num_harmonics: int = 3,
    common_amplitude: bool = False,
) -> TapResponse:
    """Least-squares Fourier fit of c(x) from per-step mean taps (S, N) at target phases psi_s (S,), c0 = 1.
    Needs at least 2K+1 distinct sample phases psi_s - theta_n.

    The model (paper Sec. III-A): tap_n - mu_dark = a_s c(psi_s - theta_n), theta_n = 2 pi n / N.

    ``common_amplitude=True`` (a target at a fixed distance: the same returned signal a at every step): one
    linear least-squares fit of a c(x) to every present tap, then divided by its constant term. Every harmonic
    is recovered, those at multiples of N included.

    ``common_amplitude=False`` (the signal changes from step to step, e.g. a moving target): each step is
    normalised by its own level a_s = mean_n(tap_n - mu_dark). Since sum_n cos(k N (psi - theta_n)) =
    N cos(k N psi), a_s = a (c0 + sum_k c_kN cos(k N psi_s) + s_kN sin(k N psi_s)): the harmonics of c at
    multiples of N are divided out with the signal (fitted as ~0) and leak into the others (N = 3,
    c = 1 + 0.5 cos x + 0.08 cos 3x: c3 = 0, c2 = -0.020). ``tap_sum_ripple`` measures them.
    A NaN entry is a missing tap (e.g. clipped at the full well at that step). A step with missing taps has
    no tap mean to normalise by; its a_s is estimated with c(x) instead: a_s and c are refined alternately
    (a_s = sum y c / sum c^2 over the step's present taps, then c from all points) until they settle. Without
    missing taps this is the closed-form fit above.
    """
    psi = np.asarray(phase_rad, dtype=np.float64).reshape(-1)
    taps = np.asarray(mean_taps_e, dtype=np.float64)
    if taps.ndim != 2 or taps.shape[0] != psi.shape[0]:
        raise ValueError(f"mean_taps_e must be (steps, taps) = ({psi.shape[0]}, N), got {taps.shape}")
    n = taps.shape[1]
    if num_harmonics < 1:
        raise ValueError(f"num_harmonics must be >= 1, got {num_harmonics}")
    sig = taps - dark_mean_e
    present = np.isfinite(sig)
    complete = present.all(axis=1)
    if not present.any(axis=1).all():
        bad = int(np.argmin(present.any(axis=1)))
        raise ValueError(f"sweep step {bad}: no tap to fit (every tap missing)")
    a_s = np.where(
        complete,
        np.where(present, sig, 0.0).sum(axis=1) / n,
        np.where(present, sig, 0.0).sum(axis=1) / np.maximum(present.sum(axis=1), 1),
    )[:, None]
    if np.any(a_s <= 0):
        bad = int(np.argmax(a_s[:, 0] <= 0))
        raise ValueError(f"sweep step {bad}: no returned signal above the dark offset (mean tap - dark <= 0)")
    theta = 2.0 * np.pi * np.arange(n) / n
    x_all = psi[:, None] - theta[None, :]
    x = x_all[present]
    design = _design(x, num_harmonics)
    distinct = np.unique(np.round(np.mod(x, 2 * np.pi), 9)).size
    if distinct < design.shape[1]:
        raise ValueError(
            f"phase sweep has {distinct} distinct sample phases; {design.shape[1]} are needed for "
            f"{num_harmonics} harmonics (add phase steps or lower num_harmonics)"
        )
    if common_amplitude:
        coef = np.linalg.lstsq(design, sig[present], rcond=None)[0]
        if not coef[0] > 0:
            raise ValueError(f"the sweep has no returned signal above the dark offset (fitted level {coef[0]:g} e-)")
        coef = coef / coef[0]
    else:
        coef = np.linalg.lstsq(design, (sig / a_s)[present], rcond=None)[0]
    if not complete.all() and not common_amplitude:
        full_design = _design(x_all.reshape(-1), num_harmonics)
        for _ in range(500):
            coef = coef / coef[0]  # convention c0 = 1 (the scale lives in a_s)
            c = (full_design @ coef).reshape(sig.shape)
            num = np.where(present, sig * c, 0.0).sum(axis=1)
            den = np.where(present, c * c, 0.0).sum(axis=1)
            a_new = np.where(complete, a_s[:, 0], num / np.maximum(den, 1e-300))[:, None]
            new = np.linalg.lstsq(design, (sig / a_new)[present], rcond=None)[0]
            done = np.max(np.abs(new / new[0] - coef)) < 1e-12
            a_s, coef = a_new, new
            if done:
                break
    K = num_harmonics
    return TapResponse(
        c0=float(coef[0]), cos=tuple(float(v) for v in coef[1 : K + 1]), sin=tuple(float(v) for v in coef[K + 1 :])
    )


@dataclass(frozen=True)
class TapSumRipple:
    """How the per-step tap sums of a phase sweep vary with the target phase (``tap_sum_ripple``)."""

    #: harmonic order j = k N of c(x) (j <= K) -> (p, q): the tap sums' relative ripple p cos(j psi) + q sin(j psi)
    harmonics: dict[int, tuple[float, float]]
    #: rms of the relative tap sums about that periodic fit: a change of the signal that is no harmonic
    drift: float
    #: complete steps (every tap present) used
    steps: int

    @property
    def amplitude(self) -> float:
        """Largest relative ripple sqrt(p^2 + q^2) over the harmonics (0 without any)."""
        return max((math.hypot(p, q) for p, q in self.harmonics.values()), default=0.0)

    def describe(self) -> str:
        if not self.harmonics:
            return (
                f"no multiple of N among the fitted harmonics of c(x); the signal drifts by {100 * self.drift:.2f} % "
                f"rms over {self.steps} steps"
            )
        parts = ", ".join(f"cos {j}x {p:+.4f}, sin {j}x {q:+.4f}" for j, (p, q) in sorted(self.harmonics.items()))
        return (
            f"per-step tap sums vary by {100 * self.amplitude:.2f} % with period 2 pi / N in the target phase "
            f"({parts}), and drifts by {100 * self.drift:.2f} % rms beyond it over {self.steps} steps"
        )


def tap_sum_ripple(
    phase_rad: Sequence[float] | np.ndarray, mean_taps_e: np.ndarray, dark_mean_e: float, num_harmonics: int
) -> TapSumRipple:
    """The harmonics of c(x) at multiples of N as the per-step tap sums of a sweep show them.

    Tap sums T_s = sum_n (tap_n - mu_dark) of the complete steps, fitted by least squares as
    T_s = T (1 + sum_{j = kN <= K} p_j cos(j psi_s) + q_j sin(j psi_s)). With the model
    tap_n - mu_dark = a c(psi_s - theta_n) and a constant signal a, sum_n c(psi - 2 pi n / N) =
    N (c0 + sum_j c_j cos(j psi) + s_j sin(j psi)), so (p_j, q_j) = (c_j, s_j) / c0: the harmonics that a
    per-step normalisation divides out. ``drift`` (the rms of T_s / T about the fit) is a change of the returned
    signal from step to step that no harmonic explains. Steps with a missing (NaN) tap are left out."""
    psi = np.asarray(phase_rad, dtype=np.float64).reshape(-1)
    taps = np.asarray(mean_taps_e, dtype=np.float64)
    n = taps.shape[1]
    complete = np.isfinite(taps).all(axis=1)
    total = (taps[complete] - dark_mean_e).sum(axis=1)
    psi = psi[complete]
    orders = [j for j in range(n, num_harmonics + 1, n)]
    cols = [np.ones_like(psi)] + [f(j * psi) for j in orders for f in (np.cos, np.sin)]
    if psi.size <= len(cols) or not np.all(total > 0):
        return TapSumRipple({}, math.nan, int(psi.size))
    design = np.stack(cols, axis=1)
    coef, *_ = np.linalg.lstsq(design, total, rcond=None)
    rel = coef[1:] / coef[0]
    resid = total / coef[0] - design @ (coef / coef[0])
    harmonics = {j: (float(rel[2 * i]), float(rel[2 * i + 1])) for i, j in enumerate(orders)}
    return TapSumRipple(harmonics, float(np.sqrt(np.mean(resid**2))), int(psi.size))


def ripple_sigma_error(calib: SensorCalibration, ripple: TapSumRipple, signal_e: float) -> tuple[float, float]:
    """The sigma_D error of a tap response fitted with per-step normalisation, if the tap sums' ripple is a
    harmonic of c(x) and not a change of the signal: (lowest, highest) of sigma_D(fitted c) / sigma_D(c') - 1
    over one unambiguous range at ``signal_e``, where c'(x) = c(x) (1 + sum_j p_j cos(j x) + q_j sin(j x))
    (per-step normalisation fits c'(x) / (1 + r(x)); j psi = j x mod 2 pi for j a multiple of N), refitted to the
    same K harmonics. (0, 0) without a ripple."""
    if not ripple.harmonics:
        return 0.0, 0.0
    tr = calib.tap_response
    k = len(tr.cos)
    x = np.linspace(0.0, 2.0 * np.pi, 4 * (k + max(ripple.harmonics)) + 16, endpoint=False)
    r = sum(p * np.cos(j * x) + q * np.sin(j * x) for j, (p, q) in ripple.harmonics.items())
    coef = np.linalg.lstsq(_design(x, k), np.asarray(tr.value(x), dtype=np.float64) * (1.0 + r), rcond=None)[0]
    coef = coef / coef[0]
    corrected = calib.replace(
        tap_response=TapResponse(1.0, tuple(float(v) for v in coef[1 : k + 1]), tuple(float(v) for v in coef[k + 1 :]))
    )
    depth = np.linspace(0.0, calib.unambiguous_range_mm, 257)[1:]
    signal = np.full_like(depth, float(signal_e))
    ratio = sigma_depth_mm(depth, signal, calib) / sigma_depth_mm(depth, signal, corrected) - 1.0
    return float(np.min(ratio)), float(np.max(ratio))


def estimate_dark(stacks_e: Sequence[np.ndarray]) -> tuple[float, float]:
    """(mu_dark, sigma_dark) [e-] from emitter-off tap stacks (F, N, H, W), all frames pooled."""
    total = 0.0
    count = 0
    var_sum = 0.0
    var_count = 0
    for s in stacks_e:
        total += float(s.sum())
        count += s.size
        var_sum += float(s.var(axis=0, ddof=1).sum())
        var_count += int(np.prod(s.shape[1:]))
    if count == 0:
        raise ValueError("no dark frames")
    return total / count, math.sqrt(var_sum / var_count)


def signal_interval(
    signal_e: np.ndarray, lower_percentile: float = 1.0, upper_percentile: float = 99.0
) -> tuple[float, float]:
    """[a_min, a_max] = percentiles of the valid (finite, > 0) returned-signal samples."""
    s = np.asarray(signal_e, dtype=np.float64).reshape(-1)
    s = s[np.isfinite(s) & (s > 0)]
    if s.size == 0:
        raise ValueError("no valid returned-signal samples to set [signal_min_e, signal_max_e]")
    lo, hi = np.percentile(s, [lower_percentile, upper_percentile])
    return float(lo), float(hi)


def fit_range_sigma(distance_mm: Sequence[float], std_mm: Sequence[float]) -> tuple[float, float, float]:
    """Least squares sigma(D) = alpha0 + alpha1 D + alpha2 D^2 (D in mm) -> (alpha0, alpha1, alpha2): the paper's
    range-aware Gaussian baseline. Every distance and std must be finite (a NaN std, e.g. of a distance with no
    valid pixel, would make every coefficient NaN): a ValueError names the first bad point."""
    d = np.asarray(distance_mm, dtype=np.float64)
    s = np.asarray(std_mm, dtype=np.float64)
    if d.shape != s.shape or d.ndim != 1:
        raise ValueError("distance_mm and std_mm must be 1-D of the same length")
    bad = ~(np.isfinite(d) & np.isfinite(s))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"the range-aware fit needs finite distances and stds; point {i} is (distance {float(d[i])!r} mm, std "
            f"{float(s[i])!r} mm) ({int(bad.sum())} of {d.size} points non-finite): leave out the distances without a "
            "measured std"
        )
    if np.unique(d).size < 3:
        raise ValueError(f"the range-aware fit needs at least 3 distinct distances, got {np.unique(d).size}")
    # centred/scaled for conditioning, then converted back to the plain polynomial
    d0, ds = d.mean(), d.std() or 1.0
    u = (d - d0) / ds
    b2, b1, b0 = np.polyfit(u, s, 2)
    a2 = b2 / ds**2
    a1 = b1 / ds - 2 * b2 * d0 / ds**2
    a0 = b0 - b1 * d0 / ds + b2 * d0**2 / ds**2
    return float(a0), float(a1), float(a2)


def circular_depth_stats_mm(
    depth_frames_mm: np.ndarray, unambiguous_range_mm: float | None, ddof: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel temporal mean and std of depths that a camera measures modulo its unambiguous range.

    The camera measures the phase psi = 4 pi f D / c = 2 pi D / U (paper Eq. 2) only modulo 2 pi, so its depth is
    D mod U with U = c / (2 f) (``SensorCalibration.unambiguous_range_mm``): a pixel at 1990 mm of a U = 1999 mm
    camera reports some frames near 1990 mm and others near 0 mm. Circular statistics over the frames (axis 0):

        m = U / (2 pi) arg( mean_t exp(i 2 pi D_t / U) )                (circular mean)
        delta_t = ((D_t - m + U/2) mod U) - U/2  in [-U/2, U/2)          (deviation, wrapped)
        mean = (m + mean_t delta_t) mod U,   std = sqrt( sum_t (delta_t - mean_t delta_t)^2 / (F - ddof) )

    i.e. the samples unwrapped around the circular mean, m + delta_t, and their ordinary mean and std: exactly the
    std of the unwrapped depths whenever every frame lies within U/2 of the circular mean (a temporal noise far
    below U), and the ordinary mean and std when no frame wrapped. ``unambiguous_range_mm=None``: depths already
    unwrapped (ordinary mean and std). Returns (mean, std), each of shape ``depth_frames_mm.shape[1:]``."""
    d = np.asarray(depth_frames_mm, dtype=np.float64)
    if unambiguous_range_mm is None:
        return d.mean(axis=0), d.std(axis=0, ddof=ddof)
    u = float(unambiguous_range_mm)
    if not (math.isfinite(u) and u > 0):
        raise ValueError(f"unambiguous_range_mm must be a finite number > 0, got {unambiguous_range_mm!r}")
    turn = 2.0 * np.pi / u
    centre = np.mod(np.angle(np.exp(1j * turn * d).mean(axis=0)) / turn, u)
    delta = np.mod(d - centre + 0.5 * u, u) - 0.5 * u
    return np.mod(centre + delta.mean(axis=0), u), delta.std(axis=0, ddof=ddof)


def temporal_std_roi_mm(
    depth_frames_mm: np.ndarray, valid: np.ndarray | None = None, *, unambiguous_range_mm: float | None
) -> tuple[float, int]:
    """ROI mean of the per-pixel temporal depth std (pixels valid in every frame) and the pixel count.

    The std is circular modulo the unambiguous range (``circular_depth_stats_mm``): a depth near U wraps to
    near 0 in some frames, and the linear std of those wrapped frames is not the camera's noise (cam75,
    U = 1999 mm, at 1900 mm: 0.1 % wrapped pixel-frames gave 26.1 mm against 16.5 mm unwrapped).
    ``unambiguous_range_mm=None`` only for depths already unwrapped."""
    d = np.asarray(depth_frames_mm, dtype=np.float64)
    ok = np.all(np.isfinite(d) & (d > 0), axis=0)
    if valid is not None:
        ok &= np.all(np.asarray(valid, dtype=bool), axis=0)
    if not ok.any():
        return math.nan, 0
    _, std = circular_depth_stats_mm(d[:, ok], unambiguous_range_mm)
    return float(std.mean()), int(ok.sum())


#: a (step, tap) whose samples are clipped more often than this is treated as missing (its unclipped
#: samples would be a truncated, biased remainder); at or below it, its unclipped samples are averaged
MAX_CLIPPED_TAP_FRACTION: float = 0.5
#: a sweep or distance step needs at least this fraction of unclipped samples (sweep: tap samples;
#: distances: pixels unclipped in every frame), else it is an error naming the file
MIN_UNCLIPPED_FRACTION: float = 0.1
#: how ``calibrate_from_folders`` fits the tap response over the sweep's steps (``fit_tap_response``)
SWEEP_AMPLITUDES: tuple[str, ...] = ("auto", "common", "per-step")
#: a per-step fit whose tap sums' ripple would change sigma_D by this fraction (``ripple_sigma_error``) is a warning
RIPPLE_SIGMA_WARNING: float = 0.01
#: a common-amplitude fit whose tap sums drift by more than this (rms, relative) is a warning
SWEEP_DRIFT_WARNING: float = 0.01
#: the paper's number of emitter-off frames; fewer are used, with a warning (at least 2: a temporal variance)
MIN_DARK_FRAMES: int = 100


def _check_same_size(index: Any, stacks: list[np.ndarray]) -> None:
    """Every stack of a capture folder images the same (H, W) region, else an error naming the odd file."""
    for entry, stack in zip(index.stacks, stacks):
        if stack.shape[-2:] != stacks[0].shape[-2:]:
            raise CaptureFormatError(
                f"{index.folder / entry['file']}: frames of {stack.shape[-2]}x{stack.shape[-1]} px; "
                f"{index.stacks[0]['file']} has {stacks[0].shape[-2]}x{stacks[0].shape[-1]} px"
            )


@dataclass
class CalibrationReport:
    calibration: SensorCalibration
    sweep_points: int
    dark_frames: int
    range_points: list[tuple[float, float]]
    #: tap samples at the full well (or the dtype's maximum) left out of the fit, and all tap samples read
    clipped_samples: int = 0
    tap_samples: int = 0
    #: file -> clipped tap samples, for the files with any
    clipped_by_file: dict[str, int] = field(default_factory=dict)
    #: what the calibration was made from that falls short of the procedure (e.g. fewer dark frames than 100)
    warnings: list[str] = field(default_factory=list)
    #: how the tap response was fitted: "common" (one amplitude over the sweep) or "per-step" (each step
    #: normalised by its own level); see ``fit_tap_response``
    sweep_amplitude: str = "common"
    #: the per-step tap sums' variation with the target phase (``tap_sum_ripple``)
    ripple: TapSumRipple | None = None

    def tap_response_summary(self) -> str:
        """How the tap response was fitted and what the sweep's tap sums show, in one line (the file header)."""
        how = {
            "common": "one common amplitude over the sweep (a fixed target), harmonics at multiples of N fitted",
            "per-step": "each step normalised by its own level (a moving target), harmonics at multiples of N "
            "not recoverable",
        }[self.sweep_amplitude]
        return how + ("" if self.ripple is None else f"; {self.ripple.describe()}")

    def clipping_summary(self) -> str:
        if not self.clipped_samples:
            return "no clipped tap samples"
        pct = 100.0 * self.clipped_samples / max(self.tap_samples, 1)
        return (
            f"{self.clipped_samples} of {self.tap_samples} tap samples ({pct:.2f} %) clipped at the full well "
            f"in {len(self.clipped_by_file)} file(s), left out of the fit"
        )


@dataclass
class _ClipTally:
    """Clipped and total tap samples over the files of a calibration, and the clipped count per file."""

    clipped: int = 0
    total: int = 0
    by_file: dict[str, int] = field(default_factory=dict)

    def add(self, path: Path, clipped: np.ndarray) -> None:
        n = int(clipped.sum())
        self.clipped += n
        self.total += clipped.size
        if n:
            self.by_file[str(path)] = n


def _phase_of(entry: dict, freq: float) -> float:
    if "phase_rad" in entry:
        return float(entry["phase_rad"])
    return 4.0 * math.pi * freq * float(entry["distance_mm"]) / C_LIGHT_MM_PER_S


def _sweep_step(
    taps: np.ndarray, clipped: np.ndarray, path: Path, min_unclipped_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """One sweep step: ROI mean of each tap over its unclipped samples (N,) and the per-pixel temporal mean
    of each tap over its unclipped frames (N, H, W), NaN where the tap is clipped too often to be used."""
    kept = 1.0 - float(clipped.mean())
    if kept < min_unclipped_fraction:
        raise CaptureFormatError(
            f"{path}: {100 * (1 - kept):.1f} % of the tap samples are clipped (at the full well or the dtype's "
            f"maximum); at least {100 * min_unclipped_fraction:.0f} % must be unclipped. Capture this step with a "
            f"shorter exposure or a darker target"
        )
    ok = ~clipped
    frac_per_tap = clipped.mean(axis=(0, 2, 3))
    counts = ok.sum(axis=(0, 2, 3))
    means = np.where(
        (frac_per_tap <= MAX_CLIPPED_TAP_FRACTION) & (counts > 0),
        np.where(ok, taps, 0.0).sum(axis=(0, 2, 3)) / np.maximum(counts, 1),
        np.nan,
    )
    if np.isfinite(means).sum() < 2:
        raise CaptureFormatError(
            f"{path}: fewer than 2 taps with unclipped samples (clipped fraction per tap "
            f"{np.round(frac_per_tap, 3).tolist()}); capture this step with a shorter exposure"
        )
    n_ok = ok.sum(axis=0)  # (N, H, W)
    with np.errstate(invalid="ignore", divide="ignore"):
        pixel = np.where(ok, taps, 0.0).sum(axis=0) / n_ok
    pixel = np.where(n_ok >= MAX_CLIPPED_TAP_FRACTION * taps.shape[0], pixel, np.nan).astype(np.float32)
    return means, pixel


def _pixel_signal(pixel_taps_e: np.ndarray, psi: float, dark_mean: float, response: TapResponse) -> np.ndarray:
    """Per-pixel returned signal a = sum_n (m_n - mu_dark) / sum_n c(psi - theta_n) over the taps m_n present
    (all taps: the mean over taps divided by c0, the usual DC-bin estimate)."""
    n = pixel_taps_e.shape[0]
    theta = 2.0 * np.pi * np.arange(n) / n
    c = np.asarray(response.value(psi - theta), dtype=np.float64)
    m = pixel_taps_e.astype(np.float64) - dark_mean
    present = np.isfinite(m)
    with np.errstate(invalid="ignore", divide="ignore"):
        a = np.where(present, m, 0.0).sum(axis=0) / np.where(present, c[:, None, None], 0.0).sum(axis=0)
    return np.where(present.any(axis=0), a, np.nan).reshape(-1)


def target_reflectance(entry: dict, shape: tuple[int, ...], path: Path) -> np.ndarray | None:
    """The reflectance map (H, W) of a distance stack's target from its index entry, or None when it has none:
    ``"reflectance": rho`` (a uniform board) or ``"reflectance_chart": [dark, white]`` (a grey chart whose
    columns run log-spaced from dark to white). With it ``calibrate`` measures the photometric gain
    ``signal_at_1m_e`` (the physical signal route)."""
    if "reflectance" in entry:
        rho = entry["reflectance"]
        if isinstance(rho, bool) or not isinstance(rho, (int, float)) or not 0 < rho <= 10:
            raise CaptureFormatError(f"{path}: index field 'reflectance' must be a number in (0, 10], got {rho!r}")
        return np.full(shape, float(rho))
    if "reflectance_chart" in entry:
        chart = entry["reflectance_chart"]
        ok = isinstance(chart, (list, tuple)) and len(chart) == 2
        ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= 10 for v in chart)
        if not ok:
            raise CaptureFormatError(
                f"{path}: index field 'reflectance_chart' must be [dark, white] reflectances in (0, 10], got {chart!r}"
            )
        return np.geomspace(float(chart[0]), float(chart[1]), shape[-1])[None, :] * np.ones(shape)
    return None


def calibrate_from_folders(
    sweep_dir: str | os.PathLike[str],
    dark_dir: str | os.PathLike[str],
    distances_dir: str | os.PathLike[str] | None = None,
    num_harmonics: int = 3,
    full_well_e: float | None = None,
    lower_percentile: float = 1.0,
    upper_percentile: float = 99.0,
    min_unclipped_fraction: float = MIN_UNCLIPPED_FRACTION,
    sweep_amplitude: str = "auto",
) -> CalibrationReport:
    """Run the whole calibration procedure on capture folders (format: tofdenoise.physics.capture_io).

    Tap samples at the full well (``full_well_e``, else the sweep index's) or at their dtype's maximum are
    clipped: they are left out of every estimate and counted in the report. Every error names the file or
    folder it comes from.

    ``sweep_amplitude`` (``fit_tap_response``): "common" (a target at a fixed distance: the same returned signal
    at every step; every harmonic of c(x) is fitted), "per-step" (the signal changes from step to step: each step
    normalised by its own level; harmonics at multiples of N cannot be recovered), or "auto": "common" when every
    sweep entry gives ``phase_rad`` (the phase set by an emitter delay), "per-step" when any gives only
    ``distance_mm`` (the target moved). A "per-step" fit whose tap sums vary with period 2 pi / N enough to change
    sigma_D by 1 % or more, or a "common" fit whose signal drifts by more than 1 % rms, is a warning.
    """
    if sweep_amplitude not in SWEEP_AMPLITUDES:
        raise ValueError(f"sweep_amplitude must be one of {', '.join(SWEEP_AMPLITUDES)}, got {sweep_amplitude!r}")
    dark_idx = read_index(dark_dir, "dark")
    dark_stacks = [load_stack(dark_idx, e["file"], ndim=(4,)) for e in dark_idx.stacks]
    try:
        dark_mean, dark_std = estimate_dark(dark_stacks)
    except ValueError as exc:
        raise CaptureFormatError(f"{dark_idx.folder}: {exc}") from None
    if not (dark_std > 0):
        raise CaptureFormatError(
            f"{dark_idx.folder}: the dark frames have no temporal noise (sigma_dark = {dark_std:g} e-, mean "
            f"{dark_mean:g} e-): constant frames (all zero?) are not emitter-off captures of a sensor"
        )
    dark_frames = sum(s.shape[0] for s in dark_stacks)
    _check_same_size(dark_idx, dark_stacks)
    del dark_stacks
    warnings = []
    if dark_frames < MIN_DARK_FRAMES:
        warnings.append(
            f"{dark_idx.folder}: {dark_frames} dark frames used; the paper's procedure uses {MIN_DARK_FRAMES} "
            f"(sigma_dark from {dark_frames} frames has a relative standard error of about "
            f"{100 / math.sqrt(2 * max(dark_frames - 1, 1)) / math.sqrt(dark_idx.num_taps):.1f} % per pixel)"
        )

    sweep_idx = read_index(sweep_dir, "sweep")
    sweep_index_path = Path(sweep_dir) / INDEX_NAME
    if sweep_idx.num_taps != dark_idx.num_taps:
        raise CaptureFormatError(
            f"{sweep_index_path}: num_taps={sweep_idx.num_taps} differs from the dark folder's {dark_idx.num_taps}"
        )
    fw = full_well_e if full_well_e is not None else sweep_idx.full_well_e
    freq = float(sweep_idx.modulation_frequency_hz)  # type: ignore[arg-type]
    phases, means, pixel_taps = [], [], []
    tally = _ClipTally()
    files = []
    sweep_size = None
    for e in sweep_idx.stacks:
        path = sweep_idx.folder / e["file"]
        taps = load_stack(sweep_idx, e["file"], ndim=(4,))
        if sweep_size is None:
            sweep_size = taps.shape[2:]
        elif taps.shape[2:] != sweep_size:
            raise CaptureFormatError(
                f"{path}: frames of {taps.shape[2]}x{taps.shape[3]} px; the sweep's first stack has "
                f"{sweep_size[0]}x{sweep_size[1]} px (every step must image the same region)"
            )
        clipped = clipped_samples(sweep_idx, e["file"], taps, fw)
        tally.add(path, clipped)
        step_means, pixel = _sweep_step(taps, clipped, path, min_unclipped_fraction)
        phases.append(_phase_of(e, freq))
        means.append(step_means)
        pixel_taps.append(pixel)
        files.append(path)
    if fw is None:
        raise CaptureFormatError(
            f"{sweep_index_path}: no 'full_well_e' in the sweep index; pass the sensor's full-well "
            f"capacity (--full-well-e)"
        )
    try:
        if sweep_amplitude == "auto":
            sweep_amplitude = "common" if all("phase_rad" in e for e in sweep_idx.stacks) else "per-step"
        tap_response = fit_tap_response(
            np.array(phases), np.stack(means), dark_mean, num_harmonics, common_amplitude=sweep_amplitude == "common"
        )
    except ValueError as exc:
        msg = str(exc)
        match = re.match(r"sweep step (\d+): (.*)", msg)
        if match:
            path = files[int(match.group(1))]
            dtype = np.load(path, mmap_mode="r", allow_pickle=False).dtype
            msg = (
                f"{path}: {match.group(2)} (stack dtype {dtype}, units {sweep_idx.units!r}; dark offset "
                f"{dark_mean:g} e- from {dark_idx.folder})"
            )
        else:
            msg = f"{sweep_idx.folder}: {msg}"
        raise CaptureFormatError(msg) from None
    if not tap_response.contrast > 0:
        raise CaptureFormatError(
            f"{sweep_idx.folder}: the fitted tap response has no contrast "
            f"({tap_response}); the sweep does not modulate the taps"
        )
    signal_samples = [_pixel_signal(px, psi, dark_mean, tap_response) for px, psi in zip(pixel_taps, phases)]
    del pixel_taps

    gain = sweep_idx.adc_gain_e_per_dn if sweep_idx.adc_gain_e_per_dn is not None else dark_idx.adc_gain_e_per_dn

    try:
        partial = SensorCalibration(
            num_taps=sweep_idx.num_taps,
            modulation_frequency_hz=freq,
            tap_response=tap_response,
            dark_mean_e=dark_mean,
            dark_std_e=dark_std,
            signal_min_e=1.0,
            signal_max_e=2.0,
            full_well_e=float(fw),
            adc_gain_e_per_dn=gain,
            range_sigma_mm=None,
        )
    except ValueError as exc:
        raise CaptureFormatError(f"calibration from {sweep_idx.folder} and {dark_idx.folder}: {exc}") from None

    range_points: list[tuple[float, float]] = []
    gain_samples: list[np.ndarray] = []
    if distances_dir is not None:
        dist_idx = read_index(distances_dir, "distances")
        if dist_idx.num_taps != partial.num_taps:
            raise CaptureFormatError(
                f"{Path(distances_dir) / INDEX_NAME}: num_taps={dist_idx.num_taps} differs from the sweep's "
                f"{partial.num_taps}"
            )
        for e in dist_idx.stacks:
            path = dist_idx.folder / e["file"]
            arr = load_stack(dist_idx, e["file"], ndim=(3, 4))
            valid = None
            if arr.ndim == 4:
                clipped = clipped_samples(dist_idx, e["file"], arr, fw)
                tally.add(path, clipped)
                valid = ~clipped.any(axis=1)  # (F, H, W): pixel-frames without a clipped tap
                kept = float(valid.all(axis=0).mean())
                if kept < min_unclipped_fraction:
                    raise CaptureFormatError(
                        f"{path}: only {100 * kept:.1f} % of the pixels are unclipped in every frame (taps at the "
                        f"full well or the dtype's maximum); at least {100 * min_unclipped_fraction:.0f} % are "
                        f"needed. Capture this distance with a shorter exposure"
                    )
                depth, amplitude = demodulate(torch.from_numpy(arr), partial, tap_axis=1)
                depth_np = depth.numpy()
                # the camera's own validity: a pixel-frame below the amplitude threshold has no depth
                valid = valid & (amplitude.numpy() >= default_min_amplitude_e(partial))
                n_ok = valid.sum(axis=0)
                with np.errstate(invalid="ignore", divide="ignore"):
                    pix = np.where(valid[:, None], arr, 0.0).sum(axis=(0, 1)) / (n_ok * arr.shape[1])
                pixel_signal = np.where(n_ok > 0, pix - dark_mean, np.nan) / tap_response.c0
                signal_samples.append(pixel_signal.reshape(-1))
                reflectance = target_reflectance(e, pixel_signal.shape, path)
                if reflectance is not None:  # K = a (D / 1 m)^2 / rho of every valid pixel of a known target
                    gain_samples.append((pixel_signal * (float(e["distance_mm"]) / 1000.0) ** 2 / reflectance).ravel())
            else:
                depth_np = arr
            std, _ = temporal_std_roi_mm(depth_np, valid, unambiguous_range_mm=partial.unambiguous_range_mm)
            if not math.isfinite(std):
                raise CaptureFormatError(f"{path}: no pixel valid in every frame")
            range_points.append((float(e["distance_mm"]), std))
    try:
        a_min, a_max = signal_interval(np.concatenate(signal_samples), lower_percentile, upper_percentile)
    except ValueError as exc:
        where = f"{sweep_idx.folder}" + (f" and {distances_dir}" if distances_dir is not None else "")
        raise CaptureFormatError(f"{where}: {exc}") from None
    if a_max <= a_min:
        a_max = a_min * (1.0 + 1e-6)
    ripple = tap_sum_ripple(np.array(phases), np.stack(means), dark_mean, num_harmonics)
    if sweep_amplitude == "per-step" and ripple.harmonics:
        a_ref = math.sqrt(a_min * a_max)
        lo, hi = ripple_sigma_error(partial.replace(signal_min_e=a_min, signal_max_e=a_max), ripple, a_ref)
        if max(-lo, hi) >= RIPPLE_SIGMA_WARNING:
            warnings.append(
                f"{sweep_idx.folder}: {ripple.describe()}. Each step was normalised by its own level (per-step: a "
                "signal that changes from step to step, e.g. a moving target), which cannot tell a harmonic of c(x) "
                f"at a multiple of N = {partial.num_taps} from a change of the returned signal: such harmonics are "
                "fitted as 0. If this variation is one, sigma_D is "
                f"off by {100 * lo:+.1f} % to {100 * hi:+.1f} % over the unambiguous range at a = {a_ref:.0f} e-; "
                "sweep a target at a fixed distance (phase_rad steps, an emitter delay) to fit it"
            )
    elif sweep_amplitude == "common" and math.isfinite(ripple.drift) and ripple.drift > SWEEP_DRIFT_WARNING:
        warnings.append(
            f"{sweep_idx.folder}: the returned signal changes from step to step by {100 * ripple.drift:.2f} % rms "
            "beyond any harmonic of c(x); the tap response was fitted with one common amplitude (a target at a "
            "fixed distance). If the target moved, give the steps' distance_mm instead of phase_rad (or "
            "--sweep-amplitude per-step)"
        )
    try:
        alphas = fit_range_sigma(*zip(*range_points)) if range_points else None
    except ValueError as exc:
        raise CaptureFormatError(f"{distances_dir}: {exc}") from None
    gains = np.concatenate(gain_samples) if gain_samples else np.array([])
    gains = gains[np.isfinite(gains) & (gains > 0)]
    k_1m = float(np.median(gains)) if gains.size else None
    try:
        calib = partial.replace(signal_min_e=a_min, signal_max_e=a_max, range_sigma_mm=alphas, signal_at_1m_e=k_1m)
    except ValueError as exc:
        if alphas is None or "range_sigma_mm" not in str(exc):
            raise
        measured = ", ".join(f"{d:g} mm: {s:.3g} mm" for d, s in range_points)
        raise CaptureFormatError(
            f"{distances_dir}: the range-aware baseline fitted to the measured temporal std ({measured}) is not a "
            f"usable noise model: {exc}"
        ) from None
    return CalibrationReport(
        calibration=calib,
        sweep_points=len(phases),
        dark_frames=dark_frames,
        range_points=range_points,
        clipped_samples=tally.clipped,
        tap_samples=tally.total,
        clipped_by_file=tally.by_file,
        warnings=warnings,
        sweep_amplitude=sweep_amplitude,
        ripple=ripple,
    )


def calibrate_to_file(
    sweep_dir: str | os.PathLike[str],
    dark_dir: str | os.PathLike[str],
    distances_dir: str | os.PathLike[str] | None,
    out: str | os.PathLike[str],
    **kwargs: Any,
) -> tuple[CalibrationReport, Path]:
    """``tofdenoise sensor calibrate``'s job: ``calibrate_from_folders`` (``kwargs``: its settings) written to ``out``
    (.yaml or .json) with a header naming the capture folders, the clipping and the warnings. ``out`` is checked
    (a file name, not a folder) before the calibration is computed. Returns the report and the written path."""
    check_calibration_out(out)
    report = calibrate_from_folders(sweep_dir, dark_dir, distances_dir, **kwargs)
    header = (
        f"Calibrated by tofdenoise sensor calibrate\nsweep: {sweep_dir} ({report.sweep_points} steps)\n"
        f"dark: {dark_dir} ({report.dark_frames} frames)\ndistances: {distances_dir or '-'}\n"
        f"clipping: {report.clipping_summary()}\ntap response: {report.tap_response_summary()}"
        + "".join(f"\nwarning: {w}" for w in report.warnings)
    )
    return report, save_calibration(report.calibration, out, header=header)


__all__ = [
    "MIN_DARK_FRAMES",
    "MAX_CLIPPED_TAP_FRACTION",
    "target_reflectance",
    "MIN_UNCLIPPED_FRACTION",
    "RIPPLE_SIGMA_WARNING",
    "SWEEP_AMPLITUDES",
    "SWEEP_DRIFT_WARNING",
    "TapSumRipple",
    "ripple_sigma_error",
    "tap_sum_ripple",
    "CalibrationReport",
    "calibrate_from_folders",
    "calibrate_to_file",
    "circular_depth_stats_mm",
    "estimate_dark",
    "fit_range_sigma",
    "fit_tap_response",
    "signal_interval",
    "temporal_std_roi_mm",
]
