"""Sensor calibration from captures (paper Sec. III-A and IV).

- Tap response c(x): phase sweep of a uniform planar target; at every phase step psi_s the repeated
  frames are averaged (and over the ROI), the dark offset removed, each step normalised by its own
  signal level a_s = mean_n(tap) (convention c0 = 1, which also cancels a signal that changes with the
  target distance), and a Fourier series of K harmonics is fitted by least squares to the points
  (x = psi_s - theta_n, y = tap_n / a_s).
- Dark offset mu_dark and residual noise sigma_dark from emitter-off frames (the paper uses 100):
  mu_dark = mean of all values; sigma_dark^2 = mean over pixels and taps of the temporal variance.
- Signal interval [a_min, a_max]: lower/upper percentiles of the valid per-pixel returned signal
  (temporal mean of the DC bin, (mean_n y_n - mu_dark) / c0) of the captured tap stacks.
- Range-aware baseline: sigma(D) = alpha0 + alpha1 D + alpha2 D^2 fitted by least squares to the
  ROI-averaged temporal depth std of an independent planar distance sequence.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tofdenoise.physics.calibration import C_LIGHT_MM_PER_S, SensorCalibration, TapResponse
from tofdenoise.physics.capture_io import CaptureFormatError, load_stack, read_index
from tofdenoise.physics.simulator import demodulate


def fit_tap_response(
    phase_rad: Sequence[float] | np.ndarray,
    mean_taps_e: np.ndarray,
    dark_mean_e: float,
    num_harmonics: int = 3,
) -> TapResponse:
    """Least-squares Fourier fit of c(x) from per-step mean taps (S, N) at target phases psi_s (S,).

    Each step is normalised by its signal level a_s = mean_n(tap_n - mu_dark), so c0 ~ 1.
    Needs at least 2K+1 distinct sample phases psi_s - theta_n.
    """
    psi = np.asarray(phase_rad, dtype=np.float64).reshape(-1)
    taps = np.asarray(mean_taps_e, dtype=np.float64)
    if taps.ndim != 2 or taps.shape[0] != psi.shape[0]:
        raise ValueError(f"mean_taps_e must be (steps, taps) = ({psi.shape[0]}, N), got {taps.shape}")
    n = taps.shape[1]
    if num_harmonics < 1:
        raise ValueError(f"num_harmonics must be >= 1, got {num_harmonics}")
    sig = taps - dark_mean_e
    a_s = sig.mean(axis=1, keepdims=True)
    if np.any(a_s <= 0):
        bad = int(np.argmax(a_s[:, 0] <= 0))
        raise ValueError(f"sweep step {bad}: no returned signal above the dark offset (mean tap - dark <= 0)")
    y = (sig / a_s).reshape(-1)
    theta = 2.0 * np.pi * np.arange(n) / n
    x = (psi[:, None] - theta[None, :]).reshape(-1)
    k = np.arange(1, num_harmonics + 1)
    design = np.concatenate([np.ones((x.size, 1)), np.cos(np.outer(x, k)), np.sin(np.outer(x, k))], axis=1)
    distinct = np.unique(np.round(np.mod(x, 2 * np.pi), 9)).size
    if distinct < design.shape[1]:
        raise ValueError(
            f"phase sweep has {distinct} distinct sample phases; {design.shape[1]} are needed for "
            f"{num_harmonics} harmonics (add phase steps or lower num_harmonics)"
        )
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    K = num_harmonics
    return TapResponse(c0=float(coef[0]), cos=tuple(float(v) for v in coef[1 : K + 1]), sin=tuple(float(v) for v in coef[K + 1 :]))


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


def signal_interval(signal_e: np.ndarray, lower_percentile: float = 1.0, upper_percentile: float = 99.0) -> tuple[float, float]:
    """[a_min, a_max] = percentiles of the valid (finite, > 0) returned-signal samples."""
    s = np.asarray(signal_e, dtype=np.float64).reshape(-1)
    s = s[np.isfinite(s) & (s > 0)]
    if s.size == 0:
        raise ValueError("no valid returned-signal samples to set [signal_min_e, signal_max_e]")
    lo, hi = np.percentile(s, [lower_percentile, upper_percentile])
    return float(lo), float(hi)


def fit_range_sigma(distance_mm: Sequence[float], std_mm: Sequence[float]) -> tuple[float, float, float]:
    """Least squares sigma(D) = alpha0 + alpha1 D + alpha2 D^2 (D in mm) -> (alpha0, alpha1, alpha2)."""
    d = np.asarray(distance_mm, dtype=np.float64)
    s = np.asarray(std_mm, dtype=np.float64)
    if d.shape != s.shape or d.ndim != 1:
        raise ValueError("distance_mm and std_mm must be 1-D of the same length")
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


def temporal_std_roi_mm(depth_frames_mm: np.ndarray, valid: np.ndarray | None = None) -> tuple[float, int]:
    """ROI mean of the per-pixel temporal depth std (pixels valid in every frame) and the pixel count."""
    d = np.asarray(depth_frames_mm, dtype=np.float64)
    ok = np.all(np.isfinite(d) & (d > 0), axis=0)
    if valid is not None:
        ok &= np.all(np.asarray(valid, dtype=bool), axis=0)
    if not ok.any():
        return math.nan, 0
    std = d[:, ok].std(axis=0, ddof=1)
    return float(std.mean()), int(ok.sum())


@dataclass
class CalibrationReport:
    calibration: SensorCalibration
    sweep_points: int
    dark_frames: int
    range_points: list[tuple[float, float]]


def _phase_of(entry: dict, freq: float) -> float:
    if "phase_rad" in entry:
        return float(entry["phase_rad"])
    return 4.0 * math.pi * freq * float(entry["distance_mm"]) / C_LIGHT_MM_PER_S


def calibrate_from_folders(
    sweep_dir: str | os.PathLike[str],
    dark_dir: str | os.PathLike[str],
    distances_dir: str | os.PathLike[str] | None = None,
    num_harmonics: int = 3,
    full_well_e: float | None = None,
    lower_percentile: float = 1.0,
    upper_percentile: float = 99.0,
) -> CalibrationReport:
    """Run the whole calibration procedure on capture folders (format: tofdenoise.physics.capture_io)."""
    dark_idx = read_index(dark_dir, "dark")
    dark_stacks = [load_stack(dark_idx, e["file"], ndim=(4,)) for e in dark_idx.stacks]
    dark_mean, dark_std = estimate_dark(dark_stacks)
    dark_frames = sum(s.shape[0] for s in dark_stacks)
    del dark_stacks

    sweep_idx = read_index(sweep_dir, "sweep")
    if sweep_idx.num_taps != dark_idx.num_taps:
        raise CaptureFormatError(
            f"{Path(sweep_dir) / 'index.json'}: num_taps={sweep_idx.num_taps} differs from the dark folder's "
            f"{dark_idx.num_taps}"
        )
    freq = float(sweep_idx.modulation_frequency_hz)  # type: ignore[arg-type]
    phases, means, signal_samples = [], [], []
    for e in sweep_idx.stacks:
        taps = load_stack(sweep_idx, e["file"], ndim=(4,))
        phases.append(_phase_of(e, freq))
        means.append(taps.mean(axis=(0, 2, 3)))
        signal_samples.append((taps.mean(axis=(0, 1)) - dark_mean).reshape(-1))
    tap_response = fit_tap_response(np.array(phases), np.stack(means), dark_mean, num_harmonics)
    signal_samples = [s / tap_response.c0 for s in signal_samples]

    fw = full_well_e if full_well_e is not None else sweep_idx.full_well_e
    if fw is None:
        raise CaptureFormatError(
            f"{Path(sweep_dir) / 'index.json'}: no 'full_well_e' in the sweep index; pass the sensor's full-well "
            f"capacity (--full-well-e)"
        )
    gain = sweep_idx.adc_gain_e_per_dn if sweep_idx.adc_gain_e_per_dn is not None else dark_idx.adc_gain_e_per_dn

    partial = SensorCalibration(
        num_taps=sweep_idx.num_taps, modulation_frequency_hz=freq, tap_response=tap_response,
        dark_mean_e=dark_mean, dark_std_e=dark_std, signal_min_e=1.0, signal_max_e=2.0,
        full_well_e=float(fw), adc_gain_e_per_dn=gain, range_sigma_mm=None,
    )

    range_points: list[tuple[float, float]] = []
    if distances_dir is not None:
        dist_idx = read_index(distances_dir, "distances")
        if dist_idx.num_taps != partial.num_taps:
            raise CaptureFormatError(
                f"{Path(distances_dir) / 'index.json'}: num_taps={dist_idx.num_taps} differs from the sweep's "
                f"{partial.num_taps}"
            )
        for e in dist_idx.stacks:
            arr = load_stack(dist_idx, e["file"], ndim=(3, 4))
            if arr.ndim == 4:
                depth, _ = demodulate(torch.from_numpy(arr), partial, tap_axis=1)
                depth_np = depth.numpy()
                signal_samples.append(((arr.mean(axis=(0, 1)) - dark_mean) / tap_response.c0).reshape(-1))
            else:
                depth_np = arr
            std, _ = temporal_std_roi_mm(depth_np)
            if not math.isfinite(std):
                raise CaptureFormatError(f"{dist_idx.folder / e['file']}: no pixel valid in every frame")
            range_points.append((float(e["distance_mm"]), std))
    a_min, a_max = signal_interval(np.concatenate(signal_samples), lower_percentile, upper_percentile)
    if a_max <= a_min:
        a_max = a_min * (1.0 + 1e-6)
    alphas = fit_range_sigma(*zip(*range_points)) if range_points else None
    calib = partial.replace(signal_min_e=a_min, signal_max_e=a_max, range_sigma_mm=alphas)
    return CalibrationReport(calibration=calib, sweep_points=len(phases), dark_frames=dark_frames, range_points=range_points)


__all__ = [
    "CalibrationReport",
    "calibrate_from_folders",
    "estimate_dark",
    "fit_range_sigma",
    "fit_tap_response",
    "signal_interval",
    "temporal_std_roi_mm",
]
