"""The stand-in real set: a second simulated camera's calibration captures, the calibration estimated from them, its
capture set and its noise-validation captures (``tofdenoise sensor realset``, ``make realset``, the first step of
``tofdenoise reproduce``; the camera engineer's flow of docs/camera-tutorial.md, run as one function).

Steps, into ``out``:

a) ``calibration-captures/``: the camera's phase sweep, dark frames and distance sequence
   (``physics.synthetic_captures.write_calibration_captures``, what ``tofdenoise sensor simulate-calibration``
   writes);
b) ``calibration.yaml``: the calibration estimated from them (``physics.calibrate.calibrate_to_file``, what
   ``tofdenoise sensor calibrate`` writes); ``realset.json`` records the camera and seed it was made for;
c) ``captures/``: its capture set with mixed pixels at depth edges (``capture_simulation.simulate_capture_set``,
   ``tofdenoise sensor simulate-captures``);
d) ``validation/``: the Fig. 6 conditions as this camera records them
   (``physics.validation.write_validation_captures``, ``tofdenoise sensor simulate-validation``).

Resumable: a) and b) are skipped when ``realset.json`` matches the camera and seed and the calibration exists,
complete scenes of c) are skipped, and d) is skipped when its index exists (``force`` redoes a), b) and d) and
rewrites the scenes).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tofdenoise.atomic import atomic_write_text
from tofdenoise.data_modules.capture_simulation import SimulationSummary, simulate_capture_set
from tofdenoise.output_guard import refuse_overwrite
from tofdenoise.physics.calibrate import calibrate_to_file
from tofdenoise.physics.calibration import resolve_calibration
from tofdenoise.physics.capture_io import INDEX_NAME
from tofdenoise.physics.synthetic_captures import write_calibration_captures
from tofdenoise.physics.validation import ValidationSettings, write_validation_captures

__all__ = ["REALSET_CAMERA", "REALSET_SEED", "RealsetSummary", "build_realset"]

#: the stand-in real set's camera: differs from configs/sensor/default.yaml in modulation frequency (75 vs 50 MHz),
#: contrast (0.54 vs 0.50), harmonics (a 2nd harmonic with a sine part vs a 3rd), dark level (800 vs 2000 e-)
#: and ADC gain (4 vs 25 e-/DN); tests/cli/test_realset.py checks each difference
REALSET_CAMERA = "cam75"
#: procedural scene seed of the stand-in real set: not a training seed (the training scenes use data.seed)
REALSET_SEED = 1000
#: what ``build_realset`` writes into ``out``
CALIBRATION_CAPTURES, CALIBRATION, CAPTURES, VALIDATION, RECORD = (
    "calibration-captures",
    "calibration.yaml",
    "captures",
    "validation",
    "realset.json",
)


@dataclass
class RealsetSummary:
    out: Path
    calibration: Path
    captures: Path
    validation: Path
    #: the steps that ran ("a", "b", "c", "d"); c) always runs (it skips complete scenes itself)
    steps: tuple[str, ...]
    capture_set: SimulationSummary


def _camera_files(camera: str | Path) -> list[Path]:
    """The camera given as a file (not a preset name): an input no output may replace."""
    return [Path(camera)] if Path(camera).expanduser().exists() else []


def build_realset(
    out: str | Path,
    camera: str | Path | None = None,
    scenes: int = 200,
    frames: int = 100,
    height: int = 128,
    width: int = 160,
    seed: int | None = None,
    mixed_pixels: int = 3,
    force: bool = False,
    log: Callable[[str], None] = print,
    workers: int | None = None,
) -> RealsetSummary:
    """Steps a)-d) of the module docstring for ``camera`` (a preset name or a calibration file; default
    ``REALSET_CAMERA``) and the scene and noise ``seed`` (default ``REALSET_SEED``) into ``out``; each step is
    announced through ``log`` before it runs; ``workers`` scenes of the capture set are simulated at a time
    (``capture_simulation``: the same files whatever the number; None: one per CPU core). The defaults are the CPU
    profile's set: the paper's 200 scenes at 128 x 160. Errors: ``ValueError`` (a bad setting, an unknown
    camera), ``OutputPathError`` (``out`` would replace the camera's file), ``CaptureFormatError``, ``WriteError``."""
    camera = REALSET_CAMERA if camera is None else camera
    workers = (os.cpu_count() or 1) if workers is None else workers
    seed = REALSET_SEED if seed is None else seed
    out = Path(out).expanduser()
    refuse_overwrite([], _camera_files(camera), output_folders=[out])
    calib = resolve_calibration(camera)
    caps, calibration = out / CALIBRATION_CAPTURES, out / CALIBRATION
    record = {"camera": str(camera), "camera_fingerprint": calib.fingerprint(), "seed": seed}
    try:
        calibrated = json.loads((out / RECORD).read_text(encoding="utf-8")) == record and calibration.is_file()
    except (OSError, json.JSONDecodeError):
        calibrated = False
    steps = []
    if calibrated and not force:
        log(f"{calibration} is up to date: steps a) and b) skipped (--force redoes them)")
    else:
        log(f"a) calibration captures of camera {camera} (seed {seed}) -> {caps}")
        folders = write_calibration_captures(calib, caps, seed=seed)
        log(f"b) calibration from {caps} -> {calibration}")
        report, _ = calibrate_to_file(folders["sweep"], folders["dark"], folders["distances"], calibration)
        for warning in report.warnings:
            log(f"warning: {warning}")
        atomic_write_text(out / RECORD, json.dumps(record, indent=1) + "\n")
        steps += ["a", "b"]

    def progress(index: int, total: int, info: dict) -> None:
        log(
            f"scene {index + 1}/{total}: reference exposure {info['reference_exposure']:.3g}, "
            f"input valid {info['input_valid_fraction']:.3f}, reference valid {info['reference_valid_fraction']:.3f}"
        )

    log(
        f"c) capture set: {scenes} scene(s) of {height} x {width}, {frames} frames, mixed pixels {mixed_pixels} -> "
        f"{out / CAPTURES}"
    )
    capture_set = simulate_capture_set(
        out / CAPTURES,
        scenes=scenes,
        frames=frames,
        height=height,
        width=width,
        seed=seed,
        calib=camera,
        force=force,
        mixed_pixels=mixed_pixels,
        progress=progress,
        workers=workers,
    )
    log(
        f"capture set in {capture_set.out_dir}: {capture_set.scenes_written} scene(s) written, "
        f"{capture_set.scenes_skipped} already complete"
    )
    steps.append("c")
    if force or not (out / VALIDATION / INDEX_NAME).is_file():
        log(f"d) noise-validation captures (the Fig. 6 conditions) -> {out / VALIDATION}")
        settings = ValidationSettings(num_frames=100, seed=seed, fit_seed=seed + 1)
        write_validation_captures(calib, out / VALIDATION, settings)
        steps.append("d")
    return RealsetSummary(out, calibration, out / CAPTURES, out / VALIDATION, tuple(steps), capture_set)
