"""Per-frame outputs of ``tofdenoise denoise`` (and of LightningCLI ``predict`` on frames), all written atomically.

For a frame named ``<rel>/<stem>`` (its path relative to the input folder, without suffix) under ``out``::

    out/<rel>/<stem>.png              restored depth, 16-bit PNG in mm (0 = invalid), ``io.write_depth_png16``
    out/<rel>/<stem>.npy              restored depth, float32 mm (0 = invalid)                   [npy]
    out/<rel>/<stem>_sigma_mm.npy     sigma_D of the input [mm], float32, NaN = invalid             [calib + amplitude]
    out/<rel>/<stem>_preview.png      input | restored | |restored - input| (| sigma_D) with colour bars  [previews]
    out/<rel>/<stem>_depth_m.tiff     restored depth, 32-bit float TIFF in metres, NaN = invalid (ROS REP 118) [depth_m]
    out/<rel>/<stem>.ply              restored valid pixels as points [m] in the camera's optical frame   [ply]

The metres map is the 32FC1 image of REP 118 (what a ROS depth topic in metres carries, NaN where no depth) as a
single-channel float32 TIFF: OpenCV (``cv2.imread(path, cv2.IMREAD_UNCHANGED)``), tifffile, ImageJ/Fiji and MATLAB
read it back bit for bit, NaN included, without any tofdenoise code. The point cloud is a binary little-endian PLY
(``float x, y, z`` per vertex, valid pixels only, row by row) from the camera intrinsics (``camera.points_m``),
which Open3D, PCL, MeshLab and CloudCompare read.

A recording's frames go to ``out/<recording>/frame_NNNNNN.*``, with ``out/<recording>/frames.csv``
(``write_recording_table``): one row per frame written, ``frame,stamp_ns,stream,frame_id`` (the output name, the
frame's timestamp in ns: a bag message's header stamp or the Kinect's device timestamp, the depth topic / track,
a bag message's ``header.frame_id``).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from tofdenoise import visualize as vis
from tofdenoise.atomic import (
    atomic_group,
    atomic_write,
    atomic_write_bytes,
    atomic_write_png,
    atomic_write_text,
    save_npy_atomic,
)
from tofdenoise.data_modules.io import write_depth_png16
from tofdenoise.inference.camera import Intrinsics, points_m

__all__ = [
    "OutputOptions",
    "RECORDING_TABLE",
    "RECORDING_TABLE_COLUMNS",
    "depth_mm_to_m",
    "output_paths",
    "preview_panel",
    "write_depth_m_tiff",
    "write_frame_outputs",
    "write_ply_points",
    "write_recording_table",
]

SIGMA_SUFFIX = "_sigma_mm.npy"
PREVIEW_SUFFIX = "_preview.png"
DEPTH_M_SUFFIX = "_depth_m.tiff"
#: the table of a recording's output folder: each frame written, with its timestamp
RECORDING_TABLE = "frames.csv"
RECORDING_TABLE_COLUMNS = ("frame", "stamp_ns", "stream", "frame_id")


@dataclass(frozen=True)
class OutputOptions:
    npy: bool = False
    previews: bool = False
    preview_max_tile: int | None = 480
    depth_m: bool = False
    ply: bool = False


def depth_mm_to_m(depth_mm: np.ndarray) -> np.ndarray:
    """float32 metres of a depth map in mm, NaN where the depth is not finite and > 0 (REP 118's 32FC1)."""
    depth = np.asarray(depth_mm, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    return np.where(valid, depth / 1000.0, np.nan).astype(np.float32)


def write_depth_m_tiff(path: str | Path, depth_mm: np.ndarray) -> Path:
    """Write a depth map [mm] as a single-channel float32 TIFF in metres, NaN = invalid, atomically."""

    depth_m = depth_mm_to_m(depth_mm)
    if depth_m.ndim != 2:
        raise ValueError(f"{path}: expected a (H, W) depth map, got shape {depth_m.shape}")
    ok, buf = cv2.imencode(".tiff", depth_m)
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode a float32 {depth_m.shape} map as TIFF")
    return atomic_write_bytes(path, buf.tobytes())


def write_ply_points(path: str | Path, points: np.ndarray, comment: str = "") -> Path:
    """Write (N, 3) points as a binary little-endian PLY (``float x, y, z``), atomically."""
    pts = np.ascontiguousarray(points, dtype="<f4")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{path}: expected (N, 3) points, got shape {pts.shape}")
    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {line}" for line in comment.splitlines() if line]
    lines += [f"element vertex {len(pts)}", "property float x", "property float y", "property float z", "end_header"]
    header = ("\n".join(lines) + "\n").encode("ascii", errors="replace")

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(pts.tobytes())

    return atomic_write(path, write)


def output_paths(out: Path, name: str) -> dict[str, Path]:
    base = Path(out) / name
    return {
        "png": base.with_name(base.name + ".png"),
        "npy": base.with_name(base.name + ".npy"),
        "sigma": base.with_name(base.name + SIGMA_SUFFIX),
        "preview": base.with_name(base.name + PREVIEW_SUFFIX),
        "depth_m": base.with_name(base.name + DEPTH_M_SUFFIX),
        "ply": base.with_name(base.name + ".ply"),
    }


def wanted_outputs(options: OutputOptions, with_sigma: bool) -> set[str]:
    """The keys of ``output_paths`` that a run with ``options`` writes."""
    keys = {"png"} | ({"npy"} if options.npy else set()) | ({"sigma"} if with_sigma else set())
    keys |= {"preview"} if options.previews else set()
    keys |= {"depth_m"} if options.depth_m else set()
    return keys | ({"ply"} if options.ply else set())


def preview_panel(
    input_mm: np.ndarray,
    valid: np.ndarray,
    restored_mm: np.ndarray,
    sigma_mm: np.ndarray | None = None,
    max_tile: int | None = 480,
    title: str | None = None,
) -> np.ndarray:
    """One-row panel (uint8 RGB): input | restored on a shared depth scale (1st..99th percentile of the valid
    input) with its colour bar, then |restored - input| over valid input pixels (and sigma_D of the input) on a
    shared millimetre scale with its colour bar. Invalid pixels are grey."""

    valid = np.asarray(valid, dtype=bool)
    out_valid = np.isfinite(restored_mm) & (restored_mm > 0)
    lo, hi = vis.robust_range(np.asarray(input_mm, dtype=np.float64), valid)
    share = 100.0 * (1.0 - valid.mean())

    def tile(rgb: np.ndarray, label: str) -> np.ndarray:
        return vis.add_title(vis._resize(rgb, max_tile), label)

    tiles = [
        tile(vis.colorize_depth(input_mm, lo, hi, valid), f"input ({share:.1f}% invalid)"),
        tile(vis.colorize_depth(restored_mm, lo, hi, out_valid), "restored"),
    ]
    tiles.append(vis.colorbar(tiles[0].shape[0], lo, hi, vis.DEPTH_COLORMAP, "mm"))
    diff = np.abs(np.asarray(restored_mm, dtype=np.float64) - input_mm)
    ok = valid & out_valid
    deviations = [(diff, ok, f"|restored-input| median {np.median(diff[ok]) if ok.any() else float('nan'):.2f} mm")]
    if sigma_mm is not None:
        s_ok = valid & np.isfinite(sigma_mm)
        deviations.append(
            (sigma_mm, s_ok, f"sigma_D input, mean {np.mean(sigma_mm[s_ok]) if s_ok.any() else float('nan'):.2f} mm")
        )
    emax = max(vis.robust_range(d, m, (0.0, 99.0))[1] for d, m, _ in deviations)
    tiles += [tile(vis.colorize_error(d, emax, m), label) for d, m, label in deviations]
    tiles.append(vis.colorbar(tiles[0].shape[0], 0.0, emax, vis.ERROR_COLORMAP, "mm"))
    panel = vis._hstack(tiles)
    if title:
        panel = vis.add_title(panel, title)
    return np.ascontiguousarray(panel)


def write_frame_outputs(
    out: str | Path,
    name: str,
    input_mm: np.ndarray,
    valid: np.ndarray,
    restored_mm: np.ndarray,
    options: OutputOptions = OutputOptions(),
    sigma_mm: np.ndarray | None = None,
    intrinsics: Intrinsics | None = None,
) -> list[Path]:
    """Write the outputs of one frame (module docstring), all or nothing (``atomic.atomic_group``: a write that fails
    leaves none of them and the files they would replace unchanged); returns the written paths. ``options.ply`` needs
    the ``intrinsics`` of the frame (checked before anything of the frame is written)."""

    paths = output_paths(Path(out), name)
    points = None
    if options.ply:
        if intrinsics is None:
            raise ValueError(f"frame {name}: a point cloud (PLY) needs the camera intrinsics (--intrinsics FILE)")
        points = points_m(depth_mm_to_m(restored_mm), intrinsics, name)
    with atomic_group():
        return _write_all(paths, name, input_mm, valid, restored_mm, options, sigma_mm, intrinsics, points)


def _write_all(paths, name, input_mm, valid, restored_mm, options, sigma_mm, intrinsics, points) -> list[Path]:
    written = [write_depth_png16(paths["png"], restored_mm)]
    if options.npy:
        written.append(save_npy_atomic(paths["npy"], np.asarray(restored_mm, dtype=np.float32)))
    if sigma_mm is not None:
        written.append(save_npy_atomic(paths["sigma"], np.asarray(sigma_mm, dtype=np.float32)))
    if options.previews:
        rgb = preview_panel(input_mm, valid, restored_mm, sigma_mm, options.preview_max_tile, title=name)
        written.append(atomic_write_png(paths["preview"], cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)))
    if options.depth_m:
        written.append(write_depth_m_tiff(paths["depth_m"], restored_mm))
    if points is not None:
        assert intrinsics is not None
        comment = f"tofdenoise restored depth {name}; metres, camera optical frame (x right, y down, z forward)\n"
        comment += (
            f"intrinsics fx {intrinsics.fx:.6g} fy {intrinsics.fy:.6g} cx {intrinsics.cx:.6g} cy {intrinsics.cy:.6g}"
        )
        written.append(write_ply_points(paths["ply"], points, comment))
    return written


def frame_sigma(frame: Any, calib: Any) -> np.ndarray | None:
    """sigma_D map of a frame's input when a calibration and the amplitude are there, else None; NaN (invalid)
    where the depth or the amplitude is not valid (``Frame.amplitude_valid``, or a non-finite amplitude)."""
    if calib is None or frame.amplitude is None:
        return None
    from tofdenoise.inference.denoise import sigma_map_mm

    amplitude = np.asarray(frame.amplitude, dtype=np.float32)
    amplitude_valid = getattr(frame, "amplitude_valid", None)
    if amplitude_valid is not None:
        amplitude = np.where(amplitude_valid, amplitude, np.nan).astype(np.float32)
    return sigma_map_mm(frame.depth_mm, frame.valid, amplitude, calib)


def write_recording_table(folder: str | Path, rows: Iterable[tuple[str, int, str, str]]) -> Path:
    """Write ``folder/frames.csv`` atomically: a header ``frame,stamp_ns,stream,frame_id``, then one row per frame
    written (its output name inside ``folder``, e.g. ``frame_000003``; its timestamp in ns; the depth topic or
    track; a bag message's ``header.frame_id``, "" for a Kinect recording), in frame order."""
    buf = io.StringIO()
    table = csv.writer(buf, lineterminator="\n")
    table.writerow(RECORDING_TABLE_COLUMNS)
    for name, stamp_ns, stream, frame_id in rows:
        table.writerow((name, int(stamp_ns), stream, frame_id))
    return atomic_write_text(Path(folder) / RECORDING_TABLE, buf.getvalue())
