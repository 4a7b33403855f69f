"""Noise-model validation (paper Sec. IV, Fig. 6).

Conditions
- range panel: planar target (reflectance 0.9, exposure 1) at 500..1500 mm every 100 mm;
- signal panel: coplanar black / gray / white surfaces (reflectance 0.2 / 0.45 / 0.9) at 1500 mm under
  four exposure settings (1, 2, 3, 4);
- range-aware baseline fit: an INDEPENDENT planar sequence (550..1450 mm every 100 mm, other random
  stream) to which sigma(D) = alpha0 + alpha1 D + alpha2 D^2 is fitted by least squares.
Returned signal: `synthetic_captures.planar_signal_e` (inverse-square law x reflectance x exposure).

For each condition, `measured` = ROI mean of the per-pixel temporal depth std over the repeated frames (circular
modulo the unambiguous range: ``calibrate.circular_depth_stats_mm``; pixels valid in every frame);
`proposed` = ROI mean of sigma_D(mean depth, estimated signal) — the signal estimated from the captures
(DC bin of the taps, or amplitude / |C1| for depth+amplitude stacks), not the simulator's input;
`range_gaussian` = ROI mean of sigma_range(mean depth). Pooled MAPE [%] and R^2 over all conditions.
A condition without a pixel valid in every frame (e.g. saturated) has no measured std: it is left out of the
metrics and of the range-aware fit alike and named in ``ValidationResult.left_out`` (``validation.json``'s
``left_out``); a range-fit sequence left with fewer than 3 distinct distances is an error.

By default the captures come from the tap-level simulator (Poisson shot noise, Gaussian dark/read noise,
ADC quantisation, third harmonic, atan2 demodulation: effects the WLS model leaves out or linearises);
`captures_dir` reads real stacks instead (format: capture_io, kind "validation").
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tofdenoise.atomic import atomic_write, atomic_write_text
from tofdenoise.physics.calibrate import (
    calibrate_from_folders,
    circular_depth_stats_mm,
    fit_range_sigma,
    temporal_std_roi_mm,
)
from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.physics.capture_io import load_stack, read_index, write_capture_folder
from tofdenoise.physics.simulator import demodulate, signal_from_taps_e, simulate_frames
from tofdenoise.physics.synthetic_captures import planar_signal_e, write_calibration_captures
from tofdenoise.physics.uncertainty import sigma_depth_mm
from tofdenoise.records.provenance import written_provenance

RANGE_DISTANCES_MM: tuple[float, ...] = tuple(float(d) for d in range(500, 1501, 100))
RANGE_FIT_DISTANCES_MM: tuple[float, ...] = tuple(float(d) for d in range(550, 1451, 100))
PLANAR_REFLECTANCE: float = 0.9
SIGNAL_DISTANCE_MM: float = 1500.0
SURFACES: dict[str, float] = {"black": 0.2, "gray": 0.45, "white": 0.9}
EXPOSURES: tuple[float, ...] = (1.0, 2.0, 3.0, 4.0)


@dataclass
class ValidationSettings:
    num_frames: int = 200
    roi_px: int = 32
    seed: int = 2024
    fit_seed: int = 777

    @classmethod
    def quick(cls) -> ValidationSettings:
        return cls(num_frames=50, roi_px=16)


@dataclass
class Condition:
    group: str  # "range" | "signal" | "range_fit"
    distance_mm: float
    surface: str
    reflectance: float | None
    exposure: float
    signal_e: float = math.nan
    measured_std_mm: float = math.nan
    proposed_std_mm: float = math.nan
    range_gaussian_std_mm: float = math.nan
    num_frames: int = 0
    num_pixels: int = 0


@dataclass
class StackStats:
    """Per-pixel statistics of one repeated-capture stack."""

    measured_std_mm: float
    mean_depth_mm: np.ndarray  # (P,) pixels valid in every frame
    signal_e: np.ndarray  # (P,)
    num_frames: int
    num_pixels: int


def stack_stats(
    depth_frames_mm: np.ndarray,
    valid: np.ndarray | None,
    signal_frames_e: np.ndarray,
    unambiguous_range_mm: float | None,
) -> StackStats:
    """Temporal std (ROI mean) and per-pixel mean depth / signal over pixels valid in every frame; depth mean and
    std circular modulo the unambiguous range (``calibrate.circular_depth_stats_mm``: a depth near U wraps)."""
    d = np.asarray(depth_frames_mm, dtype=np.float64)
    ok = np.all(np.isfinite(d) & (d > 0), axis=0)
    if valid is not None:
        ok &= np.all(valid, axis=0)
    measured, count = temporal_std_roi_mm(d, valid, unambiguous_range_mm=unambiguous_range_mm)
    mean_depth, _ = circular_depth_stats_mm(d[:, ok], unambiguous_range_mm)
    return StackStats(
        measured_std_mm=measured,
        mean_depth_mm=mean_depth,
        signal_e=np.asarray(signal_frames_e, dtype=np.float64)[:, ok].mean(axis=0),
        num_frames=d.shape[0],
        num_pixels=count,
    )


def predict_proposed_mm(stats: StackStats, calib: SensorCalibration) -> float:
    return float(np.nanmean(sigma_depth_mm(stats.mean_depth_mm, stats.signal_e, calib)))


def predict_range_mm(depth_mm: np.ndarray, alpha_mm: tuple[float, float, float]) -> float:
    a0, a1, a2 = alpha_mm
    return float(np.mean(np.maximum(a0 + a1 * depth_mm + a2 * depth_mm**2, 0.0)))


def mape_percent(predicted: np.ndarray, measured: np.ndarray) -> float:
    """Mean absolute percentage error 100 mean(|pred - meas| / meas)."""
    p, m = np.asarray(predicted, float), np.asarray(measured, float)
    return float(100.0 * np.mean(np.abs(p - m) / m))


def r2_score(predicted: np.ndarray, measured: np.ndarray) -> float:
    """Coefficient of determination of the predictions against the measurements (identity-line fit)."""
    p, m = np.asarray(predicted, float), np.asarray(measured, float)
    ss_res = float(np.sum((m - p) ** 2))
    ss_tot = float(np.sum((m - m.mean()) ** 2))
    return 1.0 - ss_res / ss_tot if ss_tot > 0 else math.nan


# ----------------------------------------------------------------------------------------------------
# measurements: simulated or real
# ----------------------------------------------------------------------------------------------------


def _planar_frames(
    calib: SensorCalibration,
    distance_mm: float,
    signal_e: float,
    exposure: float,
    settings: ValidationSettings,
    generator: torch.Generator,
):
    """``settings.num_frames`` captures (with taps) of a planar ROI at one distance and returned signal."""
    shape = (settings.roi_px, settings.roi_px)
    depth = torch.full(shape, float(distance_mm))
    signal = torch.full(shape, float(signal_e))
    fr = simulate_frames(
        depth, signal, calib, settings.num_frames, exposure=exposure, generator=generator, return_taps=True
    )
    assert fr.taps is not None
    return fr


def _simulated_stats(
    calib: SensorCalibration,
    distance_mm: float,
    signal_e: float,
    exposure: float,
    settings: ValidationSettings,
    generator: torch.Generator,
) -> StackStats:
    fr = _planar_frames(calib, distance_mm, signal_e, exposure, settings, generator)
    sig = signal_from_taps_e(fr.taps, calib, tap_axis=1)
    return stack_stats(fr.depth_mm.numpy(), fr.valid.numpy(), sig.numpy(), calib.unambiguous_range_mm)


def _streams(settings: ValidationSettings) -> dict[str, torch.Generator]:
    """The experiment's random streams: "main" (range and signal panels), "fit" (the independent range-fit
    sequence)."""
    return {
        "main": torch.Generator().manual_seed(settings.seed),
        "fit": torch.Generator().manual_seed(settings.fit_seed),
    }


def condition_plan() -> list[tuple[Condition, float, str]]:
    """Every condition of the experiment with its returned signal [e-] and its random stream ("main" or "fit"):
    the range panel, the signal panel, then the independent range-fit sequence."""
    plan: list[tuple[Condition, float, str]] = []
    for d in RANGE_DISTANCES_MM:
        plan.append(
            (
                Condition("range", d, "planar", PLANAR_REFLECTANCE, 1.0),
                float(planar_signal_e(d, PLANAR_REFLECTANCE)),
                "main",
            )
        )
    for surface, refl in SURFACES.items():
        for e in EXPOSURES:
            plan.append(
                (
                    Condition("signal", SIGNAL_DISTANCE_MM, surface, refl, e),
                    float(planar_signal_e(SIGNAL_DISTANCE_MM, refl)),
                    "main",
                )
            )
    for d in RANGE_FIT_DISTANCES_MM:
        plan.append(
            (
                Condition("range_fit", d, "planar", PLANAR_REFLECTANCE, 1.0),
                float(planar_signal_e(d, PLANAR_REFLECTANCE)),
                "fit",
            )
        )
    return plan


def simulated_conditions(calib: SensorCalibration, settings: ValidationSettings) -> list[tuple[Condition, StackStats]]:
    """All range / signal / range-fit conditions measured on the tap-level simulator."""
    streams = _streams(settings)
    return [
        (cond, _simulated_stats(calib, cond.distance_mm, a, cond.exposure, settings, streams[stream]))
        for cond, a, stream in condition_plan()
    ]


def write_validation_captures(
    calib: SensorCalibration, folder: str | os.PathLike[str], settings: ValidationSettings | None = None
) -> Path:
    """The experiment's captures as the camera ``calib`` records them (tap stacks (F, N, H, W) [e-], kind
    "validation", format ``capture_io``): what ``run_validation(captures_dir=...)`` reads. With a simulated camera
    unlike the calibration used for the prediction (e.g. one estimated by ``calibrate`` from that camera's own
    captures), the comparison tests the model and the calibration, not the simulator against itself."""
    settings = settings or ValidationSettings()
    streams = _streams(settings)
    stacks = []
    for i, (cond, a, stream) in enumerate(condition_plan()):
        frames = _planar_frames(calib, cond.distance_mm, a, cond.exposure, settings, streams[stream])
        fields = {
            "group": cond.group,
            "distance_mm": cond.distance_mm,
            "surface": cond.surface,
            "exposure": cond.exposure,
        }
        if cond.reflectance is not None:
            fields["reflectance"] = cond.reflectance
        stacks.append((f"{cond.group}_{i:03d}", frames.taps.numpy().astype(np.float32), fields))
    return write_capture_folder(
        folder, "validation", calib.num_taps, stacks, units="e", modulation_frequency_hz=calib.modulation_frequency_hz
    )


def captured_conditions(
    calib: SensorCalibration, captures_dir: str | os.PathLike[str]
) -> list[tuple[Condition, StackStats]]:
    """Conditions from real stacks: kind 'validation' folder; tap stacks or depth + amplitude stacks."""
    idx = read_index(captures_dir, "validation")
    if idx.num_taps != calib.num_taps:
        raise ValueError(
            f"{idx.folder / 'index.json'}: num_taps={idx.num_taps} but the calibration has {calib.num_taps}"
        )
    freq = idx.modulation_frequency_hz
    if freq is not None and not math.isclose(freq, calib.modulation_frequency_hz, rel_tol=1e-6):
        # decoded at another frequency, the taps give other depths and sigma_D: the model was reported as failing
        raise ValueError(
            f"{idx.folder / 'index.json'}: modulation_frequency_hz={freq:g} but the calibration has "
            f"{calib.modulation_frequency_hz:g}: the captures are another camera's or another mode's; give their "
            "calibration (--sensor)"
        )
    out = []
    for e in idx.stacks:
        arr = load_stack(idx, e["file"], ndim=(3, 4))
        if arr.ndim == 4:
            taps = torch.from_numpy(arr)
            depth, _ = demodulate(taps, calib, tap_axis=1)
            depth_np = depth.numpy()
            signal = signal_from_taps_e(taps, calib, tap_axis=1).numpy()
        else:
            if "amplitude_file" not in e:
                raise ValueError(
                    f"{idx.folder / e['file']}: a depth stack (F, H, W) needs an 'amplitude_file' entry in the index "
                    f"(the proposed model needs the returned signal)"
                )
            depth_np = arr
            amp = load_stack(idx, e["amplitude_file"], ndim=(3,), scale=False) * idx.scale_to_e
            if amp.shape != depth_np.shape:
                raise ValueError(
                    f"{idx.folder / e['amplitude_file']}: shape {amp.shape} differs from depth {depth_np.shape}"
                )
            signal = amp / calib.tap_response.first_harmonic_amplitude
        cond = Condition(
            group=e["group"],
            distance_mm=float(e["distance_mm"]),
            surface=str(e.get("surface", "planar")),
            reflectance=e.get("reflectance"),
            exposure=float(e.get("exposure", 1.0)),
        )
        out.append((cond, stack_stats(depth_np, None, signal, calib.unambiguous_range_mm)))
    return out


# ----------------------------------------------------------------------------------------------------
# the experiment
# ----------------------------------------------------------------------------------------------------


#: distinct distances the range-aware fit needs (three coefficients)
RANGE_FIT_MIN_DISTANCES: int = 3


def has_measured_std(item: StackStats | Condition) -> bool:
    """A stack (or its condition) has a measured temporal std: a pixel valid in every frame, and a finite std."""
    return item.num_pixels > 0 and math.isfinite(item.measured_std_mm)


@dataclass
class ValidationResult:
    conditions: list[Condition]
    range_sigma_mm: tuple[float, float, float]
    range_sigma_source: str
    pooled: dict[str, dict[str, float]]
    panels: dict[str, dict[str, dict[str, float]]]
    source: str
    settings: dict[str, Any] = field(default_factory=dict)
    #: the conditions without a pixel valid in every frame (no measured std), left out of the metrics and of the
    #: range-aware fit: {"group", "distance_mm", "surface", "exposure", "reason"}
    left_out: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self, calib: SensorCalibration) -> dict[str, Any]:
        """The result as a strict-JSON object: a value that is not a finite number (the std of a condition without
        valid pixels, an R^2 of equal measurements) is ``None`` (``null``)."""
        return strict_json(
            {
                "source": self.source,
                "settings": self.settings,
                "calibration": calib.to_dict(),
                "calibration_fingerprint": calib.fingerprint(),
                "range_sigma_mm": list(self.range_sigma_mm),
                "range_sigma_source": self.range_sigma_source,
                "left_out": self.left_out,
                "conditions": [asdict(c) for c in self.conditions],
                "pooled": self.pooled,
                "panels": self.panels,
            }
        )


def strict_json(value: Any) -> Any:
    """``value`` with every float that is not finite (NaN, +-inf) replaced by ``None``, through dicts, lists and
    tuples: what ``json.dumps(..., allow_nan=False)`` accepts."""
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _metrics(conds: list[Condition]) -> dict[str, dict[str, float]]:
    meas = np.array([c.measured_std_mm for c in conds])
    out = {}
    for key, attr in (("proposed", "proposed_std_mm"), ("range_gaussian", "range_gaussian_std_mm")):
        pred = np.array([getattr(c, attr) for c in conds])
        out[key] = {"mape_percent": mape_percent(pred, meas), "r2": r2_score(pred, meas), "n": len(conds)}
    return out


def run_validation(
    calib: SensorCalibration,
    settings: ValidationSettings | None = None,
    captures_dir: str | os.PathLike[str] | None = None,
) -> ValidationResult:
    settings = settings or ValidationSettings()
    if captures_dir is None:
        pairs = simulated_conditions(calib, settings)
        source = "simulated (tofdenoise.physics.simulator)"
    else:
        pairs = captured_conditions(calib, captures_dir)
        source = f"captures: {captures_dir}"
    where = source if captures_dir is None else f"{Path(captures_dir) / 'index.json'}"
    left_out = [
        {
            "group": c.group,
            "distance_mm": c.distance_mm,
            "surface": c.surface,
            "exposure": c.exposure,
            "reason": f"no pixel valid in every one of its {s.num_frames} frames (saturated, or too dark for a "
            "depth, in some frame)",
        }
        for c, s in pairs
        if not has_measured_std(s)
    ]
    fit_pairs = [(c, s) for c, s in pairs if c.group == "range_fit"]
    if fit_pairs:
        usable = [(c, s) for c, s in fit_pairs if has_measured_std(s)]
        distinct = len({c.distance_mm for c, _ in usable})
        if distinct < RANGE_FIT_MIN_DISTANCES:
            dropped = [f"{c.distance_mm:g} mm" for c, s in fit_pairs if not has_measured_std(s)]
            raise ValueError(
                f"{where}: {len(usable)} of the {len(fit_pairs)} 'range_fit' conditions have a pixel valid in every "
                f"frame ({distinct} distinct distances; left out: {', '.join(dropped) or 'none'}); the range-aware "
                f"fit sigma(D) = alpha0 + alpha1 D + alpha2 D^2 needs at least {RANGE_FIT_MIN_DISTANCES} distinct "
                "distances (saturated or too dark: lower the exposure or the reflectance, or use another sequence)"
            )
        alpha = fit_range_sigma([c.distance_mm for c, _ in usable], [s.measured_std_mm for _, s in usable])
        alpha_source = "least squares on the independent range_fit sequence"
        if len(usable) < len(fit_pairs):
            alpha_source += (
                f" ({len(usable)} of {len(fit_pairs)} distances; left out without valid pixels: "
                + ", ".join(f"{c.distance_mm:g} mm" for c, s in fit_pairs if not has_measured_std(s))
                + ")"
            )
    elif calib.range_sigma_mm is not None:
        alpha = calib.range_sigma_mm
        alpha_source = "calibration range_sigma_mm"
    else:
        raise ValueError("no 'range_fit' stacks and no range_sigma_mm in the calibration: cannot build the baseline")
    conds: list[Condition] = []
    for cond, st in pairs:
        cond.signal_e = float(np.mean(st.signal_e)) if st.num_pixels else math.nan
        cond.measured_std_mm = st.measured_std_mm
        cond.num_frames, cond.num_pixels = st.num_frames, st.num_pixels
        if has_measured_std(st):
            cond.proposed_std_mm = predict_proposed_mm(st, calib)
            cond.range_gaussian_std_mm = predict_range_mm(st.mean_depth_mm, alpha)
        conds.append(cond)
    evaluated = [c for c in conds if c.group in ("range", "signal") and has_measured_std(c)]
    if not evaluated:
        raise ValueError(f"{where}: no 'range' or 'signal' condition with valid pixels to evaluate")
    panels = {
        g: _metrics([c for c in evaluated if c.group == g])
        for g in ("range", "signal")
        if any(c.group == g for c in evaluated)
    }
    return ValidationResult(
        conditions=conds,
        range_sigma_mm=tuple(alpha),
        range_sigma_source=alpha_source,  # type: ignore[arg-type]
        pooled=_metrics(evaluated),
        panels=panels,
        source=source,
        settings=asdict(settings) if captures_dir is None else {"captures": str(captures_dir)},
        left_out=left_out,
    )


def plot_validation(result: ValidationResult, path: str | os.PathLike[str]) -> Path:
    """Three-panel figure like the paper's Fig. 6, written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    rng = sorted((c for c in result.conditions if c.group == "range" and c.num_pixels), key=lambda c: c.distance_mm)
    sig = sorted((c for c in result.conditions if c.group == "signal" and c.num_pixels), key=lambda c: c.signal_e)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4))
    ax = axes[0]
    if rng:
        x = [c.distance_mm for c in rng]
        ax.plot(x, [c.measured_std_mm for c in rng], "ko-", label="measured")
        ax.plot(x, [c.proposed_std_mm for c in rng], "s--", color="tab:red", label="proposed (WLS)")
        ax.plot(x, [c.range_gaussian_std_mm for c in rng], "^:", color="tab:blue", label="range-aware Gaussian")
    ax.set_xlabel("distance [mm]")
    ax.set_ylabel("temporal depth std [mm]")
    ax.set_title("(a) std vs distance")
    ax.legend()
    ax = axes[1]
    if sig:
        x = [c.signal_e for c in sig]
        ax.plot(x, [c.measured_std_mm for c in sig], "ko", label="measured")
        ax.plot(x, [c.proposed_std_mm for c in sig], "s", color="tab:red", mfc="none", label="proposed (WLS)")
        ax.plot(
            x, [c.range_gaussian_std_mm for c in sig], "^", color="tab:blue", mfc="none", label="range-aware Gaussian"
        )
        ax.set_xscale("log")
        from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter

        lo, hi = min(x), max(x)
        ticks = [t for t in (500, 1000, 2000, 5000, 10000, 20000, 50000, 100000) if lo / 1.5 <= t <= hi * 1.5]
        ax.xaxis.set_major_locator(FixedLocator(ticks))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(bottom=0)
    ax.set_xlabel("returned signal [e-]")
    ax.set_ylabel("temporal depth std [mm]")
    ax.set_title(f"(b) std vs returned signal at {SIGNAL_DISTANCE_MM:.0f} mm")
    ax.legend()
    ax = axes[2]
    ev = rng + sig
    if ev:
        meas = np.array([c.measured_std_mm for c in ev])
        p = result.pooled["proposed"]
        r = result.pooled["range_gaussian"]
        ax.plot(
            meas,
            [c.proposed_std_mm for c in ev],
            "s",
            color="tab:red",
            mfc="none",
            label=f"proposed: MAPE {p['mape_percent']:.1f}%, R2 {p['r2']:.3f}",
        )
        ax.plot(
            meas,
            [c.range_gaussian_std_mm for c in ev],
            "^",
            color="tab:blue",
            mfc="none",
            label=f"range-aware: MAPE {r['mape_percent']:.1f}%, R2 {r['r2']:.3f}",
        )
        lim = [0.0, float(max(meas.max(), max(c.proposed_std_mm for c in ev))) * 1.08]
        ax.plot(lim, lim, "k-", lw=0.8, label="identity")
        ax.set_xlim(lim)
        ax.set_ylim(lim)
    ax.set_xlabel("measured std [mm]")
    ax.set_ylabel("predicted std [mm]")
    ax.set_title("(c) predicted vs measured")
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))
    finally:
        plt.close(fig)
    return path


#: the files ``write_validation`` writes into its folder
VALIDATION_FILES = ("validation.json", "validation.png")


def write_validation(
    result: ValidationResult, calib: SensorCalibration, out_dir: str | os.PathLike[str]
) -> tuple[Path, Path]:
    """``validation.json`` (the result, the calibration, and under ``provenance`` when, at which commit and on which
    machine it was written: :func:`~tofdenoise.records.provenance.written_provenance`) and ``validation.png``.
    ``validation.json`` is strict JSON: a value that is not a finite number is written as ``null``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / VALIDATION_FILES[0]
    record = {**result.to_dict(calib), "provenance": written_provenance()}
    atomic_write_text(json_path, json.dumps(strict_json(record), indent=2, allow_nan=False) + "\n")
    png = plot_validation(result, out / VALIDATION_FILES[1])
    return json_path, png


def validate_to_folder(
    calib: SensorCalibration,
    out_dir: str | os.PathLike[str],
    settings: ValidationSettings | None = None,
    captures_dir: str | os.PathLike[str] | None = None,
) -> tuple[ValidationResult, Path, Path]:
    """The validation of Fig. 6 (``tofdenoise sensor validate``, ``tofdenoise reproduce --figure 6``): the camera's
    measured temporal noise (``captures_dir``, else the tap-level simulator) against ``calib``'s prediction,
    written to ``out_dir`` (``VALIDATION_FILES``). Returns the result and the two files."""
    result = run_validation(calib, settings or ValidationSettings(), captures_dir=captures_dir)
    json_path, png = write_validation(result, calib, out_dir)
    return result, json_path, png


def calibrate_simulated_camera(calib: SensorCalibration, seed: int = 0, shape: tuple[int, int] = (16, 16)) -> Any:
    """Calibrate a camera the way a user calibrates theirs (``tofdenoise sensor calibrate``), from its own
    simulated captures: the phase sweep, 100 dark frames and the distance sequence (``write_calibration_captures``:
    a grey chart across the working range for a camera with a photometric gain). Returns the ``CalibrationReport``;
    the presets' ``signal_min_e``/``signal_max_e`` and ``range_sigma_mm`` are measured with it (docs/physics.md)."""

    with tempfile.TemporaryDirectory(prefix="tofdenoise-calib-") as tmp:
        folders = write_calibration_captures(calib, tmp, shape=shape, seed=seed)
        return calibrate_from_folders(folders["sweep"], folders["dark"], folders["distances"])


__all__ = [
    "VALIDATION_FILES",
    "EXPOSURES",
    "calibrate_simulated_camera",
    "PLANAR_REFLECTANCE",
    "RANGE_DISTANCES_MM",
    "RANGE_FIT_DISTANCES_MM",
    "SIGNAL_DISTANCE_MM",
    "SURFACES",
    "Condition",
    "ValidationResult",
    "ValidationSettings",
    "captured_conditions",
    "mape_percent",
    "plot_validation",
    "r2_score",
    "RANGE_FIT_MIN_DISTANCES",
    "has_measured_std",
    "strict_json",
    "run_validation",
    "simulated_conditions",
    "validate_to_folder",
    "write_validation",
    "write_validation_captures",
]
