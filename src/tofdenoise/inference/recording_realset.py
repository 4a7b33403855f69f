"""A real test scene from a static recording: ``tofdenoise sensor realset --from-recording REC``.

A camera engineer records a static scene (camera on a tripod, nothing moving) for a few seconds. Its frames become
one scene of the capture-set format of ``data_modules.real_captures`` (docs/data.md), ready for ``data.real_dir``:

- ``input_depth_mm.png`` / ``input_amplitude.png``: one frame as captured (``input_frame``, default the first), the
  noisy input;
- ``hiexp/depth_mm_NNN.png``: every other frame (the input frame is left out, so the reference's noise is
  independent of the input's), with an all-zero ``hiexp/saturated_NNN.png`` each (a depth camera's recording marks
  saturated pixels invalid, 0, itself);
- ``reference_depth_mm.npy`` / ``reference_count.npy`` / ``reference.json``: ``real_captures.build_reference``,
  the per-pixel mean over the frames where the pixel is valid; a pixel needs ``min_count`` valid frames (default:
  half of them, the capture-set default, so that ``data.real_dir`` loads the reference as written; a run with a
  stricter ``data.real_min_count`` derives its reference from this one, a laxer one rebuilds it with a warning).
  The scores are computed over the common valid region of input and reference (``load_real_scene``'s mask);
- ``recording.json``: where the scene came from (recording, streams, frames, the motion check).

The frames are same-exposure frames, not the paper's high-exposure ones: the reference averages N frames of the
input's own noise (its noise std is about 1/sqrt(N) of the input's), not a brighter capture.

**A moving scene is refused** (``SceneMotionError``), not warned about: the mean of frames of a scene that moved is
no reference for any of them, and a test set built from it would score models against a blur. Every frame is
compared with the per-pixel median of all frames; a pixel disagrees when it is more than
``max(motion_tolerance_mm, 1 % of its depth)`` away, and a frame in which more than ``max_moving_fraction`` (5 %)
of the valid pixels disagree is a moving frame. Any moving frame stops the command with a line listing them (the
tolerance is an option: a camera noisier than 20 mm at its range needs a larger one).

Nothing is half-written: the recording is read and checked whole first, and the scene is written into a hidden
temporary folder next to its destination and renamed into place at the end (:func:`publish_scene`). Without
``force`` that rename is the check that the scene is new: a folder renamed onto an existing, non-empty folder fails
(POSIX ``rename``: ENOTEMPTY / EEXIST), so of two runs writing one scene at once exactly one publishes it and the
other is refused (:class:`SceneExistsError`) with its own work removed; the "exists" check before the work only
saves reading a recording for nothing.

The partial folder (``.<scene>.XXXXXXXX.partial``) is held with an ``flock`` for as long as its run writes it; the
kernel drops the lock when the run ends in any way. A run killed hard (SIGKILL, a power cut) leaves its partial
folder behind: the next run onto the same scene removes it (:func:`remove_stale_partials`) when nobody holds its
lock and it holds nothing but what a scene being written holds. Readers of a capture set skip folders whose name
starts with a dot. Ctrl-C before the scene is published removes the partial folder; once the rename has begun, the
rename completes and the scene stands (a Ctrl-C then no longer undoes it).
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tofdenoise.atomic import atomic_write_text, sigint_deferred
from tofdenoise.data_modules.io import depth_mm_to_png16, write_png_uint8, write_png_uint16
from tofdenoise.data_modules.real_captures import (
    HIEXP_DIR,
    INPUT_AMPLITUDE,
    INPUT_DEPTH,
    REFERENCE_COUNT,
    REFERENCE_DEPTH,
    REFERENCE_META,
    build_reference,
    default_min_count,
)
from tofdenoise.inference.recordings import RecordingError, RecordingFrame, open_recording

__all__ = [
    "SceneExistsError",
    "SceneMotionError",
    "SceneSummary",
    "moving_frames",
    "publish_scene",
    "remove_stale_partials",
    "scene_from_frames",
    "scene_from_recording",
]

RECORDING_META = "recording.json"


class SceneMotionError(ValueError):
    """The frames of a recording disagree: the scene (or the camera) moved."""


class SceneExistsError(ValueError):
    """The scene folder exists (or another run published it meanwhile) and ``force`` is off."""


def _exists_error(scene_dir: Path, meanwhile: bool) -> SceneExistsError:
    when = " (another run wrote it while this one worked; this run's scene was discarded)" if meanwhile else ""
    return SceneExistsError(f"scene folder {scene_dir} exists{when}; --force replaces it")


#: errno of a rename onto a folder that is taken (exists and is not empty) or onto a file
_TAKEN = (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR, errno.EISDIR)


def publish_scene(tmp: Path, scene_dir: Path, force: bool = False) -> None:
    """Rename the complete scene ``tmp`` to ``scene_dir`` (both in one folder).

    Without ``force`` the rename is exclusive: it fails when ``scene_dir`` exists and is not an empty folder (a
    scene another run published since this one checked), :class:`SceneExistsError`; ``tmp`` is left for the caller
    to remove. With ``force`` an existing scene is moved aside, the new one renamed in, and the old one removed
    (put back if the rename fails otherwise): the folder holds one complete scene (two forced runs: the last one's)."""
    while True:
        aside = None
        if force and scene_dir.exists():
            aside = Path(tempfile.mkdtemp(prefix=f".{scene_dir.name}.", suffix=".old", dir=scene_dir.parent))
            try:
                os.rename(scene_dir, aside / scene_dir.name)
            except FileNotFoundError:  # another forced run moved it aside first
                pass
        try:
            os.rename(tmp, scene_dir)  # onto a missing or an empty folder only (POSIX rename)
        except OSError as exc:
            taken = exc.errno in _TAKEN
            if aside is not None and not taken:  # the new scene could not go in: the old one goes back
                try:
                    os.rename(aside / scene_dir.name, scene_dir)
                except OSError:
                    pass
            if aside is not None and (taken or not (aside / scene_dir.name).exists()):
                shutil.rmtree(aside, ignore_errors=True)  # taken: another forced run's complete scene is in place
            if not taken:
                raise
            if not force:
                raise _exists_error(scene_dir, meanwhile=True) from None
            continue  # another forced run published in between: that scene is moved aside in turn
        if aside is not None:
            shutil.rmtree(aside, ignore_errors=True)
        return


#: what a partial scene folder may hold (besides the atomic writers' temporary files ``.<name>.*.tmp*``)
_PARTIAL_ENTRIES = frozenset(
    {INPUT_DEPTH, INPUT_AMPLITUDE, HIEXP_DIR, REFERENCE_DEPTH, REFERENCE_COUNT, REFERENCE_META, RECORDING_META}
)
_HIEXP_ENTRY = re.compile(r"^(depth_mm|saturated)_\d+\.png$")
_TMP_ENTRY = re.compile(r"^\..+\.tmp[.\w]*$")


def _partial_pattern(scene: str) -> re.Pattern[str]:
    """Names of this scene's partial folders: ``tempfile.mkdtemp(prefix=".<scene>.", suffix=".partial")``."""
    return re.compile(rf"^\.{re.escape(scene)}\.[A-Za-z0-9_]{{8}}\.partial$")


def _looks_like_a_partial_scene(folder: Path) -> bool:
    """Only the files a scene being written holds (and nothing that is not a plain file or ``hiexp/``)."""
    for entry in folder.iterdir():
        if entry.name == HIEXP_DIR and entry.is_dir() and not entry.is_symlink():
            if not all(
                (_HIEXP_ENTRY.match(e.name) or _TMP_ENTRY.match(e.name)) and e.is_file() and not e.is_symlink()
                for e in entry.iterdir()
            ):
                return False
        elif not ((entry.name in _PARTIAL_ENTRIES or _TMP_ENTRY.match(entry.name)) and entry.is_file()):
            return False
        elif entry.is_symlink():
            return False
    return True


def remove_stale_partials(scene_dir: str | Path) -> list[Path]:
    """Remove the partial folders of ``scene_dir`` that runs killed hard left behind (module docstring); returns
    them. A partial folder is removed only when its name is one this module gives, nobody holds its lock (its run
    has ended) and it holds nothing but a scene's files; anything else is left as it is."""
    scene_dir = Path(scene_dir)
    if not scene_dir.parent.is_dir():
        return []
    pattern, removed = _partial_pattern(scene_dir.name), []
    for folder in sorted(scene_dir.parent.iterdir()):
        if not pattern.match(folder.name) or folder.is_symlink() or not folder.is_dir():
            continue
        try:
            fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # a running run's partial
                continue
            if os.fstat(fd).st_nlink == 0 or not _looks_like_a_partial_scene(folder):
                continue
            shutil.rmtree(folder)
            removed.append(folder)
        finally:
            os.close(fd)
    return removed


def _own_partial(scene_dir: Path) -> tuple[Path, int]:
    """A new partial folder next to ``scene_dir`` and the descriptor that holds its lock until it is closed."""
    while True:
        tmp = Path(tempfile.mkdtemp(prefix=f".{scene_dir.name}.", suffix=".partial", dir=scene_dir.parent))
        fd = os.open(tmp, os.O_RDONLY | os.O_DIRECTORY)
        fcntl.flock(fd, fcntl.LOCK_EX)
        if os.fstat(fd).st_nlink > 0:  # not removed by another run's clean-up between mkdtemp and the lock
            return tmp, fd
        os.close(fd)


@dataclass
class SceneSummary:
    scene_dir: Path
    input_frame: int
    reference_frames: int
    min_count: int
    reference_valid_fraction: float
    disagreeing_fraction_max: float
    #: partial folders of this scene that runs killed hard had left, removed before this run wrote its own
    stale_partials_removed: list[Path] = field(default_factory=list)


def moving_frames(
    depth_mm: Sequence[np.ndarray],
    valid: Sequence[np.ndarray],
    motion_tolerance_mm: float = 20.0,
    max_moving_fraction: float = 0.05,
) -> tuple[list[tuple[int, float]], np.ndarray]:
    """((frame, fraction of its valid pixels that disagree) for each moving frame, the fraction of every frame):
    a pixel disagrees when it is more than ``max(motion_tolerance_mm, 1 % of the depth)`` from the per-pixel median
    of the frames (module docstring)."""
    stack = np.stack([np.where(v, d, np.nan) for d, v in zip(depth_mm, valid)]).astype(np.float32)
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: no frame sees them
            median = np.nanmedian(stack, axis=0)
        tolerance = np.maximum(float(motion_tolerance_mm), 0.01 * median)
        disagree = np.abs(stack - median[None]) > tolerance[None]
    counts = np.isfinite(stack).reshape(len(stack), -1).sum(axis=1)
    fractions = disagree.reshape(len(stack), -1).sum(axis=1) / np.maximum(counts, 1)
    moving = [(i, float(f)) for i, f in enumerate(fractions) if f > max_moving_fraction]
    return moving, fractions


def _amplitude_u16(amplitude: np.ndarray, where: str) -> np.ndarray:
    amp = np.asarray(amplitude, dtype=np.float64)
    amp = np.where(np.isfinite(amp), amp, 0.0)
    if amp.min() < 0 or amp.max() > 65535:
        raise RecordingError(f"{where}: amplitude values span [{amp.min():g}, {amp.max():g}]; expected 0..65535")
    return np.rint(amp).astype(np.uint16)


def scene_from_frames(
    frames: Sequence[RecordingFrame],
    scene_dir: str | Path,
    input_frame: int = 0,
    min_count: int | None = None,
    motion_tolerance_mm: float = 20.0,
    max_moving_fraction: float = 0.05,
    force: bool = False,
    source: dict | None = None,
    where: str = "recording",
) -> SceneSummary:
    """Write one capture-set scene from the frames of a static recording (module docstring)."""
    scene_dir = Path(scene_dir).expanduser()
    if len(frames) < 3:
        raise RecordingError(f"{where}: {len(frames)} frame(s); a scene needs an input frame and >= 2 others")
    if not 0 <= input_frame < len(frames):
        raise RecordingError(f"{where}: --input-frame {input_frame} is not a frame (0 .. {len(frames) - 1})")
    shape = frames[0].depth_mm.shape
    for f in frames:
        if f.depth_mm.shape != shape:
            raise RecordingError(f"{where}: frame {f.index} is {f.depth_mm.shape}; expected {shape} like frame 0")
    chosen = frames[input_frame]
    if chosen.amplitude is None:
        why = f" ({chosen.no_amplitude})" if chosen.no_amplitude else ""
        raise RecordingError(
            f"{where}: frame {chosen.index} has no amplitude{why}; a capture-set scene needs the input's amplitude "
            "(name the IR / amplitude stream with --amplitude-stream)"
        )
    others = [f for i, f in enumerate(frames) if i != input_frame]
    needed = default_min_count(len(others)) if min_count is None else int(min_count)
    if not 1 <= needed <= len(others):
        raise RecordingError(f"{where}: --min-count {needed} must lie in 1 .. {len(others)} (the reference frames)")
    moving, fractions = moving_frames(
        [f.depth_mm for f in frames], [f.valid for f in frames], motion_tolerance_mm, max_moving_fraction
    )
    if moving:
        listed = ", ".join(f"{frames[i].index} ({100 * frac:.0f} %)" for i, frac in moving[:8])
        raise SceneMotionError(
            f"{where}: the scene moved: in {len(moving)} of {len(frames)} frames more than "
            f"{100 * max_moving_fraction:g} % of the valid pixels are farther than max({motion_tolerance_mm:g} mm, "
            f"1 % of the depth) from the per-pixel median of the frames: frames {listed}"
            f"{' ...' if len(moving) > 8 else ''}; record a static scene (or raise --motion-tolerance-mm for a "
            "noisier camera)"
        )
    if scene_dir.exists() and not force:  # early, to spare the work; publish_scene decides
        raise _exists_error(scene_dir, meanwhile=False)
    amplitude = _amplitude_u16(chosen.amplitude, f"{where} frame {chosen.index}")

    scene_dir.parent.mkdir(parents=True, exist_ok=True)
    stale = remove_stale_partials(scene_dir)
    tmp, lock_fd = _own_partial(scene_dir)
    published = False
    try:
        write_png_uint16(tmp / INPUT_DEPTH, depth_mm_to_png16(np.where(chosen.valid, chosen.depth_mm, 0.0)))
        write_png_uint16(tmp / INPUT_AMPLITUDE, amplitude)
        zeros = np.zeros(shape, dtype=np.uint8)
        for k, f in enumerate(others):
            depth = depth_mm_to_png16(np.where(f.valid, f.depth_mm, 0.0))
            write_png_uint16(tmp / HIEXP_DIR / f"depth_mm_{k:03d}.png", depth)
            write_png_uint8(tmp / HIEXP_DIR / f"saturated_{k:03d}.png", zeros)
        reference = build_reference(tmp, min_count=needed, force=True)
        meta = {
            **(source or {}),
            "input_frame": chosen.index,
            "reference_frames": [f.index for f in others],
            "min_count": needed,
            "motion_check": {
                "tolerance_mm": motion_tolerance_mm,
                "tolerance_relative": 0.01,
                "max_moving_fraction": max_moving_fraction,
                "disagreeing_fraction_max": float(fractions.max()),
            },
            "note": "static recording: input = one frame as captured; reference = mean of the other frames' valid "
            "depths where at least min_count are valid (same exposure as the input)",
        }
        atomic_write_text(tmp / RECORDING_META, json.dumps(meta, indent=1) + "\n")
        try:
            with sigint_deferred():  # a Ctrl-C during the rename is raised after it
                publish_scene(tmp, scene_dir, force=force)  # --force: the old scene goes once the new one is complete
                published = True
        except KeyboardInterrupt:
            if not published:
                raise
            # the scene is complete and in place: the Ctrl-C came too late to undo it, the command finishes
    except BaseException:
        if not published:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        os.close(lock_fd)
    return SceneSummary(
        scene_dir=scene_dir,
        input_frame=chosen.index,
        reference_frames=len(others),
        min_count=needed,
        reference_valid_fraction=float(np.isfinite(reference.depth_mm).mean()),
        disagreeing_fraction_max=float(fractions.max()),
        stale_partials_removed=stale,
    )


def scene_from_recording(
    recording: str | Path,
    out: str | Path,
    scene: str | None = None,
    depth_stream: str | None = None,
    amplitude_stream: str | None = None,
    **options,
) -> SceneSummary:
    """Read a static recording whole (``recordings.open_recording``) and write it as the scene ``OUT/<scene>``
    (default: the recording's name without suffix); ``options`` go to ``scene_from_frames``."""
    path = Path(recording).expanduser()
    rec = open_recording(path, depth_stream, amplitude_stream)
    rec.scan()
    frames = list(rec.frames())
    name = scene or (path.stem if path.is_file() else path.name)
    source = {
        "recording": str(path),
        "depth_stream": rec.depth_name,
        "amplitude_stream": rec.amplitude_name,
        "frames": len(frames),
    }
    return scene_from_frames(frames, Path(out).expanduser() / name, source=source, where=f"recording {path}", **options)
