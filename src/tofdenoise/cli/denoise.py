"""``tofdenoise denoise``: denoise a camera's own depth frames with a trained checkpoint.

    tofdenoise denoise (--ckpt best.ckpt | --onnx model.onnx) INPUT [INPUT ...] --out DIR
                       [--amplitude DIR_OR_PATTERN] [--sensor FILE]
                       [--depth-scale-mm S] [--fill-holes] [--npy] [--previews] [--device auto|cpu|cuda]
                       [--depth-m] [--ply --intrinsics FILE] [--depth-stream NAME] [--amplitude-stream NAME]

INPUT: depth frames or folders of them (searched recursively): 16-bit PNG/TIFF in mm (0 = invalid), ``.npy``
float mm (NaN/0/negative = invalid) or ``.exr``; or recordings (``tofdenoise.inference.recordings``): Azure Kinect
``.mkv``, ROS 1 ``.bag``, ROS 2 bag folders, whose frames go to ``OUT/<recording>/frame_NNNNNN.*`` with
``OUT/<recording>/frames.csv`` (each frame written and its timestamp; a recording is checked whole before its first
frame is written, and every depth message is one frame). A recording's units are its encoding's: with a recording
among the inputs ``--depth-scale-mm`` is refused. Outputs mirror the input sub-folders under ``--out``
(``tofdenoise.inference.outputs``). Frames are processed one at a time (memory bounded by one frame; a frame whose
activations do not fit the memory budget runs tile by tile, ``tofdenoise.training.tile_memory``, and the summary says
which frames did). A frame that fails (unreadable, 8-bit/colour, amplitude missing, ambiguous or of another shape,
depths implausible in millimetres without ``--depth-scale-mm`` ...) is reported and the others go on; the exit
status is 1 when any frame failed, 2 for a bad command line, checkpoint or calibration, or an output that would
replace an input or be written by two inputs (``tofdenoise.output_guard``: checked for every frame before anything
is written), 0 otherwise. The summary names, per recording, the streams and intrinsics used. See docs/denoise.md.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tofdenoise.output_guard import OutputPathError, refuse_overwrite

__all__ = ["build_parser", "main", "missing_file", "run", "timing_text"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tofdenoise denoise",
        description="Denoise iToF depth frames (16-bit PNG mm, .npy, .exr) or recordings (Azure Kinect .mkv, ROS 1 "
        ".bag, ROS 2 bag folders) with a trained tofdenoise checkpoint; invalid pixels stay invalid unless "
        "--fill-holes.",
    )
    p.add_argument(
        "inputs",
        nargs="+",
        metavar="INPUT",
        help="depth frames, recordings, or folders of them (recursive); a recording's frames go to "
        "OUT/<recording>/frame_NNNNNN.*",
    )
    model = p.add_mutually_exclusive_group(required=True)
    model.add_argument("--ckpt", type=Path, help="DepthRestorer checkpoint (.ckpt)")
    model.add_argument(
        "--onnx",
        type=Path,
        help="a restore graph of tofdenoise export, run by onnxruntime (no torch weights loaded; whole frames, "
        "--fp32/--tile do not apply; --device picks the execution provider: CUDA needs onnxruntime-gpu)",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (input sub-folders are mirrored)")
    p.add_argument(
        "--amplitude",
        default=None,
        metavar="DIR_OR_PATTERN",
        help="amplitude frames paired by stem: a folder, a template with {stem} (amp/{stem}_amp.png) or "
        "{stem:OLD=NEW}, the stem with OLD replaced by NEW (ADI ADTF3175D: 'adi/{stem:depth=ab}.npy' pairs "
        "frame_mode2_depth_000123.npy with frame_mode2_ab_000123.npy), or a glob (amp/*.png); required by "
        "checkpoints that use the signal channel",
    )
    p.add_argument(
        "--sensor",
        default=None,
        metavar="FILE",
        help="sensor calibration (YAML/JSON, or a preset name): with --amplitude, write the per-pixel "
        "sigma_D map of the input (<stem>_sigma_mm.npy, and in the preview)",
    )
    p.add_argument(
        "--depth-scale-mm",
        type=float,
        default=None,
        help="millimetres per stored depth unit of frame files (default 1, and then a frame whose median valid depth "
        "lies below 300 mm, the training scenes' nearest depth, or beyond the sensor's unambiguous range (--sensor, "
        "else the default camera: 2998 mm) is refused as not in mm; e.g. 0.25, 0.1, 10 for cm, 1000 for metres); "
        "refused with recordings, whose units are their encoding's",
    )
    p.add_argument("--fill-holes", action="store_true", help="give invalid input pixels a restored depth too")
    p.add_argument("--npy", action="store_true", help="also write the restored depth as float32 .npy (mm)")
    p.add_argument(
        "--previews",
        action="store_true",
        help="write <stem>_preview.png: input | restored | |difference| (| sigma_D) with colour bars",
    )
    p.add_argument(
        "--depth-m",
        action="store_true",
        help="also write <stem>_depth_m.tiff: restored depth as 32-bit float metres, NaN = invalid (ROS REP 118)",
    )
    p.add_argument(
        "--ply",
        action="store_true",
        help="also write <stem>.ply: the restored valid pixels as a point cloud [m] (needs the intrinsics: "
        "--intrinsics, a Kinect recording's calibration or the CameraInfo of a bag's depth topic, "
        "<ns>/camera_info beside <ns>/image_raw)",
    )
    p.add_argument(
        "--intrinsics",
        type=Path,
        default=None,
        metavar="FILE",
        help="camera intrinsics: YAML/JSON with fx, fy, cx, cy, width, height; a ROS camera_info YAML; an OpenCV "
        "FileStorage YAML/XML (camera_matrix, image_width, image_height); or an Azure Kinect calibration.json (the "
        "depth mode of the frame's size); overrides those of a recording",
    )
    p.add_argument(
        "--depth-stream",
        default=None,
        metavar="NAME",
        help="recordings: the depth topic of a bag or track of a .mkv (default: the Kinect's DEPTH track, or "
        "the first image topic named like depth)",
    )
    p.add_argument(
        "--amplitude-stream",
        default=None,
        metavar="NAME",
        help="recordings: the amplitude / IR topic or track (default: the Kinect's IR track, or the first image "
        "topic named like ir / amplitude / intensity)",
    )
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="default: CUDA when available")
    p.add_argument("--fp32", action="store_true", help="no bf16 autocast on CUDA")
    p.add_argument(
        "--tile",
        type=int,
        default=None,
        help="force tiles of this side in pixels (default: a frame runs whole when the network's activations fit "
        "the memory budget of the device, else in tiles of the checkpoint's tiling.predict_tile_px; the summary "
        "says which)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


#: why a frame file fails under --ply without --intrinsics (a frame file carries no intrinsics of its own)
NO_FRAME_INTRINSICS = (
    "--ply needs the camera intrinsics and a frame file carries none: give --intrinsics FILE (the other inputs go on)"
)


def onnx_device(name: str):
    """The device the summary names for an onnxruntime run (that of its execution provider)."""
    import torch

    return torch.device(name)


def _fail(message: str) -> int:
    print(f"tofdenoise denoise: error: {message}", file=sys.stderr)
    return 2


def missing_file(args: argparse.Namespace) -> str:
    """The first input, intrinsics file, checkpoint or ONNX model named on the command line that does not exist, as
    the error the loader would give ("" when all exist): checked before torch, the model or any frame reader is
    imported, so a mistyped path is refused in a fraction of a second."""
    for name in args.inputs:
        if not Path(name).exists():
            return f"input not found: {name} (expected a depth frame or a folder of them)"
    if args.intrinsics is not None and not Path(args.intrinsics).expanduser().is_file():
        return f"intrinsics file not found: {Path(args.intrinsics).expanduser()}"
    if args.ckpt is not None and not Path(args.ckpt).expanduser().is_file():
        return f"checkpoint file not found: {Path(args.ckpt).expanduser()}"
    if args.onnx is not None and not Path(args.onnx).expanduser().is_file():
        return f"ONNX model {Path(args.onnx).expanduser()} does not exist"
    return ""


def run(args: argparse.Namespace) -> int:
    """Run the command on parsed arguments; returns the exit status. The arguments and the files they name are
    checked before the model and the frame readers are imported (:func:`missing_file`)."""
    if args.depth_scale_mm is not None and not args.depth_scale_mm > 0:
        return _fail(f"--depth-scale-mm must be > 0, got {args.depth_scale_mm}")
    if args.tile is not None and args.tile < 32:
        return _fail(f"--tile must be >= 32 pixels, got {args.tile}")
    missing = missing_file(args)
    if missing:
        return _fail(missing)
    from tqdm.auto import tqdm

    from tofdenoise.inference.camera import IntrinsicsError, load_intrinsics
    from tofdenoise.inference.denoise import CheckpointError, load_restorer, resolve_device
    from tofdenoise.inference.frames import (
        AmplitudeSource,
        FrameError,
        drop_amplitude_files,
        find_frames,
        plausible_depth_range_mm,
    )
    from tofdenoise.inference.outputs import OutputOptions
    from tofdenoise.inference.recordings import find_recordings

    try:
        device = resolve_device("cpu" if args.onnx is not None else args.device)
        amplitude = AmplitudeSource(args.amplitude) if args.amplitude is not None else None
        # an amplitude folder inside an input folder holds no depth frames
        skip = [args.out] + ([amplitude.folder] if amplitude and amplitude.folder else [])
        frames = drop_amplitude_files(find_frames(args.inputs, exclude=skip), amplitude)
        recordings = find_recordings(args.inputs, exclude=skip)
        intrinsics = load_intrinsics(args.intrinsics) if args.intrinsics is not None else None
        calib = None
        if args.sensor is not None:
            from tofdenoise.physics.calibration import resolve_calibration

            calib = resolve_calibration(args.sensor)
    except (FrameError, IntrinsicsError, ValueError, OSError) as exc:
        return _fail(str(exc))
    if args.depth_scale_mm is not None and recordings:
        more = f" and {len(recordings) - 1} more" if len(recordings) > 1 else ""
        return _fail(
            f"--depth-scale-mm {args.depth_scale_mm:g} does not apply to recordings ({recordings[0].path}{more}): a "
            "recording's depth units are its encoding's (16UC1 / mono16 and the Kinect's DEPTH track: mm; 32FC1: "
            "metres; ROS REP 118); run the recordings without --depth-scale-mm, apart from the frame files that "
            "need it"
        )
    if args.sensor is not None and args.amplitude is None and frames:
        return _fail("--sensor needs --amplitude: the sigma_D map is computed from the input's amplitude")
    if args.ply and intrinsics is None and frames and not recordings:  # no input could give a point cloud
        return _fail(
            "--ply needs the camera intrinsics of the depth frames: give --intrinsics FILE (fx, fy, cx, cy, "
            "width, height)"
        )
    try:
        if args.onnx is not None:
            from tofdenoise.inference.onnx_runner import OnnxRestorer

            model = OnnxRestorer(args.onnx, device=args.device)
            device, signal = onnx_device(model.device), model.use_signal_channel
        else:
            model = load_restorer(args.ckpt, device)
            signal = model.conditioning.use_signal_channel
    except (CheckpointError, ValueError, OSError) as exc:
        return _fail(str(exc))
    overlap = getattr(getattr(model, "tiling", None), "overlap_px", None)
    if args.tile is not None and overlap is not None:
        from tofdenoise.models.tiling import min_tile_px, model_multiple

        multiple = model_multiple(getattr(model, "eval_net", None))
        if args.tile < min_tile_px(overlap, multiple):
            return _fail(
                f"--tile must be at least {min_tile_px(overlap, multiple)} px for this checkpoint (its tile overlap "
                f"tiling.overlap_px = {overlap} plus the backbone's padding multiple of {multiple} px, tiles starting "
                f"on that multiple), got {args.tile}"
            )
    if signal and amplitude is None and frames:
        return _fail(
            f"{'ONNX model' if args.onnx is not None else 'checkpoint'} {args.onnx or args.ckpt} uses the "
            "amplitude (signal) channel (use_signal_channel=true): give the frames' amplitude with "
            "--amplitude DIR_OR_PATTERN"
        )
    if not frames and not recordings:
        try:  # an input folder inside --out: its frames were skipped as outputs ("no depth frame found" misled)
            refuse_overwrite([], args.inputs, "--out", output_folders=[args.out])
        except OutputPathError as exc:
            return _fail(str(exc))
        return _fail(f"no depth frame or recording found in {', '.join(map(str, args.inputs))}")

    options = OutputOptions(npy=args.npy, previews=args.previews, depth_m=args.depth_m, ply=args.ply)
    try:
        _refuse_replacing_inputs(args, frames, recordings, amplitude, options, calib is not None)
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
        intrinsics=intrinsics,
        signal=signal,
        depth_range_mm=plausible_depth_range_mm(calib),
        training_range_mm=model.training_depth_range_mm,
    )
    tally = _Tally()
    interrupted = False
    try:
        for frame in tqdm(frames, desc="denoise", unit="frame", disable=args.quiet or None, file=sys.stderr):
            _denoise_one(frame, job, tally)
        for recording in recordings:
            _denoise_recording(recording, job, tally)
    except KeyboardInterrupt:  # Ctrl-C: every frame written so far is complete (atomic writes); say what was done
        interrupted = True
    seen = tally.done + len(tally.skipped) + len(tally.failed)
    total = f"{len(frames)} frame(s)" + (f" and {len(recordings)} recording(s)" if recordings else "")
    ended = f"interrupted (Ctrl-C) after {seen} of {total}: " if interrupted else ""
    print(
        f"tofdenoise denoise: {ended}{tally.done} frame(s) done, {len(tally.skipped)} skipped, "
        f"{len(tally.failed)} failed; {timing_text(tally.seconds)} on {device.type} -> {args.out}",
        file=sys.stderr,
    )
    for line in tiling_lines(args, tally) + training_depth_lines(job, tally) + tally.notes:
        print(f"  {line}", file=sys.stderr)
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
    intrinsics: Any = None
    signal: bool = False
    #: (nearest, farthest) median depth [mm] a frame without --depth-scale-mm may have (frames.check_depth_units_mm)
    depth_range_mm: tuple[float, float] | None = None
    #: (nearest, farthest) depth [mm] the network was trained on (training/depth_range.py); None: not recorded
    training_range_mm: tuple[float, float] | None = None


@dataclass
class _Tally:
    """What happened to the frames so far (the summary)."""

    done: int = 0
    skipped: list[tuple[str, str]] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    claimed: dict[Path, Path] = field(default_factory=dict)
    #: frames done whose valid depths lie mostly outside the training depths: (frame, note)
    outside: list[tuple[str, str]] = field(default_factory=list)
    #: (shape, training.tile_memory.TilePlan) of every frame restored by a checkpoint
    plans: list[tuple[tuple[int, ...], Any]] = field(default_factory=list)
    #: summary lines of the recordings: the streams and intrinsics used, shared timestamps
    notes: list[str] = field(default_factory=list)


def _write_failure(exc: OSError, out: Path) -> str:
    """An output write that failed, with the file (or the folder) and the cause, said once; the frame's outputs are
    written all or nothing (``outputs.write_frame_outputs``), so none of them was kept."""
    from tofdenoise.atomic import WriteError

    if isinstance(exc, WriteError):  # names the file and the cause, "(disk full?)" included
        return f"{exc}; none of the frame's outputs was written"
    full = exc.errno in (errno.ENOSPC, errno.EFBIG) or "requested and" in str(exc)
    return f"could not write its outputs under {out}: {exc}" + (" (disk full?)" if full else "")


def _denoise_one(frame: Any, job: _Job, tally: _Tally) -> None:
    """Restore one frame file and write its outputs, or record why it was skipped or failed."""
    from tofdenoise.inference.frames import FrameError, check_depth_units_mm, load_frame

    if not _claim(frame.rel_stem.as_posix(), frame.path, job, tally):
        return
    if job.options.ply and job.intrinsics is None:  # a recording of the same command may carry its own
        tally.failed.append((str(frame.path), NO_FRAME_INTRINSICS))
        return
    started = time.perf_counter()
    try:
        data = load_frame(frame, job.depth_scale_mm, job.amplitude)
        if data.valid.any() and job.args.depth_scale_mm is None:
            check_depth_units_mm(data, frame.path, job.depth_range_mm)
    except (FrameError, ValueError, OSError) as exc:
        tally.failed.append((str(frame.path), str(exc)))
        return
    _restore_and_write(data, str(frame.path), job.intrinsics, job, tally, started)


def _claim(name: str, source: Any, job: _Job, tally: _Tally) -> bool:
    """False (and the frame skipped) when an earlier input already maps to the same output name."""
    from tofdenoise.inference.outputs import output_paths

    target = output_paths(job.args.out, name)["png"].resolve()
    if target in tally.claimed:
        tally.skipped.append((str(source), f"same output name as {tally.claimed[target]}"))
        return False
    tally.claimed[target] = source
    return True


def _restore_and_write(
    data: Any, label: str, intrinsics: Any, job: _Job, tally: _Tally, started: float, on_written: Any = None
) -> None:
    """Restore a frame read into memory (``frames.Frame``) and write its outputs, or record why not;
    ``on_written()`` is called once they are written, counted with them (a Ctrl-C comes after both)."""
    from tofdenoise.atomic import sigint_deferred
    from tofdenoise.inference.camera import IntrinsicsError, resolve_intrinsics
    from tofdenoise.inference.denoise import frame_tile_plan, restore_frame
    from tofdenoise.inference.frames import FrameError, outside_training_depths
    from tofdenoise.inference.outputs import frame_sigma, write_frame_outputs

    args = job.args
    if not data.valid.any():
        tally.skipped.append((label, "no valid pixel"))
        return
    try:
        if job.options.ply:
            intrinsics = resolve_intrinsics(intrinsics, data.depth_mm.shape, label)
        if args.onnx is not None:  # onnxruntime: whole frame, the graph's own precision
            restored = job.model.restore_frame(data.depth_mm, data.valid, data.amplitude, fill_holes=args.fill_holes)
        else:
            plan = frame_tile_plan(job.model, data.depth_mm.shape, args.tile, job.precision)
            restored = restore_frame(
                job.model,
                data.depth_mm,
                data.valid,
                data.amplitude,
                fill_holes=args.fill_holes,
                tile=plan,
                precision=job.precision,
            )
            tally.plans.append((tuple(data.depth_mm.shape), plan))
    except (FrameError, IntrinsicsError, ValueError, OSError, RuntimeError) as exc:
        tally.failed.append((label, str(exc)))
        return
    sigma_mm = frame_sigma(data, job.calib)
    # a Ctrl-C while the outputs are written lands after the frame is counted: the summary counts what is on disk
    with sigint_deferred():
        try:
            write_frame_outputs(
                args.out,
                data.name,
                data.depth_mm,
                data.valid,
                restored,
                job.options,
                sigma_mm=sigma_mm,
                intrinsics=intrinsics,
            )
        except OSError as exc:
            tally.failed.append((label, _write_failure(exc, Path(args.out))))
            return
        tally.seconds.append(time.perf_counter() - started)
        tally.done += 1
        if on_written is not None:
            on_written()
    note = outside_training_depths(data, job.training_range_mm)
    if note is not None:
        tally.outside.append((label, note))


def _denoise_recording(recording: Any, job: _Job, tally: _Tally) -> None:
    """Check a whole recording (``Recording.scan``), then restore and write its frames one by one, every depth frame
    one frame, and their table (``frames.csv``); a recording that cannot be read is one failure and writes nothing.
    The amplitude stream is read only when the model or ``--sensor`` uses it, and the intrinsics only for ``--ply``
    without ``--intrinsics``."""
    from tqdm.auto import tqdm

    from tofdenoise.inference.frames import FrameError
    from tofdenoise.inference.outputs import RECORDING_TABLE, write_recording_table
    from tofdenoise.inference.recordings import RecordingError, open_recording

    args = job.args
    path = recording.path
    needs_amplitude = job.signal or job.calib is not None
    try:
        rec = open_recording(path, args.depth_stream, args.amplitude_stream, use_amplitude=needs_amplitude)
        if needs_amplitude and rec.amplitude_name is None:
            raise RecordingError(
                f"recording {path} has no amplitude / IR stream ({_amplitude_user(job)} needs it); it has: "
                f"{', '.join(rec.stream_names) or 'none'}; name the amplitude stream with --amplitude-stream"
            )
        count = rec.scan()
        intrinsics = None
        if job.options.ply:
            intrinsics = job.intrinsics if job.intrinsics is not None else rec.intrinsics
            if intrinsics is None:
                raise RecordingError(
                    f"recording {path} has no camera intrinsics: {rec.intrinsics_absent()}; --ply needs "
                    "--intrinsics FILE"
                )
        if needs_amplitude and len(rec.no_amplitude) == count:
            first = min(rec.no_amplitude)
            raise RecordingError(
                f"recording {path}: none of its {count} depth frame(s) has a usable amplitude in "
                f"{rec.amplitude_name} ({_amplitude_user(job)} needs it): frame {first}: {rec.no_amplitude[first]}"
            )
    except RecordingError as exc:
        tally.failed.append((str(path), str(exc)))
        return
    folder = recording.rel_stem.as_posix()
    rows: list[tuple[str, int, str, str]] = []
    seen: set[int] = set()
    frames = rec.frames()
    bar = tqdm(total=count, desc=recording.rel.as_posix(), unit="frame", disable=args.quiet or None, file=sys.stderr)
    try:
        with bar:
            while True:
                started = time.perf_counter()
                try:
                    item = next(frames, None)
                except (ValueError, OSError) as exc:  # RecordingError, or a read error past the scan
                    tally.failed.append((str(path), f"{exc} ({_unread(count, seen)})"))
                    return
                if item is None:
                    break
                bar.update(1)
                seen.add(item.index)
                name = f"{folder}/frame_{item.index:06d}"
                label = f"{path} frame {item.index}"
                if not _claim(name, label, job, tally):
                    continue
                if needs_amplitude and item.amplitude is None:
                    why = item.no_amplitude or f"no amplitude frame of the same timestamp in {rec.amplitude_name}"
                    tally.failed.append((label, f"{why} ({_amplitude_user(job)} needs it)"))
                    continue
                try:
                    data = item.frame(name, amplitude=needs_amplitude)
                except FrameError as exc:  # a depth beyond 65535 mm, an amplitude without a finite value ...
                    tally.failed.append((label, str(exc)))
                    continue
                row = (f"frame_{item.index:06d}", item.stamp_ns, rec.depth_name, item.frame_id)
                _restore_and_write(data, label, intrinsics, job, tally, started, lambda row=row: rows.append(row))
        if len(seen) != count:
            unread = f"; {_unread(count, seen)}" if len(seen) < count else ""
            tally.failed.append((str(path), f"the check counted {count} frame(s), reading gave {len(seen)}{unread}"))
    finally:  # also on Ctrl-C: the table lists the frames written so far
        table = Path(args.out) / folder / RECORDING_TABLE
        if rows:
            try:
                write_recording_table(table.parent, rows)
            except OSError as exc:  # the frames are written; the table of their timestamps is not
                tally.failed.append((str(path), f"its table of frames and timestamps was not written: {exc}"))
        tally.notes.append(_recording_line(rec, job, count, rows, table, intrinsics, needs_amplitude))
        tally.notes += [f"warning: {note}" for note in rec.notes]


def _amplitude_user(job: _Job) -> str:
    """What needs a recording's amplitude, for messages."""
    return "the model's signal channel" if job.signal else "--sensor (sigma_D)"


def _unread(count: int, seen: set[int]) -> str:
    """Which of a recording's ``count`` frames were not read, for the line of a read that failed past the check."""
    missing = [i for i in range(count) if i not in seen]
    listed = ", ".join(map(str, missing[:5])) + (" ..." if len(missing) > 5 else "")
    return f"{len(missing)} of its {count} frame(s) not read and not written: {listed}"


def _recording_line(rec: Any, job: _Job, count: int, rows: list, table: Path, intrinsics: Any, amp: bool) -> str:
    """The summary's line on a recording: the streams and intrinsics used, the frames written and their table."""
    if amp:
        missing = f", {len(rec.no_amplitude)} frame(s) without one" if rec.no_amplitude else ""
        amplitude = f"amplitude {rec.amplitude_name}{missing}"
    else:
        amplitude = "amplitude not read (neither the model nor --sensor uses it)"
    line = f"recording {rec.path}: depth {rec.depth_name}, {amplitude}"
    if job.options.ply and intrinsics is not None:
        if job.intrinsics is not None:
            line += f", intrinsics from --intrinsics {job.args.intrinsics}"
        else:
            line += (
                f", intrinsics from {intrinsics.source}: fx {intrinsics.fx:g}, fy {intrinsics.fy:g}, cx "
                f"{intrinsics.cx:g}, cy {intrinsics.cy:g}, {intrinsics.width} x {intrinsics.height} px"
            )
    written = f"{len(rows)} of {count} frame(s) written"
    return f"{line}; {written}" + (f", with their timestamps in {table}" if rows else "")


def _refuse_replacing_inputs(
    args: argparse.Namespace, frames, recordings, amplitude, options, with_sigma: bool
) -> None:
    """Every output of every frame against every file the command reads (frames, their amplitude, recordings,
    checkpoint, calibration, intrinsics), before the first write: ``OutputPathError`` names the output and the
    input. A recording's frames go to a folder of their own, which must hold no input."""
    from tofdenoise.inference.frames import FrameError
    from tofdenoise.inference.outputs import output_paths, wanted_outputs

    inputs: list[Path] = (
        [frame.path for frame in frames] + [r.path for r in recordings] + [Path(args.onnx or args.ckpt)]
    )
    if args.sensor is not None and Path(args.sensor).exists():
        inputs.append(Path(args.sensor))
    if args.intrinsics is not None:
        inputs.append(Path(args.intrinsics))
    if amplitude is not None:
        for frame in frames:
            try:
                inputs.append(amplitude.find(frame))
            except FrameError:  # reported for that frame when it is processed
                pass
    _refuse_shared_outputs(args.out, frames, recordings)
    wanted = wanted_outputs(options, with_sigma)
    outputs = [
        path
        for frame in frames
        for key, path in output_paths(args.out, frame.rel_stem.as_posix()).items()
        if key in wanted
    ]
    out = Path(args.out)
    if out.exists() and not out.is_dir():  # an input file, the checkpoint: "File exists" once a frame was computed
        refuse_overwrite([out], [*inputs, *args.inputs], "--out")
        raise OutputPathError(f"--out {out} is a file; give a folder for the outputs")
    folders = [out] + [out / r.rel_stem for r in recordings]
    refuse_overwrite(outputs, inputs, "--out", output_folders=folders)


def _refuse_shared_outputs(out: Path, frames, recordings) -> None:
    """``OutputPathError`` naming both inputs when two frames (or two recordings) would write to one output name:
    frames of one name in two input folders (two cameras numbering their frames from 0), or ``a.png`` beside
    ``a.npy``. Restoring one and skipping the other ended with exit status 0 and half the frames. So does a frame
    file whose outputs lie in a recording's output folder (``take1/frame_000000.png`` beside ``take1.bag``),
    or a recording's folder inside another's: their outputs would mix in one folder."""
    from tofdenoise.inference.outputs import output_paths

    folders = [(Path(os.path.realpath(Path(out) / r.rel_stem)), r.path) for r in recordings]
    for frame in frames:
        target = Path(os.path.realpath(output_paths(out, frame.rel_stem.as_posix())["png"]))
        for folder, source in folders:
            if folder in target.parents:
                raise OutputPathError(
                    f"{frame.path} and the recording {source} would both write into {folder} (the frame file's "
                    f"output {target.name} among the recording's frames): run them with separate --out folders, or "
                    "rename one"
                )
    for folder, source in folders:
        for other, other_source in folders:
            if other in folder.parents:
                raise OutputPathError(
                    f"the recordings {source} and {other_source} would both write into {other} (the output folder "
                    f"of one inside the other's): run them with separate --out folders, or rename one"
                )

    for kind, items, target in (
        ("frames", frames, lambda f: output_paths(out, f.rel_stem.as_posix())["png"]),
        ("recordings", recordings, lambda r: Path(out) / r.rel_stem),
    ):
        taken: dict[Path, Path] = {}
        for item in items:
            path = Path(os.path.realpath(target(item)))
            if path in taken:
                raise OutputPathError(
                    f"{item.path} and {taken[path]} would both be written to {path} (two {kind} of one name under "
                    "--out): run them with separate --out folders, or rename one"
                )
            taken[path] = item.path


def tiling_lines(args: argparse.Namespace, tally: _Tally) -> list[str]:
    """The summary's line on tiling: whole frames, or which frames ran in tiles of which side and why
    (``training.tile_memory.tile_plan``)."""
    from tofdenoise.training.tile_memory import gib

    if args.onnx is not None:
        return ["tiling: none, whole frames (an ONNX graph runs whole frames)"] if tally.done else []
    if not tally.plans:
        return []

    def size(shape: tuple[int, ...]) -> str:
        return f"{shape[-1]} x {shape[-2]}"

    whole = [(shape, plan) for shape, plan in tally.plans if not plan.tiled]
    tiled = [(shape, plan) for shape, plan in tally.plans if plan.tiled]
    parts = []
    if tiled:
        sides = sorted({plan.tile for _, plan in tiled})
        shape, plan = max(tiled, key=lambda item: item[0][-1] * item[0][-2])
        if plan.forced:
            why = f"--tile {args.tile}"
        else:
            why = f"the largest, {size(shape)}, needs about {gib(plan.need_bytes)}, over the memory budget of "
            why += f"{gib(plan.budget_bytes)}"
        parts.append(f"{len(tiled)} frame(s) in tiles of {'/'.join(map(str, sides))} px ({why})")
    if whole:
        shape, plan = max(whole, key=lambda item: item[0][-1] * item[0][-2])
        if plan.forced:
            why = f"no side beyond --tile {args.tile}"
        elif plan.need_bytes is None:
            why = "the checkpoint never tiles"
        elif plan.budget_bytes is None:
            why = f"the largest, {size(shape)}, needs about {gib(plan.need_bytes)}; memory budget unknown"
        else:
            why = (
                f"the largest, {size(shape)}, needs about {gib(plan.need_bytes)} of the {gib(plan.budget_bytes)} budget"
            )
        parts.append(f"{len(whole)} whole frame(s) ({why})")
    return [f"tiling: {'; '.join(parts)}"]


def training_depth_lines(job: _Job, tally: _Tally) -> list[str]:
    """The summary's lines on the depths the network was trained on: the range and each frame done that lies
    mostly outside it, or that the checkpoint does not record it (nothing for a classical filter, never trained)."""
    if not tally.done or not getattr(job.model, "trainable", True):
        return []
    if job.training_range_mm is None:
        return [
            "the checkpoint does not record the depths it was trained on (written before they were kept): the frames "
            "were not checked against them"
        ]
    low, high = job.training_range_mm
    head = f"trained on depths {low:.0f}-{high:.0f} mm"
    if not tally.outside:
        return [f"{head}: no frame lies mostly outside them"]
    return [f"{head}: {len(tally.outside)} frame(s) lie mostly outside them"] + [
        f"outside the training depths {label}: {note}" for label, note in tally.outside
    ]


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
    """Console script ``tofdenoise denoise``."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
