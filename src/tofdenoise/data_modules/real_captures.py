"""Real (or simulated) iToF capture sets: on-disk format, reference building and loading for evaluation.

Format: one folder per static scene, ``SCENES_DIR/<scene>/``::

    input_depth_mm.png          16-bit, depth in mm, 0 = invalid   (the standard-exposure frame: noisy input)
    input_amplitude.png         16-bit, amplitude of the same frame (sensor units, e.g. DN)
    hiexp/depth_mm_NNN.png      16-bit, mm, 0 = invalid            (high-exposure frames, NNN = 000, 001, ...)
    hiexp/saturated_NNN.png     8-bit, nonzero = saturated pixel    (one per depth frame)
    input_taps.npy, hiexp/taps_NNN.npy   optional raw tap stacks (N, H, W); not needed by the loader
    reference_depth_mm.npy      float32, NaN = invalid              (written by build-reference)
    reference_count.npy         uint16, valid frames per pixel       (written by build-reference)
    reference.json              how the reference was built (min_count, frames)

The reference is the per-pixel mean over the valid (depth > 0), unsaturated high-exposure frames; a pixel with
fewer than ``min_count`` such frames is invalid (NaN). It is cached next to the scene (atomic writes) and rebuilt
when a high-exposure frame is newer than it or when ``min_count`` / the frame list changed.
"""

from __future__ import annotations

import json
import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.atomic import atomic_write_text, save_npy_atomic
from tofdenoise.data_modules.io import DataFileError, check_same_shape, read_image, read_png_uint16
from tofdenoise.physics.uncertainty import amplitude_to_signal_e, sigma_depth_mm

INPUT_DEPTH = "input_depth_mm.png"
INPUT_AMPLITUDE = "input_amplitude.png"
HIEXP_DIR = "hiexp"
REFERENCE_DEPTH = "reference_depth_mm.npy"
REFERENCE_COUNT = "reference_count.npy"
REFERENCE_META = "reference.json"
_FRAME_RE = re.compile(r"^depth_mm_(\d+)\.png$")


def default_min_count(num_frames: int) -> int:
    """Default minimum number of valid frames for a reference pixel: half of the frames (at least 1)."""
    return max(1, int(math.ceil(0.5 * num_frames)))


def list_scenes(
    scenes_dir: str | Path, *, config_key: str = "data.real_dir", incomplete: list[str] | None = None
) -> list[Path]:
    """Scene folders (those holding ``input_depth_mm.png``), sorted by name; hidden folders (a name starting with a
    dot, such as the partial folder of a scene being written) are not scenes.

    A folder that looks like a scene (it has ``hiexp/``) but lacks ``input_depth_mm.png`` cannot be evaluated:
    it is left out with a warning naming it, and its name is appended to ``incomplete`` when given (the
    caller counts it as skipped).
    """
    root = Path(scenes_dir).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"capture set folder not found: {root} (check {config_key})")
    scenes, partial = [], []
    for p in sorted(root.iterdir()):
        if p.name.startswith("."):  # hidden: a scene being written (``.<scene>.XXXXXXXX.partial``) or not a scene
            continue
        if p.is_dir() and (p / INPUT_DEPTH).is_file():
            scenes.append(p)
        elif p.is_dir() and (p / HIEXP_DIR).is_dir():
            partial.append(p.name)
    if partial:
        warnings.warn(
            f"capture set {root}: {len(partial)} scene folder(s) with {HIEXP_DIR}/ but no {INPUT_DEPTH} "
            f"skipped: {', '.join(partial[:5])}{' ...' if len(partial) > 5 else ''}",
            stacklevel=2,
        )
        if incomplete is not None:
            incomplete.extend(partial)
    if not scenes:
        raise FileNotFoundError(f"capture set {root} has no scene folder with {INPUT_DEPTH} (check {config_key})")
    return scenes


def hiexp_frames(scene_dir: str | Path) -> list[tuple[Path, Path]]:
    """(depth, saturation) file pairs of the high-exposure frames, in frame order."""
    hiexp = Path(scene_dir) / HIEXP_DIR
    if not hiexp.is_dir():
        raise FileNotFoundError(f"capture scene {scene_dir}: high-exposure folder {hiexp} not found")
    frames = []
    for path in hiexp.iterdir():
        match = _FRAME_RE.match(path.name)
        if match:
            frames.append((int(match.group(1)), path, hiexp / f"saturated_{match.group(1)}.png"))
    if not frames:
        raise FileNotFoundError(f"capture scene {scene_dir}: no {HIEXP_DIR}/depth_mm_NNN.png frames")
    frames.sort()
    missing = [str(sat) for _, _, sat in frames if not sat.is_file()]
    if missing:
        raise FileNotFoundError(f"capture scene {scene_dir}: saturation mask(s) missing: {', '.join(missing[:5])}")
    return [(depth, sat) for _, depth, sat in frames]


@dataclass
class Reference:
    depth_mm: np.ndarray  # float32, NaN = invalid
    count: np.ndarray  # uint16
    rebuilt: bool


def accumulate_reference(frames: list[tuple[np.ndarray, np.ndarray]], min_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean over valid (> 0, finite), unsaturated frames per pixel; NaN where fewer than min_count frames."""
    total = None
    count = None
    for depth, saturated in frames:
        depth = np.asarray(depth, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(depth) & (depth > 0) & ~np.asarray(saturated, dtype=bool)
        if total is None:
            total = np.zeros(depth.shape, dtype=np.float64)
            count = np.zeros(depth.shape, dtype=np.int64)
        total += np.where(ok, depth, 0.0)
        count += ok
    if total is None:
        raise ValueError("reference: no frames")
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count >= max(int(min_count), 1), total / np.maximum(count, 1), np.nan)
    return mean.astype(np.float32), np.minimum(count, np.iinfo(np.uint16).max).astype(np.uint16)


def _reference_is_fresh(scene: Path, frames: list[tuple[Path, Path]], min_count: int) -> bool:
    ref, cnt, meta = scene / REFERENCE_DEPTH, scene / REFERENCE_COUNT, scene / REFERENCE_META
    if not (ref.is_file() and cnt.is_file() and meta.is_file()):
        return False
    try:
        info = json.loads(meta.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return False
    if info.get("min_count") != int(min_count) or info.get("frames") != [p.name for p, _ in frames]:
        return False
    built = min(ref.stat().st_mtime, cnt.stat().st_mtime, meta.stat().st_mtime)
    newest = max(max(d.stat().st_mtime, s.stat().st_mtime) for d, s in frames)
    return newest <= built


def build_reference(scene_dir: str | Path, min_count: int | None = None, force: bool = False) -> Reference:
    """Build (or reuse) the scene's multi-frame reference; writes the three reference files atomically."""
    scene = Path(scene_dir)
    frames = hiexp_frames(scene)
    needed = default_min_count(len(frames)) if min_count is None else int(min_count)
    if needed < 1:
        raise ValueError(f"min_count must be >= 1, got {min_count}")
    if not force and _reference_is_fresh(scene, frames, needed):
        try:
            return Reference(np.load(scene / REFERENCE_DEPTH), np.load(scene / REFERENCE_COUNT), rebuilt=False)
        except (OSError, ValueError):
            pass  # unreadable cached reference: rebuild below
    shape = None

    def _frames():
        nonlocal shape
        for depth_path, sat_path in frames:
            depth = read_png_uint16(depth_path, what="high-exposure depth")
            saturated = read_image(sat_path, what="saturation mask", allowed_dtypes=(np.uint8,))
            if shape is None:
                shape = depth.shape
            elif depth.shape != shape:
                raise DataFileError(
                    f"high-exposure depth file {depth_path} has shape {depth.shape}; expected {shape} "
                    f"like {frames[0][0]}"
                )
            check_same_shape(depth, saturated, reference_path=depth_path, other_path=sat_path, what="saturation mask")
            yield depth, saturated != 0

    mean, count = accumulate_reference(_frames(), needed)
    input_path = scene / INPUT_DEPTH
    if input_path.is_file():
        input_depth = read_png_uint16(input_path, what="input depth")
        check_same_shape(
            input_depth, mean, reference_path=input_path, other_path=frames[0][0], what="high-exposure depth"
        )
    save_npy_atomic(scene / REFERENCE_DEPTH, mean)
    save_npy_atomic(scene / REFERENCE_COUNT, count)
    meta = {
        "min_count": needed,
        "num_frames": len(frames),
        "frames": [p.name for p, _ in frames],
        "valid_pixels": int(np.isfinite(mean).sum()),
        "note": "mean over valid, unsaturated high-exposure frames",
    }
    atomic_write_text(scene / REFERENCE_META, json.dumps(meta, indent=1) + "\n")
    return Reference(mean, count, rebuilt=True)


def load_real_scene(scene_dir: str | Path, calib: Any, min_count: int | None = None) -> dict[str, Any]:
    """One evaluation sample.

    The network input is the frame as captured: ``noisy`` = input depth and ``amplitude`` = input amplitude at
    every valid input pixel (depth > 0; 0 elsewhere), whatever the reference. ``mask`` = the scoring region,
    the common valid region of input and reference (paper Sec. V-D applies this ROI to the metrics only);
    ``clean`` = reference and ``sigma`` = WLS sigma_D of the input (amplitude mapped to the calibration's
    signal interval) inside it, 0 outside."""
    scene = Path(scene_dir)
    depth_path, amp_path = scene / INPUT_DEPTH, scene / INPUT_AMPLITUDE
    depth = read_png_uint16(depth_path, what="input depth").astype(np.float32)
    amplitude = read_png_uint16(amp_path, what="input amplitude").astype(np.float32)
    check_same_shape(depth, amplitude, reference_path=depth_path, other_path=amp_path, what="input amplitude")
    reference = build_reference(scene, min_count=min_count).depth_mm
    check_same_shape(
        depth, reference, reference_path=depth_path, other_path=scene / REFERENCE_DEPTH, what="reference depth"
    )
    input_valid = depth > 0
    with np.errstate(invalid="ignore"):
        mask = input_valid & np.isfinite(reference) & (reference > 0)
    sigma = np.zeros_like(depth)
    if mask.any():
        signal = np.asarray(
            amplitude_to_signal_e(np.maximum(amplitude, 1e-6), calib, valid=input_valid), dtype=np.float32
        )
        safe_signal = np.where(input_valid & np.isfinite(signal), signal, calib.signal_min_e).astype(np.float32)
        sigma = np.asarray(
            sigma_depth_mm(np.where(input_valid, depth, 1.0).astype(np.float32), safe_signal, calib), dtype=np.float32
        )
        mask &= np.isfinite(sigma)
    zero = np.float32(0.0)
    return {
        "name": scene.name,
        "noisy": np.where(input_valid, depth, zero),
        "clean": np.where(mask, reference, zero),
        "sigma": np.where(mask, sigma, zero),
        "mask": mask.astype(np.float32),
        "amplitude": np.where(input_valid, amplitude, zero),
    }
