"""``tofdenoise-denoise``: denoise a camera's own depth frames with a trained checkpoint.

    tofdenoise-denoise (--ckpt best.ckpt | --onnx model.onnx) INPUT [INPUT ...] --out DIR
                       [--amplitude DIR_OR_PATTERN] [--calib FILE]
                       [--depth-scale-mm S] [--fill-holes] [--npy] [--previews] [--device auto|cpu|cuda]

INPUT: depth frames or folders of them (searched recursively): 16-bit PNG/TIFF in mm (0 = invalid), ``.npy``
float mm (NaN/0/negative = invalid) or ``.exr``. Outputs mirror the input sub-folders under ``--out``
(``tofdenoise.inference.outputs``). Frames are processed one at a time (memory bounded by one frame; large frames
run tile by tile). A frame that fails (unreadable, 8-bit/colour, amplitude missing or of another shape, depths
implausible in millimetres without ``--depth-scale-mm`` ...) is reported and the others go on; the exit status is
1 when any frame failed, 2 for a bad command line, checkpoint or calibration, or an output that would replace an
input (``tofdenoise.output_guard``: checked for every frame before anything is written), 0 otherwise. See
docs/denoise.md.
"""

from __future__ import annotations

import argparse
import errno
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tofdenoise.output_guard import OutputPathError, refuse_overwrite

__all__ = ["build_parser", "main", "run", "timing_text"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tofdenoise-denoise",
        description="Denoise iToF depth frames (16-bit PNG mm, .npy, .exr) with a trained tofdenoise checkpoint; "
        "invalid pixels stay invalid unless --fill-holes.",
    )
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="depth frames or folders of them (recursive)")
    model = p.add_mutually_exclusive_group(required=True)
    model.add_argument("--ckpt", type=Path, help="DepthRestorer checkpoint (.ckpt)")
    model.add_argument(
        "--onnx",
        type=Path,
        help="a restore graph of tofdenoise-export, run by onnxruntime on the CPU (no torch weights loaded; "
        "whole frames, --device/--fp32/--tile do not apply)",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (input sub-folders are mirrored)")
    p.add_argument(
        "--amplitude",
        default=None,
        metavar="DIR_OR_PATTERN",
        help="amplitude frames paired by stem: a folder, a template with {stem} (amp/{stem}_amp.png) or a "
        "glob (amp/*.png); required by checkpoints that use the signal channel",
    )
    p.add_argument(
        "--calib",
        default=None,
        metavar="FILE",
        help="sensor calibration (YAML/JSON, or a preset name): with --amplitude, write the per-pixel "
        "sigma_D map of the input (<stem>_sigma_mm.npy, and in the preview)",
    )
    p.add_argument(
        "--depth-scale-mm",
        type=float,
        default=None,
        help="millimetres per stored depth unit (default 1, and then a frame whose median valid depth is below "
        "20 is refused as not in mm; e.g. 0.25, or 1000 for metres)",
    )
    p.add_argument("--fill-holes", action="store_true", help="give invalid input pixels a restored depth too")
    p.add_argument("--npy", action="store_true", help="also write the restored depth as float32 .npy (mm)")
    p.add_argument(
        "--previews",
        action="store_true",
        help="write <stem>_preview.png: input | restored | |difference| (| sigma_D) with colour bars",
    )
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="default: CUDA when available")
    p.add_argument("--fp32", action="store_true", help="no bf16 autocast on CUDA")
    p.add_argument(
        "--tile",
        type=int,
        default=None,
        help="tile side in pixels for large frames (default: the checkpoint's predict_tile_size)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def torch_cpu():
    """The device the summary names for an onnxruntime run (its CPU execution provider)."""
    import torch

    return torch.device("cpu")


def _fail(message: str) -> int:
    print(f"tofdenoise-denoise: error: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    """Run the command on parsed arguments; returns the exit status."""
    from tqdm.auto import tqdm

    from tofdenoise.inference.denoise import CheckpointError, load_restorer, resolve_device
    from tofdenoise.inference.frames import AmplitudeSource, FrameError, find_frames
    from tofdenoise.inference.outputs import OutputOptions

    if args.depth_scale_mm is not None and not args.depth_scale_mm > 0:
        return _fail(f"--depth-scale-mm must be > 0, got {args.depth_scale_mm}")
    if args.tile is not None and args.tile < 32:
        return _fail(f"--tile must be >= 32 pixels, got {args.tile}")
    if args.calib is not None and args.amplitude is None:
        return _fail("--calib needs --amplitude: the sigma_D map is computed from the input's amplitude")
    try:
        device = resolve_device(args.device)
        amplitude = AmplitudeSource(args.amplitude) if args.amplitude is not None else None
        # an amplitude folder inside an input folder holds no depth frames
        frames = find_frames(
            args.inputs, exclude=[args.out] + ([amplitude.folder] if amplitude and amplitude.folder else [])
        )
        calib = None
        if args.calib is not None:
            from tofdenoise.physics.calibration import resolve_calibration

            calib = resolve_calibration(args.calib)
        if args.onnx is not None:
            from tofdenoise.inference.onnx_runner import OnnxRestorer

            model = OnnxRestorer(args.onnx)
            device, signal = torch_cpu(), model.use_signal_channel
        else:
            model = load_restorer(args.ckpt, device)
            signal = bool(model.hparams.use_signal_channel)
    except (FrameError, CheckpointError, ValueError, OSError) as exc:
        return _fail(str(exc))
    if signal and amplitude is None:
        return _fail(
            f"{'ONNX model' if args.onnx is not None else 'checkpoint'} {args.onnx or args.ckpt} uses the "
            "amplitude (signal) channel (use_signal_channel=true): give the frames' amplitude with "
            "--amplitude DIR_OR_PATTERN"
        )
    if not frames:
        try:  # an input folder inside --out: its frames were skipped as outputs ("no depth frame found" misled)
            refuse_overwrite([], args.inputs, "--out", output_folders=[args.out])
        except OutputPathError as exc:
            return _fail(str(exc))
        return _fail(f"no depth frame found in {', '.join(map(str, args.inputs))}")

    options = OutputOptions(npy=args.npy, previews=args.previews)
    try:
        _refuse_replacing_inputs(args, frames, amplitude, options, calib is not None)
    except OutputPathError as exc:
        return _fail(str(exc))
    job = _Job(
        args=args,
        model=model,
        amplitude=amplitude,
        calib=calib,
        options=options,
        depth_scale_mm=1.0 if args.depth_scale_mm is None else args.depth_scale_mm,
        precision="fp32" if args.fp32 else "bf16",
    )
    tally = _Tally()
    interrupted = False
    try:
        for frame in tqdm(frames, desc="denoise", unit="frame", disable=args.quiet or None, file=sys.stderr):
            _denoise_one(frame, job, tally)
    except KeyboardInterrupt:  # Ctrl-C: every frame written so far is complete (atomic writes); say what was done
        interrupted = True
    seen = tally.done + len(tally.skipped) + len(tally.failed)
    ended = f"interrupted (Ctrl-C) after {seen} of {len(frames)} frame(s): " if interrupted else ""
    print(
        f"tofdenoise-denoise: {ended}{tally.done} frame(s) done, {len(tally.skipped)} skipped, "
        f"{len(tally.failed)} failed; {timing_text(tally.seconds)} on {device.type} -> {args.out}",
        file=sys.stderr,
    )
    for path, reason in tally.skipped:
        print(f"  skipped {path}: {reason}", file=sys.stderr)
    for path, reason in tally.failed:
        print(f"  FAILED {path}: {reason}", file=sys.stderr)
    if interrupted:
        print("  the frames done are complete; run the same command again to do the rest", file=sys.stderr)
        return 130
    return 1 if tally.failed else 0


@dataclass
class _Job:
    """What every frame of one command shares."""

    args: argparse.Namespace
    model: Any
    amplitude: Any
    calib: Any
    options: Any
    depth_scale_mm: float
    precision: str


@dataclass
class _Tally:
    """What happened to the frames so far (the summary)."""

    done: int = 0
    skipped: list[tuple[str, str]] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    claimed: dict[Path, Path] = field(default_factory=dict)


def _write_failure(exc: OSError, out: Path) -> str:
    """An output write that failed, with the folder and the cause (numpy's short write names neither)."""
    full = exc.errno == errno.ENOSPC or "requested and" in str(exc)
    return f"could not write its outputs under {out}: {exc}" + (" (disk full?)" if full else "")


def _denoise_one(frame: Any, job: _Job, tally: _Tally) -> None:
    """Restore one frame and write its outputs, or record why it was skipped or failed."""
    from tofdenoise.inference.denoise import restore_frame
    from tofdenoise.inference.frames import FrameError, check_depth_units_mm, load_frame
    from tofdenoise.inference.outputs import frame_sigma, output_paths, write_frame_outputs

    args = job.args
    target = output_paths(args.out, frame.rel_stem.as_posix())["png"].resolve()
    if target in tally.claimed:
        tally.skipped.append((str(frame.path), f"same output name as {tally.claimed[target]}"))
        return
    tally.claimed[target] = frame.path
    started = time.perf_counter()
    try:
        data = load_frame(frame, job.depth_scale_mm, job.amplitude)
        if not data.valid.any():
            tally.skipped.append((str(frame.path), "no valid pixel"))
            return
        if args.depth_scale_mm is None:
            check_depth_units_mm(data, frame.path)
        if args.onnx is not None:  # onnxruntime: whole frame, the graph's own precision
            restored = job.model.restore_frame(data.depth_mm, data.valid, data.amplitude, fill_holes=args.fill_holes)
        else:
            restored = restore_frame(
                job.model,
                data.depth_mm,
                data.valid,
                data.amplitude,
                fill_holes=args.fill_holes,
                tile=args.tile,
                precision=job.precision,
            )
    except (FrameError, ValueError, OSError, RuntimeError) as exc:
        tally.failed.append((str(frame.path), str(exc)))
        return
    try:
        write_frame_outputs(
            args.out, data.name, data.depth_mm, data.valid, restored, job.options, sigma_mm=frame_sigma(data, job.calib)
        )
    except OSError as exc:
        tally.failed.append((str(frame.path), _write_failure(exc, Path(args.out))))
        return
    tally.seconds.append(time.perf_counter() - started)
    tally.done += 1


def _refuse_replacing_inputs(args: argparse.Namespace, frames, amplitude, options, with_sigma: bool) -> None:
    """Every output of every frame against every file the command reads (frames, their amplitude, checkpoint,
    calibration), before the first write: ``OutputPathError`` names the output and the input."""
    from tofdenoise.inference.frames import FrameError
    from tofdenoise.inference.outputs import output_paths

    inputs: list[Path] = [frame.path for frame in frames] + [Path(args.onnx or args.ckpt)]
    if args.calib is not None and Path(args.calib).exists():
        inputs.append(Path(args.calib))
    if amplitude is not None:
        for frame in frames:
            try:
                inputs.append(amplitude.find(frame))
            except FrameError:  # reported for that frame when it is processed
                pass
    wanted = {"png"} | ({"npy"} if options.npy else set()) | ({"sigma"} if with_sigma else set())
    wanted |= {"preview"} if options.previews else set()
    outputs = [
        path
        for frame in frames
        for key, path in output_paths(args.out, frame.rel_stem.as_posix()).items()
        if key in wanted
    ]
    refuse_overwrite(outputs, inputs, "--out")


def timing_text(seconds: Sequence[float]) -> str:
    """The summary's time per frame. The first frame pays one-time set-up (the first forward pass, a native
    kernel built on first use), so with more frames the mean is over the others and the first is given apart."""
    if not seconds:
        return "n/a s/frame"
    if len(seconds) == 1:
        return f"{seconds[0]:.3f} s/frame (one frame, one-time set-up included)"
    rest = seconds[1:]
    return f"{sum(rest) / len(rest):.3f} s/frame after the first ({seconds[0]:.3f} s, one-time set-up included)"


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``tofdenoise-denoise``."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
