"""Simulated calibration/validation captures of planar targets, written in the capture-folder format.

Returned signal of a fronto-parallel Lambertian planar target at normal incidence (inverse-square law):
    a(D) = SIGNAL_AT_1M_E * reflectance * exposure * (1000 mm / D)^2
with SIGNAL_AT_1M_E = 15000 e- per tap for a reflectance-1 target at 1 m and exposure 1 (default
calibration: a white 0.9 board gives 54 ke- at 0.5 m, still below full well, and 6 ke- at 1.5 m).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.physics.capture_io import write_capture_folder
from tofdenoise.physics.simulator import simulate_dark_taps, simulate_frames

SIGNAL_AT_1M_E: float = 15000.0
REFERENCE_DISTANCE_MM: float = 1000.0


def planar_signal_e(
    distance_mm: float | np.ndarray,
    reflectance: float = 1.0,
    exposure: float = 1.0,
    signal_at_1m_e: float = SIGNAL_AT_1M_E,
) -> float | np.ndarray:
    """a(D) = signal_at_1m_e * reflectance * exposure * (1000 / D)^2 [e-] (D in mm)."""
    return (
        signal_at_1m_e
        * reflectance
        * exposure
        * (REFERENCE_DISTANCE_MM / np.asarray(distance_mm, dtype=np.float64)) ** 2
    )


def planar_tap_stack(
    calib: SensorCalibration,
    distance_mm: float,
    signal_e: float | np.ndarray,
    num_frames: int,
    shape: tuple[int, int],
    generator: torch.Generator,
    exposure: float = 1.0,
) -> np.ndarray:
    """Tap stack (F, N, H, W) [e-] of a planar target at one distance."""
    depth = torch.full(shape, float(distance_mm), dtype=torch.float32)
    signal = torch.as_tensor(np.broadcast_to(np.asarray(signal_e, dtype=np.float32), shape).copy())
    frames = simulate_frames(depth, signal, calib, num_frames, exposure=exposure, generator=generator, return_taps=True)
    assert frames.taps is not None
    return frames.taps.numpy()


def write_sweep_folder(
    calib: SensorCalibration,
    folder: str | os.PathLike[str],
    num_steps: int = 24,
    num_frames: int = 20,
    shape: tuple[int, int] = (8, 8),
    signal_e: float = 20000.0,
    seed: int = 11,
) -> Path:
    """Phase sweep: target phase psi_s = 2 pi s / S emulated by moving the plane (distance psi / (4 pi f / c))."""
    g = torch.Generator().manual_seed(seed)
    stacks = []
    for s in range(num_steps):
        psi = 2.0 * np.pi * (s + 0.5) / num_steps
        d = psi / calib.phase_per_mm
        stacks.append(
            (
                f"step_{s:03d}",
                planar_tap_stack(calib, d, signal_e, num_frames, shape, g).astype(np.float32),
                {"phase_rad": psi},
            )
        )
    return write_capture_folder(
        folder,
        "sweep",
        calib.num_taps,
        stacks,
        modulation_frequency_hz=calib.modulation_frequency_hz,
        units="e",
        full_well_e=calib.full_well_e,
        adc_gain_e_per_dn=calib.adc_gain_e_per_dn,
    )


def write_dark_folder(
    calib: SensorCalibration,
    folder: str | os.PathLike[str],
    num_frames: int = 100,
    shape: tuple[int, int] = (8, 8),
    seed: int = 12,
) -> Path:
    """Emitter-off stack (F, N, H, W), stored in DN when the calibration has an ADC gain."""
    g = torch.Generator().manual_seed(seed)
    taps = simulate_dark_taps(shape, calib, num_frames, generator=g).numpy()
    if calib.adc_gain_e_per_dn is not None:
        dn = np.round(taps / calib.adc_gain_e_per_dn).astype(np.uint16)
        return write_capture_folder(
            folder,
            "dark",
            calib.num_taps,
            [("dark_000", dn, {})],
            units="dn",
            adc_gain_e_per_dn=calib.adc_gain_e_per_dn,
        )
    return write_capture_folder(folder, "dark", calib.num_taps, [("dark_000", taps.astype(np.float32), {})], units="e")


def write_distances_folder(
    calib: SensorCalibration,
    folder: str | os.PathLike[str],
    distances_mm: Sequence[float],
    num_frames: int = 100,
    shape: tuple[int, int] = (8, 8),
    reflectance: float = 0.9,
    signal_spread: tuple[float, float] | None = None,
    seed: int = 13,
    reflectance_chart: tuple[float, float] | None = None,
    signal_at_1m_e: float = SIGNAL_AT_1M_E,
) -> Path:
    """Planar distance sequence (tap stacks). `signal_spread=(lo, hi)` multiplies the target's signal by a
    left-to-right ramp lo..hi (illumination fall-off), giving a spread of returned signals.
    `reflectance_chart=(dark, white)` replaces the uniform target by a grey chart: the columns' reflectances run
    log-spaced from dark to white (dark and bright targets at every distance: the signal-interval sequence)."""
    g = torch.Generator().manual_seed(seed)
    stacks = []
    for i, dist in enumerate(distances_mm):
        meta: dict = {"distance_mm": float(dist)}
        if reflectance_chart is not None:
            lo, hi = reflectance_chart
            chart = np.geomspace(lo, hi, shape[1])[None, :] * np.ones(shape)
            a = planar_signal_e(dist, chart, signal_at_1m_e=signal_at_1m_e)
            meta["reflectance_chart"] = [float(lo), float(hi)]
        else:
            a = float(planar_signal_e(dist, reflectance, signal_at_1m_e=signal_at_1m_e))
            if signal_spread is None:
                meta["reflectance"] = float(reflectance)
        if signal_spread is not None:
            ramp = np.linspace(signal_spread[0], signal_spread[1], shape[1])[None, :] * np.ones(shape)
            a = a * ramp
        stacks.append(
            (
                f"dist_{i:03d}",
                planar_tap_stack(calib, dist, a, num_frames, shape, g).astype(np.float32),
                meta,
            )
        )
    return write_capture_folder(folder, "distances", calib.num_taps, stacks, units="e")


# the signal-interval sequence of a camera with a photometric gain: a grey chart from black (2 %) to white (90 %)
# at distances across the working range, WORKING_RANGE_MIN_MM .. WORKING_RANGE_FRACTION x the unambiguous range
# (the procedural scenes' default depth range)
GREY_CHART: tuple[float, float] = (0.02, 0.9)
WORKING_RANGE_MIN_MM: float = 300.0
WORKING_RANGE_FRACTION: float = 0.8


def default_distances_mm(calib: SensorCalibration, count: int = 10) -> list[float]:
    """``count`` planar-target distances (mm, rounded to 1 mm): across the working range (300 mm to 80 % of the
    unambiguous range) for a camera with a photometric gain ``signal_at_1m_e``, else 25 % to 75 % of the
    unambiguous range."""
    if calib.signal_at_1m_e is not None:
        hi = WORKING_RANGE_FRACTION * calib.unambiguous_range_mm
        return [float(round(v)) for v in np.linspace(WORKING_RANGE_MIN_MM, hi, int(count))]
    return [float(round(v)) for v in np.linspace(0.25, 0.75, int(count)) * calib.unambiguous_range_mm]


def write_calibration_captures(
    calib: SensorCalibration,
    out_dir: str | os.PathLike[str],
    sweep_steps: int = 24,
    sweep_frames: int = 20,
    dark_frames: int = 100,
    distances_mm: Sequence[float] | None = None,
    distance_frames: int = 100,
    shape: tuple[int, int] = (16, 16),
    signal_spread: tuple[float, float] = (0.3, 1.0),
    seed: int = 0,
) -> dict[str, Path]:
    """The three capture folders ``tofdenoise sensor calibrate`` reads, as a camera with ``calib`` records them:
    ``out_dir/sweep`` (phase sweep), ``out_dir/dark`` (emitter-off frames) and ``out_dir/distances`` (planar
    target at ``distances_mm``, default ``default_distances_mm``). The target is a grey chart ``GREY_CHART`` lit
    by the camera's own photometric gain when it has one (the paper's signal-interval sequence: dark and bright
    targets across the working range), else a uniform white board with a left-to-right signal ramp
    ``signal_spread``. Each folder has its own generator seeded from ``seed``."""
    out = Path(out_dir)
    distances = list(distances_mm) if distances_mm is not None else default_distances_mm(calib)
    if calib.signal_at_1m_e is not None:
        target = {"reflectance_chart": GREY_CHART, "signal_at_1m_e": calib.signal_at_1m_e, "signal_spread": None}
    else:
        target = {"signal_spread": signal_spread}
    return {
        "sweep": write_sweep_folder(
            calib, out / "sweep", num_steps=sweep_steps, num_frames=sweep_frames, shape=shape, seed=seed * 3 + 11
        ),
        "dark": write_dark_folder(calib, out / "dark", num_frames=dark_frames, shape=shape, seed=seed * 3 + 12),
        "distances": write_distances_folder(
            calib,
            out / "distances",
            distances,
            num_frames=distance_frames,
            shape=shape,
            seed=seed * 3 + 13,
            **target,
        ),
    }


__all__ = [
    "GREY_CHART",
    "REFERENCE_DISTANCE_MM",
    "SIGNAL_AT_1M_E",
    "default_distances_mm",
    "planar_signal_e",
    "planar_tap_stack",
    "write_calibration_captures",
    "write_dark_folder",
    "write_distances_folder",
    "write_sweep_folder",
]
