"""Simulated capture sets in the real capture format (see ``real_captures``), from built-in procedural scenes.

Per scene: the clean depth and amplitude of procedural scene ``i`` (seed ``seed``) give the returned signal
a(p) (``maps.scene_signal_e``: the physical route when the camera has a photometric gain ``signal_at_1m_e``, so dark far
surfaces and absorbers fall below the camera's threshold and specular highlights saturate; else the amplitude
mapped to the calibration's signal interval); then the tap-level simulator
(``tofdenoise.physics.simulator.simulate_frames``) produces
- one standard-exposure frame (exposure 1): the noisy input;
- ``frames`` high-exposure frames at ``min(hi_exposure, safe)`` where ``safe`` keeps the brightest expected tap
  10 % below the full well, so the reference frames do not saturate (any pixel that still reaches the full well
  is flagged in ``saturated_NNN.png`` and excluded by build-reference).
The simulator draws Poisson photo-electrons, Gaussian dark/read noise, clips at the full well, quantises to the
ADC gain and demodulates with the camera's N-phase atan2 decoder using the calibrated response (harmonics
included) - effects the Gaussian WLS training synthesis leaves out. With ``mixed_pixels = s > 1`` the scene is
ray-cast at s times the resolution and every pixel's taps integrate its s x s samples
(``tofdenoise.physics.mixed_pixels``): at a depth edge a pixel's taps mix the returns of both surfaces, a
flying pixel between them (in the input and in the high-exposure frames, as in a real camera); the ground
truth is the 1x render (the ray through the pixel centre). Frames are generated and written in chunks,
one scene at a time, so memory does not grow with the number of frames or scenes; a scene whose ``scene.json``
exists is complete and is skipped when the command is re-run (resume).

``workers`` > 1 simulates that many scenes at a time, each in a process of its own (spawned, with the CPU's
threads shared among them). Every scene draws its noise from its own generator (seed, scene index), so the files
are the same, byte for byte, whatever the number of workers and the order in which scenes finish.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from tofdenoise.atomic import atomic_write_text, save_npy_atomic
from tofdenoise.data_modules.datasets import stable_seed
from tofdenoise.data_modules.io import write_depth_png16, write_png_uint8, write_png_uint16
from tofdenoise.data_modules.maps import scene_signal_e
from tofdenoise.data_modules.real_captures import HIEXP_DIR, INPUT_AMPLITUDE, INPUT_DEPTH, build_reference
from tofdenoise.data_modules.sources.base import SourceContext
from tofdenoise.data_modules.sources.procedural import (
    DEFAULT_MAX_DEPTH_FRACTION,
    DEFAULT_MIN_DEPTH_MM,
    ProceduralSource,
)
from tofdenoise.physics.calibration import resolve_calibration, save_calibration
from tofdenoise.physics.mixed_pixels import footprint_tap_means_e, mixed_pixel_map
from tofdenoise.physics.simulator import simulate_frames, simulate_tap_mean_frames
from tofdenoise.physics.uncertainty import tap_responses

SCENE_DONE = "scene.json"
GROUND_TRUTH = "ground_truth_depth_mm.npy"
SIMULATED_CAMERA = "simulated_camera.yaml"
SATURATION_MARGIN = 0.9
# the high-exposure frames may saturate the brightest 2 % of the pixels that the standard exposure does not
REFERENCE_PEAK_PERCENTILE = 98.0


@dataclass
class SimulationSummary:
    out_dir: Path
    scenes_written: int
    scenes_skipped: int
    seconds: float


def amplitude_to_png(amplitude_e: np.ndarray) -> np.ndarray:
    """Amplitude in electrons rounded and clipped to 16 bit."""
    return np.clip(np.rint(np.nan_to_num(np.asarray(amplitude_e, dtype=np.float64))), 0, 65535).astype(np.uint16)


def safe_exposure(depth_mm: np.ndarray, signal_e: np.ndarray, calib: Any, requested: float) -> float:
    """Largest exposure <= requested whose brightest expected tap stays SATURATION_MARGIN below the full well.

    Pixels that saturate already at the standard exposure (specular highlights, white surfaces close by) cannot be
    kept out of saturation by any exposure above it, and a few bright ones should not hold the whole frame at the
    standard exposure: the exposure is chosen for the REFERENCE_PEAK_PERCENTILE-th percentile of the others' peaks
    (never below 1). Pixels that saturate are flagged in the high-exposure frames and left out of the reference."""
    ok = (depth_mm > 0) & np.isfinite(signal_e) & (signal_e > 0)
    if not ok.any():
        return float(requested)
    responses, _ = tap_responses(depth_mm[ok].astype(np.float64), calib)
    peaks = (signal_e[ok][:, None] * np.asarray(responses)).max(axis=1)
    headroom = SATURATION_MARGIN * calib.full_well_e - calib.dark_mean_e - 6.0 * calib.dark_std_e
    peaks = peaks[peaks < headroom]  # empty when headroom <= 0 (every peak is > 0)
    if peaks.size == 0:
        return 1.0
    peak = float(np.percentile(peaks, REFERENCE_PEAK_PERCENTILE))
    if peak <= 0:
        return float(requested)
    return float(max(min(requested, headroom / peak), min(requested, 1.0)))


def write_readme(out_dir: Path, params: dict[str, Any]) -> None:
    text = f"""# Simulated iToF capture set (NOT real data)

This folder was generated by `tofdenoise sensor simulate-captures`. Every scene is a built-in procedural
scene rendered and passed through the tap-level simulator of `tofdenoise.physics` (Poisson photo-electrons,
dark/read noise, full-well clipping and saturation flags, ADC quantisation, the calibrated tap response with
its harmonics, N-phase atan2 demodulation). It stands in for a private real capture set so that the real-data
evaluation path runs end to end; results on it are simulation results.

Parameters: `{json.dumps(params, sort_keys=True)}`

Layout per scene (`<scene>/`):
- `input_depth_mm.png` 16-bit depth [mm], 0 = invalid - the standard-exposure frame (noisy input)
- `input_amplitude.png` 16-bit amplitude [e-] of the same frame
- `hiexp/depth_mm_NNN.png` 16-bit [mm] and `hiexp/saturated_NNN.png` 8-bit (nonzero = saturated): high-exposure
  frames for the reference (exposure in `scene.json`)
- `reference_depth_mm.npy` (float32, NaN = invalid), `reference_count.npy`, `reference.json`: the multi-frame
  reference (`tofdenoise sensor build-reference`)
- `ground_truth_depth_mm.npy`: the clean rendered depth (only simulated sets have it)

`simulated_camera.yaml` (next to this file) is the camera the set was simulated with: the simulation's ground
truth, not a calibration to train with (calibrate the camera from its own captures, docs/camera-tutorial.md).
- `scene.json`: per-scene settings; its presence marks the scene as complete
"""
    atomic_write_text(out_dir / "README.md", text)


def simulate_scene(
    scene_dir: Path,
    source: ProceduralSource,
    index: int,
    calib: Any,
    frames: int,
    hi_exposure: float,
    seed: int,
    chunk_frames: int = 8,
    write_taps: bool = False,
    min_count: int | None = None,
    mixed_pixels: int = 1,
) -> dict[str, Any]:

    sample_id = f"scene_{index:06d}"
    raw = source.load(sample_id)
    fine = raw if mixed_pixels == 1 else source.supersampled(mixed_pixels).load(sample_id)
    signal = scene_signal_e(fine, calib, source.hfov_deg)
    depth = np.where(fine.valid, fine.depth_mm, 0.0).astype(np.float32)
    generator = torch.Generator().manual_seed(stable_seed(seed, "captures", index))
    if mixed_pixels == 1:  # one surface per pixel: the simulator's own tap means (bit-identical to earlier sets)

        def simulate(count: int, exposure: float):
            return simulate_frames(
                depth, signal, calib, count, exposure=exposure, generator=generator, return_taps=write_taps
            )
    else:
        tap_means = footprint_tap_means_e(depth, signal, calib, mixed_pixels)

        def simulate(count: int, exposure: float):
            return simulate_tap_mean_frames(
                tap_means, calib, count, exposure=exposure, generator=generator, return_taps=write_taps
            )

    hiexp = scene_dir / HIEXP_DIR
    hiexp.mkdir(parents=True, exist_ok=True)

    standard = simulate(1, 1.0)
    write_depth_png16(scene_dir / INPUT_DEPTH, standard.depth_mm[0].numpy())
    write_png_uint16(scene_dir / INPUT_AMPLITUDE, amplitude_to_png(standard.amplitude[0].numpy()))
    if write_taps:
        save_npy_atomic(scene_dir / "input_taps.npy", standard.taps[0].numpy())
    save_npy_atomic(scene_dir / GROUND_TRUTH, np.where(raw.valid, raw.depth_mm, np.nan).astype(np.float32))

    exposure = safe_exposure(depth, signal, calib, hi_exposure)  # the brightest sample bounds every mix
    saturated_pixels = 0
    width = max(3, len(str(frames - 1)))
    for start in range(0, frames, chunk_frames):
        count = min(chunk_frames, frames - start)
        captured = simulate(count, exposure)
        for k in range(count):
            tag = f"{start + k:0{width}d}"
            write_depth_png16(hiexp / f"depth_mm_{tag}.png", captured.depth_mm[k].numpy())
            saturated = captured.saturated[k].numpy()
            saturated_pixels += int(saturated.sum())
            write_png_uint8(hiexp / f"saturated_{tag}.png", (saturated * 255).astype(np.uint8))
            if write_taps:
                save_npy_atomic(hiexp / f"taps_{tag}.npy", captured.taps[k].numpy())
        del captured
    reference = build_reference(scene_dir, min_count=min_count, force=True)
    info = {
        "scene_index": index,
        "seed": seed,
        "height": source.height,
        "width": source.width,
        "frames": frames,
        "input_exposure": 1.0,
        "reference_exposure": exposure,
        "saturated_pixel_frames": saturated_pixels,
        "mixed_pixels": mixed_pixels,
        "mixed_pixel_fraction": float(mixed_pixel_map(depth, mixed_pixels).mean()),
        "input_valid_fraction": float(standard.valid[0].float().mean()),
        "reference_valid_fraction": float(np.isfinite(reference.depth_mm).mean()),
        "calibration_fingerprint": calib.fingerprint(),
    }
    atomic_write_text(scene_dir / SCENE_DONE, json.dumps(info, indent=1) + "\n")
    return info


def _scene_name(index: int, digits: int) -> str:
    return f"scene_{index:0{digits}d}"


def _scene_complete(scene_dir: Path, params: dict[str, Any]) -> bool:
    """Whether ``scene_dir`` holds a finished scene (``scene.json``) of these settings: it is skipped (resume)."""
    try:
        info = json.loads((scene_dir / SCENE_DONE).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    return (
        info.get("frames") == params["frames"]
        and info.get("calibration_fingerprint") == params["calibration_fingerprint"]
        and info.get("seed") == params["seed"]
        and info.get("height") == params["height"]
        and info.get("width") == params["width"]
        and info.get("mixed_pixels", 1) == params["mixed_pixels"]
    )


def _simulate_one(
    index: int,
    *,
    out: str,
    digits: int,
    source_config: dict[str, Any],
    seed: int,
    calib: Any,
    frames: int,
    hi_exposure: float,
    write_taps: bool,
    min_count: int | None,
    mixed_pixels: int,
    source: ProceduralSource | None = None,
    threads: int | None = None,
) -> dict:
    """Scene ``index`` of ``simulate_capture_set`` (in this process, or in a worker: ``threads`` torch threads, the
    scene source rebuilt from ``source_config``)."""
    if threads is not None:
        torch.set_num_threads(threads)
    if source is None:
        source = ProceduralSource.from_config(source_config, SourceContext(seed=seed, calibration=calib))
    scene_dir = Path(out) / _scene_name(index, digits)
    try:
        scene_dir.mkdir(parents=True, exist_ok=True)
        return simulate_scene(
            scene_dir,
            source,
            index,
            calib,
            frames,
            hi_exposure,
            seed,
            write_taps=write_taps,
            min_count=min_count,
            mixed_pixels=mixed_pixels,
        )
    except Exception as exc:
        exc.add_note(f"while simulating scene {scene_dir}")
        raise


def simulate_capture_set(
    out_dir: str | Path,
    scenes: int,
    frames: int,
    height: int = 480,
    width: int = 640,
    seed: int = 0,
    calib: Any = None,
    hi_exposure: float = 4.0,
    min_depth_mm: float = DEFAULT_MIN_DEPTH_MM,
    max_depth_fraction: float = DEFAULT_MAX_DEPTH_FRACTION,
    write_taps: bool = False,
    force: bool = False,
    min_count: int | None = None,
    mixed_pixels: int = 1,
    progress: Callable[[int, int, dict], None] | None = None,
    workers: int = 1,
) -> SimulationSummary:
    """Write ``scenes`` simulated scenes (``scene_0000`` ...) with ``frames`` high-exposure frames each;
    ``mixed_pixels`` = s > 1 integrates s x s samples per pixel (mixed pixels at depth edges); ``workers`` scenes
    at a time (module docstring). ``progress(index, scenes, info)`` is called as each scene is written."""
    if scenes < 1 or frames < 1:
        raise ValueError(f"--scenes and --frames must be >= 1, got {scenes} and {frames}")
    if hi_exposure <= 0:
        raise ValueError(f"--hi-exposure must be > 0, got {hi_exposure}")
    if int(workers) != workers or workers < 1:
        raise ValueError(f"--workers must be an integer >= 1, got {workers}")
    if int(mixed_pixels) != mixed_pixels or mixed_pixels < 1:
        raise ValueError(f"--mixed-pixels must be an integer >= 1 (samples per pixel side), got {mixed_pixels}")
    mixed_pixels = int(mixed_pixels)
    calib = resolve_calibration(calib)
    out = Path(out_dir).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    # the training scenes' source as the datamodule builds it (data.source_kwargs + the seed and this camera)
    settings = {"num_samples": scenes, "height": height, "width": width, "min_depth_mm": min_depth_mm}
    source_config = {**settings, "max_depth_fraction": max_depth_fraction}
    source = ProceduralSource.from_config(source_config, SourceContext(seed=seed, calibration=calib))
    params = {
        "scenes": scenes,
        "frames": frames,
        "height": height,
        "width": width,
        "seed": seed,
        "hi_exposure_requested": hi_exposure,
        "calibration_fingerprint": calib.fingerprint(),
        "min_depth_mm": min_depth_mm,
        "max_depth_mm": source.max_depth_mm,
        "mixed_pixels": mixed_pixels,
    }
    write_readme(out, params)

    save_calibration(
        calib,
        out / SIMULATED_CAMERA,
        header=(
            "The camera this capture set was simulated with (ground truth of the simulation). A real capture set has\n"
            "no such file: calibrate the camera (tofdenoise sensor calibrate, docs/camera-tutorial.md) and train\n"
            "with that calibration, not with this one."
        ),
    )
    started = time.perf_counter()
    digits = max(4, len(str(scenes - 1)))
    todo = [index for index in range(scenes) if force or not _scene_complete(out / _scene_name(index, digits), params)]
    skipped = scenes - len(todo)
    simulate = partial(
        _simulate_one,
        out=str(out),
        digits=digits,
        source_config=source_config,
        seed=seed,
        calib=calib,
        frames=frames,
        hi_exposure=hi_exposure,
        write_taps=write_taps,
        min_count=min_count,
        mixed_pixels=mixed_pixels,
    )
    workers = max(1, min(int(workers), len(todo)))
    if workers == 1:
        for index in todo:
            info = simulate(index, source=source)
            if progress is not None:
                progress(index, scenes, info)
    else:
        threads = max(1, (os.cpu_count() or 1) // workers)
        pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
        try:
            futures = {pool.submit(simulate, index, threads=threads): index for index in todo}
            for future in as_completed(futures):
                info = future.result()  # a worker's error is raised here, with a note naming its scene
                if progress is not None:
                    progress(futures[future], scenes, info)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    written = len(todo)
    return SimulationSummary(out, written, skipped, time.perf_counter() - started)
