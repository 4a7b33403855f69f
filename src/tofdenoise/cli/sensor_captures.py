"""`tofdenoise sensor simulate-calibration`, `simulate-captures`, `simulate-validation`, `realset` and
`build-reference` (a simulated camera's calibration captures and capture sets; the stand-in real set, all its steps
at once: `tofdenoise.data_modules.realset`).

Formats: calibration captures `tofdenoise.physics.capture_io` (docs/physics.md), capture sets
`tofdenoise.data_modules.real_captures` (docs/data.md); the whole flow: docs/camera-tutorial.md.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from tofdenoise.cli.sensor_physics import input_files
from tofdenoise.experiments.targets import REALSET_SIZES
from tofdenoise.output_guard import OutputPathError, refuse_overwrite

#: exit status after Ctrl-C (128 + SIGINT, what a shell reports)
EXIT_INTERRUPTED = 130


def _simulate(args: argparse.Namespace) -> int:
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set

    def progress(index: int, total: int, info: dict) -> None:
        if not args.quiet:
            print(
                f"scene {index + 1}/{total}: reference exposure {info['reference_exposure']:.3g}, "
                f"input valid {info['input_valid_fraction']:.3f}, reference valid "
                f"{info['reference_valid_fraction']:.3f}",
                flush=True,
            )

    refuse_overwrite([], input_files(args.sensor), output_folders=[args.out])
    summary = simulate_capture_set(
        args.out,
        scenes=args.scenes,
        frames=args.frames,
        height=args.height,
        width=args.width,
        seed=args.seed,
        calib=args.sensor,
        hi_exposure=args.hi_exposure,
        write_taps=args.taps,
        force=args.force,
        min_count=args.min_count,
        mixed_pixels=args.mixed_pixels,
        progress=progress,
        workers=args.workers,
    )
    per_scene = summary.seconds / max(summary.scenes_written, 1)
    print(
        f"simulated capture set in {summary.out_dir}: {summary.scenes_written} scene(s) written, "
        f"{summary.scenes_skipped} already complete, {summary.seconds:.1f} s ({per_scene:.2f} s per scene)"
    )
    return 0


def _simulate_calibration(args: argparse.Namespace) -> int:
    from tofdenoise.physics.calibration import resolve_calibration
    from tofdenoise.physics.synthetic_captures import default_distances_mm, write_calibration_captures

    refuse_overwrite([], input_files(args.sensor), output_folders=[args.out])
    calib = resolve_calibration(args.sensor)
    distances = args.distances_mm if args.distances_mm is not None else default_distances_mm(calib)
    too_far = [d for d in distances if not 0 < d < calib.unambiguous_range_mm]
    if too_far:
        raise ValueError(
            f"--distances-mm {too_far[0]:g}: distances must lie in (0, {calib.unambiguous_range_mm:.0f}) "
            f"mm, the unambiguous range of this camera ({calib.modulation_frequency_hz / 1e6:g} MHz)"
        )
    for name, value in (
        ("--sweep-steps", args.sweep_steps),
        ("--sweep-frames", args.sweep_frames),
        ("--dark-frames", args.dark_frames),
        ("--distance-frames", args.distance_frames),
        ("--size", args.size),
    ):
        if value < 2:
            raise ValueError(f"{name} must be >= 2, got {value}")
    folders = write_calibration_captures(
        calib,
        args.out,
        sweep_steps=args.sweep_steps,
        sweep_frames=args.sweep_frames,
        dark_frames=args.dark_frames,
        distances_mm=distances,
        distance_frames=args.distance_frames,
        shape=(args.size, args.size),
        seed=args.seed,
    )
    out = Path(args.out)
    for name, folder in folders.items():
        print(f"wrote {folder} ({name})")
    print(
        f"next: tofdenoise sensor calibrate --sweep {out}/sweep --dark {out}/dark --distances {out}/distances "
        "--out CALIBRATION.yaml"
    )
    return 0


def _simulate_validation(args: argparse.Namespace) -> int:
    from tofdenoise.physics.calibration import resolve_calibration
    from tofdenoise.physics.validation import ValidationSettings, write_validation_captures

    for name, value in (("--frames", args.frames), ("--roi-px", args.roi_px)):
        if value < 2:
            raise ValueError(f"{name} must be >= 2, got {value}")
    refuse_overwrite([], input_files(args.sensor), output_folders=[args.out])
    settings = ValidationSettings(num_frames=args.frames, roi_px=args.roi_px, seed=args.seed, fit_seed=args.seed + 1)
    folder = write_validation_captures(resolve_calibration(args.sensor), args.out, settings)
    print(f"wrote {folder} (validation)")
    print(f"next: tofdenoise sensor validate --captures {folder} --sensor CALIBRATION.yaml --out DIR")
    return 0


def _realset_from_recording(args: argparse.Namespace) -> int:
    """``realset --from-recording REC``: a static recording -> one capture-set scene in ``--out``."""
    from tofdenoise.inference.recording_realset import scene_from_recording

    rec = Path(args.from_recording).expanduser()
    out = Path(args.out).expanduser()
    name = args.scene or (rec.stem if rec.is_file() else rec.name)
    if out.exists() and not out.is_dir():  # --out REC.mkv: a FileExistsError once the recording was read
        refuse_overwrite([out], [rec])
        raise OutputPathError(f"--out {out} is a file; give the folder of the capture set")
    refuse_overwrite([], [rec], output_folders=[out / name])
    try:
        summary = scene_from_recording(
            rec,
            out,
            scene=name,
            depth_stream=args.depth_stream,
            amplitude_stream=args.amplitude_stream,
            input_frame=args.input_frame,
            min_count=args.min_count,
            motion_tolerance_mm=args.motion_tolerance_mm,
            force=args.force,
        )
    except KeyboardInterrupt:  # before the scene was published: its partial folder is removed, nothing else written
        print(
            f"tofdenoise sensor realset: interrupted (Ctrl-C); scene {out / name} not written "
            f"({'the scene there is unchanged' if args.force and (out / name).exists() else 'nothing published'})",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    for folder in summary.stale_partials_removed:
        print(f"removed {folder}: the partial scene of an earlier run that was killed", file=sys.stderr)
    print(
        f"scene {summary.scene_dir}: input frame {summary.input_frame}, reference = mean of "
        f"{summary.reference_frames} frames (a pixel needs {summary.min_count} valid), valid reference pixels "
        f"{summary.reference_valid_fraction:.3f}; frames agree (at most {100 * summary.disagreeing_fraction_max:.1f} "
        f"% of a frame's pixels off the median)\n"
        f"test on it: tofdenoise train ++data.sensor=YOUR_CALIBRATION.yaml ++data.real_dir={out}"
        + (f" ++data.real_min_count={args.min_count}" if args.min_count is not None else "")
    )
    return 0


def _realset(args: argparse.Namespace) -> int:
    if args.from_recording is not None:
        return _realset_from_recording(args)
    from tofdenoise.data_modules.realset import build_realset

    summary = build_realset(
        args.out,
        args.sensor,
        scenes=args.scenes,
        frames=args.frames,
        height=args.height,
        width=args.width,
        seed=args.seed,
        mixed_pixels=args.mixed_pixels,
        force=args.force,
        log=lambda line: print(line, flush=True),
        workers=args.workers,
    )
    print(
        f"stand-in real set ready: train with its calibration and test on its captures:\n"
        f"  tofdenoise train ++data.sensor={summary.calibration} ++data.real_dir={summary.captures}"
    )
    return 0


def _build_reference(args: argparse.Namespace) -> int:
    import numpy as np

    from tofdenoise.data_modules.real_captures import HIEXP_DIR, build_reference, list_scenes

    root = Path(args.scenes_dir).expanduser()
    if (root / HIEXP_DIR).is_dir():  # a single scene folder
        scenes = [root]
    else:
        scenes = list_scenes(root, config_key="SCENES_DIR")
    rebuilt = 0
    for scene in scenes:
        ref = build_reference(scene, min_count=args.min_count, force=args.force)
        rebuilt += int(ref.rebuilt)
        if not args.quiet:
            valid = float((ref.count > 0).mean()) if ref.count.size else 0.0
            derived = (
                f" (min_count {ref.min_count} from the cached reference at min_count {ref.cached_min_count}, exactly; "
                f"--force caches it at {ref.min_count})"
                if ref.cached_min_count is not None and ref.cached_min_count != ref.min_count
                else ""
            )
            print(
                f"{scene.name}: {'rebuilt' if ref.rebuilt else 'up to date'}{derived}; valid reference pixels "
                f"{float(np.isfinite(ref.depth_mm).mean()):.3f} (any frame {valid:.3f}); frames per pixel "
                f"max {int(ref.count.max())}"
            )
    print(f"{len(scenes)} scene(s): {rebuilt} reference(s) rebuilt, {len(scenes) - rebuilt} up to date")
    return 0


WORKERS_HELP = (
    "scenes simulated at a time, each in its own process (default: the number of CPU cores, os.cpu_count()). The "
    "files are the same whatever the number"
)


#: the stand-in real set ``tofdenoise sensor realset`` builds by default: the CPU profile's (scenes, height, width)
REALSET_SCENES, *REALSET_SHAPE = REALSET_SIZES["cpu"]


def default_workers() -> int:
    """Scenes simulated at a time when ``--workers`` is not given: one per CPU core."""
    return os.cpu_count() or 1


def add_commands(subparsers) -> None:
    sim = subparsers.add_parser(
        "simulate-captures",
        help="write a simulated capture set (built-in scenes through the tap-level simulator)",
        description="Create a capture set in the real-capture format from built-in procedural scenes: one "
        "standard-exposure frame (noisy input) and high-exposure frames without saturation for the "
        "reference, simulated at tap level (Poisson, dark noise, full well, ADC, harmonics).",
    )
    sim.add_argument("--out", required=True, help="output folder (SCENES_DIR)")
    sim.add_argument("--scenes", type=int, default=200, help="number of scenes (default 200)")
    sim.add_argument("--frames", type=int, default=100, help="high-exposure frames per scene (default 100)")
    sim.add_argument("--height", type=int, default=480)
    sim.add_argument("--width", type=int, default=640)
    sim.add_argument("--seed", type=int, default=0, help="scene and noise seed")
    sim.add_argument("--sensor", default=None, help="calibration file or preset (default: configs/sensor/default.yaml)")
    sim.add_argument(
        "--hi-exposure",
        type=float,
        default=4.0,
        help="requested reference exposure (lowered per scene to stay below the full well)",
    )
    sim.add_argument(
        "--min-count", type=int, default=None, help="valid frames a reference pixel needs (default: half of the frames)"
    )
    sim.add_argument(
        "--mixed-pixels",
        type=int,
        default=1,
        metavar="S",
        help="integrate S x S samples per pixel, so pixels at depth edges mix the returns of both "
        "surfaces (default 1: one surface per pixel)",
    )
    sim.add_argument("--workers", type=int, default=default_workers(), help=WORKERS_HELP)
    sim.add_argument("--taps", action="store_true", help="also write raw tap stacks (.npy)")
    sim.add_argument("--force", action="store_true", help="rewrite scenes that are already complete")
    sim.add_argument("--quiet", action="store_true")
    sim.set_defaults(func=_simulate)

    cal = subparsers.add_parser(
        "simulate-calibration",
        help="write a simulated camera's calibration captures (phase sweep, dark frames, distance sequence)",
        description="Write the three capture folders `tofdenoise sensor calibrate` reads (format "
        "tofdenoise-captures-v1, docs/physics.md) as the camera --sensor records them through the "
        "tap-level simulator: OUT/sweep (a planar target at --sweep-steps phases), OUT/dark "
        "(--dark-frames emitter-off frames, in DN when the camera has an ADC gain) and OUT/distances "
        "(a planar target at --distances-mm).",
    )
    cal.add_argument("--out", required=True, help="output folder (sweep/, dark/, distances/ are written in it)")
    cal.add_argument(
        "--sensor",
        default=None,
        help="the simulated camera: calibration file or preset (default: configs/sensor/default.yaml)",
    )
    cal.add_argument("--sweep-steps", type=int, default=24, help="phase steps of the sweep (default 24)")
    cal.add_argument("--sweep-frames", type=int, default=20, help="frames per sweep step (default 20)")
    cal.add_argument("--dark-frames", type=int, default=100, help="emitter-off frames (default 100)")
    cal.add_argument(
        "--distances-mm",
        type=float,
        nargs="+",
        default=None,
        metavar="D",
        help="planar-target distances (default: 10 from 25 %% to 75 %% of the unambiguous range)",
    )
    cal.add_argument("--distance-frames", type=int, default=100, help="frames per distance (default 100)")
    cal.add_argument("--size", type=int, default=16, help="captured region side in pixels (default 16)")
    cal.add_argument("--seed", type=int, default=0, help="noise seed")
    cal.set_defaults(func=_simulate_calibration)

    real = subparsers.add_parser(
        "realset",
        help="the stand-in real set: a second simulated camera's calibration and capture set (one command)",
        description="Run the camera tutorial's steps for a simulated camera unlike the training default "
        "(docs/camera-tutorial.md): simulate-calibration -> OUT/calibration-captures, calibrate -> "
        "OUT/calibration.yaml, simulate-captures (mixed pixels at depth edges) -> OUT/captures, "
        "simulate-validation -> OUT/validation (the Fig. 6 conditions), in this process "
        "(tofdenoise.data_modules.realset). Each step is printed before it runs. Resumable: an existing "
        "OUT/calibration.yaml is kept (--force redoes it) and completed scenes are skipped.",
    )
    real.add_argument("--out", required=True, help="output folder")
    real.add_argument(
        "--sensor",
        default=None,
        help="the simulated camera: preset or calibration file (default: the stand-in camera, preset cam75; "
        "tofdenoise.data_modules.realset.REALSET_CAMERA)",
    )
    real.add_argument(
        "--scenes",
        type=int,
        default=REALSET_SCENES,
        help=f"static scenes (default {REALSET_SCENES}, the paper's count)",
    )
    real.add_argument("--frames", type=int, default=100, help="high-exposure frames per scene (default 100)")
    real.add_argument(
        "--height", type=int, default=REALSET_SHAPE[0], help=f"default {REALSET_SHAPE[0]} (the CPU profile's scenes)"
    )
    real.add_argument("--width", type=int, default=REALSET_SHAPE[1], help=f"default {REALSET_SHAPE[1]}")
    real.add_argument(
        "--seed",
        type=int,
        default=None,
        help="scene and noise seed (default 1000, REALSET_SEED; not a training data.seed)",
    )
    real.add_argument(
        "--mixed-pixels",
        type=int,
        default=3,
        metavar="S",
        help="samples per pixel side (default 3: mixed pixels at depth edges)",
    )
    real.add_argument("--workers", type=int, default=default_workers(), help=WORKERS_HELP)
    real.add_argument(
        "--force",
        action="store_true",
        help="redo the calibration captures and the calibration (--from-recording: replace the scene)",
    )
    rec = real.add_argument_group(
        "your own scene from a static recording (docs/camera-tutorial.md, step 6; the simulation options above do "
        "not apply)"
    )
    rec.add_argument(
        "--from-recording",
        default=None,
        metavar="REC",
        help="an Azure Kinect .mkv, ROS 1 .bag or ROS 2 bag folder of a static scene: writes the capture-set scene "
        "OUT/<scene> (input = one frame, reference = mean of the other frames' valid depths)",
    )
    rec.add_argument("--scene", default=None, help="scene folder name (default: the recording's name)")
    rec.add_argument("--input-frame", type=int, default=0, help="the frame used as the noisy input (default 0)")
    rec.add_argument(
        "--min-count",
        type=int,
        default=None,
        help="valid frames a reference pixel needs (default: half of the reference frames, as data.real_min_count; "
        "train with ++data.real_min_count=N when you change it)",
    )
    rec.add_argument(
        "--motion-tolerance-mm",
        type=float,
        default=20.0,
        help="a pixel farther than max(this, 1%% of its depth) from the frames' median disagrees; more than 5%% "
        "disagreeing pixels in a frame = the scene moved (an error; default 20)",
    )
    rec.add_argument("--depth-stream", default=None, metavar="NAME", help="depth topic / track of the recording")
    rec.add_argument(
        "--amplitude-stream", default=None, metavar="NAME", help="amplitude / IR topic / track of the recording"
    )
    real.set_defaults(func=_realset)

    val = subparsers.add_parser(
        "simulate-validation",
        help="write a simulated camera's noise-validation captures (the Fig. 6 conditions)",
        description="Planar targets at 500..1500 mm every 100 mm, black/gray/white surfaces at 1500 mm under "
        "exposures 1-4, and an independent 550..1450 mm sequence for the range-aware fit, as tap "
        "stacks of the camera --sensor (kind validation, format tofdenoise-captures-v1). "
        "`tofdenoise sensor validate --captures OUT --sensor C` then compares the measured temporal "
        "noise with the prediction of the calibration C (e.g. the one `calibrate` estimated).",
    )
    val.add_argument("--out", required=True, help="output folder")
    val.add_argument(
        "--sensor",
        default=None,
        help="the simulated camera: calibration file or preset (default: configs/sensor/default.yaml)",
    )
    val.add_argument("--frames", type=int, default=100, help="frames per condition (default 100)")
    val.add_argument("--roi-px", type=int, default=32, help="captured region side in pixels (default 32)")
    val.add_argument("--seed", type=int, default=2024, help="noise seed (the range-fit sequence uses seed + 1)")
    val.set_defaults(func=_simulate_validation)

    ref = subparsers.add_parser(
        "build-reference",
        help="build the multi-frame reference depth of every scene in a capture set",
        description="Per-pixel mean over the valid, unsaturated high-exposure frames (hiexp/), with a per-pixel "
        "count; pixels with fewer than --min-count frames are invalid (NaN). Written next to each "
        "scene (reference_depth_mm.npy, reference_count.npy); skipped when up to date.",
    )
    ref.add_argument("scenes_dir", help="capture set folder (or one scene folder)")
    ref.add_argument(
        "--min-count", type=int, default=None, help="valid frames a pixel needs (default: half of the scene's frames)"
    )
    ref.add_argument("--force", action="store_true", help="rebuild even when up to date")
    ref.add_argument("--quiet", action="store_true")
    ref.set_defaults(func=_build_reference)


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser(prog="sensor_captures")
    add_commands(parser.add_subparsers(dest="command", required=True))
    ns = parser.parse_args()
    sys.exit(ns.func(ns))
