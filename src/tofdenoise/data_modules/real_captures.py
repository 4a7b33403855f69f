"""Real (or simulated) iToF capture sets: on-disk format, reference building and loading for evaluation.

Format: one folder per static scene, ``SCENES_DIR/<scene>/``::

    input_depth_mm.png          16-bit, depth in mm, 0 = invalid   (the standard-exposure frame: noisy input)
    input_amplitude.png         16-bit, amplitude of the same frame (sensor units, e.g. DN)
    hiexp/depth_mm_NNN.png      16-bit, mm, 0 = invalid            (high-exposure frames, NNN = 000, 001, ...)
    hiexp/saturated_NNN.png     8-bit, nonzero = saturated pixel    (one per depth frame)
    input_taps.npy, hiexp/taps_NNN.npy   optional raw tap stacks (N, H, W); not needed by the loader
    reference_depth_mm.npy      float32, NaN = invalid              (written by build-reference)
    reference_count.npy         uint16, valid frames per pixel       (written by build-reference)
    reference.json              how the reference was built (min_count, frames, each hiexp/ file's size and
                                SHA-256)

The reference is the per-pixel mean over the valid (depth > 0), unsaturated high-exposure frames; a pixel with
fewer than ``min_count`` such frames is invalid (NaN). It is cached next to the scene (atomic writes).

The cache is used while every ``hiexp/`` file has the content it was built from: ``reference.json`` records each
file's size and SHA-256 (nothing that depends on when or where the file was written, so that a set simulated twice
is the same byte for byte), and a file is unchanged when its size and digest match. A process hashes a file once for
as long as its size, mtime, ctime and inode stay the same (``file_stamps``; a write, a copy or a ``touch`` moves the
ctime, which ``cp -p`` and ``rsync -a`` cannot set back): 0.04 s for a scene of 100 frames of 640 x 576 (31 MB of
PNG) on one core, where building its reference takes 0.8 s. Frames rewritten with other depths but their old mtimes
are thus seen, which the mtime test before 2026-11-29 missed.

One cache serves every ``min_count``: the mean at a pixel does not depend on it, so a reference at ``min_count``
m is the cached one (built at c <= m) with the pixels of fewer than m frames set invalid, bit for bit what a build
at m gives. A smaller ``min_count`` than the cached one is rebuilt from the frames and replaces the cache, with a
warning naming both values (the larger one stays derivable from it).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.atomic import atomic_group, atomic_write_bytes, atomic_write_text
from tofdenoise.data_modules.file_stamps import size_and_digest
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


#: the format of ``reference.json`` whose file records this code trusts (older caches are rebuilt once)
REFERENCE_FORMAT = 2


@dataclass
class Reference:
    depth_mm: np.ndarray  # float32, NaN = invalid
    count: np.ndarray  # uint16
    rebuilt: bool
    min_count: int = 0  # the valid frames a pixel of ``depth_mm`` needed
    cached_min_count: int | None = None  # the min_count of the cache on disk (< min_count: derived from it)


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


def _file_record(path: Path) -> dict[str, Any]:
    """A frame's size and SHA-256 (hashed again only when its size, mtime, ctime or inode moved: ``file_stamps``)."""
    size, digest = size_and_digest(path)
    return {"size": size, "sha256": digest}


def _frame_files(frames: list[tuple[Path, Path]]) -> list[Path]:
    return [p for pair in frames for p in pair]


def _cached_meta(scene: Path, frames: list[tuple[Path, Path]]) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """(the cache's ``reference.json`` when the cache holds a reference of exactly these frames' contents, else
    None; the parsed ``reference.json`` whatever its state, None when there is none)."""
    ref, cnt, meta = scene / REFERENCE_DEPTH, scene / REFERENCE_COUNT, scene / REFERENCE_META
    try:
        info = json.loads(meta.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None, None
    if not isinstance(info, dict):
        return None, None
    if not (ref.is_file() and cnt.is_file()) or info.get("format") != REFERENCE_FORMAT:
        return None, info
    records = info.get("files")
    if info.get("frames") != [p.name for p, _ in frames] or not isinstance(records, dict):
        return None, info
    if not isinstance(info.get("min_count"), int) or info["min_count"] < 1:
        return None, info
    for path in _frame_files(frames):
        record = records.get(f"{HIEXP_DIR}/{path.name}")
        if not isinstance(record, dict) or path.stat().st_size != record.get("size"):
            return None, info
    for path in _frame_files(frames):
        if _file_record(path) != records[f"{HIEXP_DIR}/{path.name}"]:
            return None, info
    return info, info


def _npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return buf.getvalue()


def _load_cached(scene: Path, info: dict[str, Any], needed: int) -> Reference | None:
    """The cached reference at ``needed`` (>= the cache's ``min_count``), or None when its arrays are unreadable,
    are not the ones ``reference.json`` recorded (their SHA-256: a build cut short or two builds at once) or do not
    hold a reference at its ``min_count``."""
    arrays, loaded = info.get("arrays"), []
    for name in (REFERENCE_DEPTH, REFERENCE_COUNT):
        try:
            data = (scene / name).read_bytes()
            if not isinstance(arrays, dict) or hashlib.sha256(data).hexdigest() != arrays.get(name):
                return None
            loaded.append(np.load(io.BytesIO(data), allow_pickle=False))
        except (OSError, ValueError):
            return None
    depth, count = loaded
    cached_min_count = int(info["min_count"])
    if depth.shape != count.shape or depth.dtype != np.float32 or np.isnan(depth[count >= cached_min_count]).any():
        return None  # not a reference at its recorded min_count (a pixel of enough frames without a depth)
    if needed != cached_min_count:
        depth = np.where(count >= needed, depth, np.float32(np.nan)).astype(np.float32)
    return Reference(depth, count, rebuilt=False, min_count=needed, cached_min_count=cached_min_count)


def build_reference(scene_dir: str | Path, min_count: int | None = None, force: bool = False) -> Reference:
    """Build (or reuse) the scene's multi-frame reference at ``min_count`` (None: half of the frames).

    The cache (module docstring) is reused while the ``hiexp/`` files hold the bytes it was built from; a cache
    built at a smaller ``min_count`` gives this one exactly, without a rebuild; otherwise the reference is rebuilt
    and the three files written, all or none (``reference.json`` records the arrays' SHA-256, and a cache whose
    arrays are not those is rebuilt). A rebuild keeps the smaller of the cache's ``min_count`` and this one, and a
    cache of another ``min_count`` is replaced with a warning naming both. ``force``: rebuilt at ``min_count``
    whatever the cache."""
    scene = Path(scene_dir)
    frames = hiexp_frames(scene)
    needed = default_min_count(len(frames)) if min_count is None else int(min_count)
    if needed < 1:
        raise ValueError(f"min_count must be >= 1, got {min_count}")
    fresh, old = (None, None) if force else _cached_meta(scene, frames)
    if force:
        try:
            old = json.loads((scene / REFERENCE_META).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            old = None
    if fresh is not None and fresh["min_count"] <= needed:
        cached = _load_cached(scene, fresh, needed)
        if cached is not None:
            return cached
    old_min_count = old.get("min_count") if isinstance(old, dict) else None
    keep = needed
    if not force and isinstance(old_min_count, int) and 1 <= old_min_count < needed:
        keep = old_min_count  # the cache stays as informative as it was: ``needed`` is derived from it
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

    records = {f"{HIEXP_DIR}/{path.name}": _file_record(path) for path in _frame_files(frames)}
    mean, count = accumulate_reference(_frames(), keep)
    input_path = scene / INPUT_DEPTH
    if input_path.is_file():
        input_depth = read_png_uint16(input_path, what="input depth")
        check_same_shape(
            input_depth, mean, reference_path=input_path, other_path=frames[0][0], what="high-exposure depth"
        )
    if isinstance(old_min_count, int) and old_min_count != keep:
        warnings.warn(
            f"capture scene {scene}: its cached reference was built with min_count {old_min_count} "
            f"({REFERENCE_META}); rebuilt with min_count {keep} and cached in its place"
            + (
                f" (a reference at min_count {old_min_count} is derived from it exactly)"
                if old_min_count > keep
                else f" (--force; a reference at min_count {old_min_count} now needs a rebuild)"
            ),
            stacklevel=2,
        )
    arrays = {REFERENCE_DEPTH: _npy_bytes(mean), REFERENCE_COUNT: _npy_bytes(count)}
    meta = {
        "format": REFERENCE_FORMAT,
        "min_count": keep,
        "num_frames": len(frames),
        "frames": [p.name for p, _ in frames],
        "valid_pixels": int(np.isfinite(mean).sum()),
        "files": records,
        "arrays": {name: hashlib.sha256(data).hexdigest() for name, data in arrays.items()},
        "note": "mean over valid, unsaturated high-exposure frames; a reference at a larger min_count is this one "
        "where reference_count.npy >= it",
    }
    with atomic_group():  # all three or none
        for name, data in arrays.items():
            atomic_write_bytes(scene / name, data)
        atomic_write_text(scene / REFERENCE_META, json.dumps(meta, indent=1) + "\n")
    if keep != needed:
        mean = np.where(count >= needed, mean, np.float32(np.nan)).astype(np.float32)
    return Reference(mean, count, rebuilt=True, min_count=needed, cached_min_count=keep)


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
