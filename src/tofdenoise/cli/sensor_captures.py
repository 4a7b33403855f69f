"""`tofdenoise-sensor simulate-captures` and `tofdenoise-sensor build-reference` (capture sets).

Format of a capture set: see `tofdenoise.data_modules.real_captures` and docs/data.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _simulate(args: argparse.Namespace) -> int:
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set

    def progress(index: int, total: int, info: dict) -> None:
        if not args.quiet:
            print(f"scene {index + 1}/{total}: reference exposure {info['reference_exposure']:.3g}, "
                  f"input valid {info['input_valid_fraction']:.3f}, reference valid "
                  f"{info['reference_valid_fraction']:.3f}", flush=True)

    summary = simulate_capture_set(
        args.out, scenes=args.scenes, frames=args.frames, height=args.height, width=args.width, seed=args.seed,
        calib=args.sensor, hi_exposure=args.hi_exposure, write_taps=args.taps, force=args.force,
        min_count=args.min_count, progress=progress,
    )
    per_scene = summary.seconds / max(summary.scenes_written, 1)
    print(f"simulated capture set in {summary.out_dir}: {summary.scenes_written} scene(s) written, "
          f"{summary.scenes_skipped} already complete, {summary.seconds:.1f} s ({per_scene:.2f} s per scene)")
    return 0


def _build_reference(args: argparse.Namespace) -> int:
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
            import numpy as np

            print(f"{scene.name}: {'rebuilt' if ref.rebuilt else 'up to date'}; valid reference pixels "
                  f"{float(np.isfinite(ref.depth_mm).mean()):.3f} (any frame {valid:.3f}); frames per pixel "
                  f"max {int(ref.count.max())}")
    print(f"{len(scenes)} scene(s): {rebuilt} reference(s) rebuilt, {len(scenes) - rebuilt} up to date")
    return 0


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
    sim.add_argument("--hi-exposure", type=float, default=4.0,
                     help="requested reference exposure (lowered per scene to stay below the full well)")
    sim.add_argument("--min-count", type=int, default=None,
                     help="valid frames a reference pixel needs (default: half of the frames)")
    sim.add_argument("--taps", action="store_true", help="also write raw tap stacks (.npy)")
    sim.add_argument("--force", action="store_true", help="rewrite scenes that are already complete")
    sim.add_argument("--quiet", action="store_true")
    sim.set_defaults(func=_simulate)

    ref = subparsers.add_parser(
        "build-reference",
        help="build the multi-frame reference depth of every scene in a capture set",
        description="Per-pixel mean over the valid, unsaturated high-exposure frames (hiexp/), with a per-pixel "
                    "count; pixels with fewer than --min-count frames are invalid (NaN). Written next to each "
                    "scene (reference_depth_mm.npy, reference_count.npy); skipped when up to date.",
    )
    ref.add_argument("scenes_dir", help="capture set folder (or one scene folder)")
    ref.add_argument("--min-count", type=int, default=None,
                     help="valid frames a pixel needs (default: half of the scene's frames)")
    ref.add_argument("--force", action="store_true", help="rebuild even when up to date")
    ref.add_argument("--quiet", action="store_true")
    ref.set_defaults(func=_build_reference)


if __name__ == "__main__":  # pragma: no cover
    parser = argparse.ArgumentParser(prog="sensor_captures")
    add_commands(parser.add_subparsers(dest="command", required=True))
    ns = parser.parse_args()
    sys.exit(ns.func(ns))
