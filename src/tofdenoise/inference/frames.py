"""Camera frames for inference: find depth frames, read them with their validity, pair amplitude frames by stem.

Depth formats (by suffix): 16-bit PNG/TIFF holding millimetres (0 = invalid), ``.npy`` float or integer maps in
millimetres (NaN, inf, 0 and negative values = invalid), ``.exr`` (the depth-like channel, same validity). A
``depth_scale_mm`` other than 1 converts stored units to mm (e.g. 0.25 for a camera counting quarter millimetres,
1000 for metres). An 8-bit or colour image, and an 8-bit integer ``.npy``, is refused: it cannot hold depth in
millimetres. Without a depth scale, ``check_depth_units_mm`` refuses a frame whose valid depths lie mostly outside
the depths the network and the sensor work in (``plausible_depth_range_mm``): its median valid depth below the
training scenes' nearest depth (``DEFAULT_MIN_DEPTH_MM``, 300 mm) or beyond the calibration's unambiguous range
(c / 2f, 2998 mm for the default camera), i.e. more than half of its valid depths out of that range on one side. Such a
frame is almost surely in other units: metres (a Kinect frame / 1000), centimetres (/ 10) or 0.1 mm (x 10); the
error names the median and the likely unit. With or without a depth scale, a frame holding a valid depth beyond
``PNG16_MAX_MM`` (65535 mm) is refused (naming the count and the largest): no time-of-flight camera measures that
far, the restored 16-bit millimetre PNG could not hold it, and the network would see an input far outside anything
it was trained on (a 2^40 mm map was restored to an all-zero PNG, with numpy's overflow warning).

``outside_training_depths`` is a warning, not a refusal: a frame in millimetres whose valid depths lie mostly (more
than half of them) outside the depths the checkpoint was trained on (``training/depth_range.py``; e.g. an ADI
ADTF3175D frame reaching 7.5 m against the built-in scenes' 0.3-2.4 m) is restored, and the summary says that its
restoration there is an extrapolation.

Amplitude values that are not finite (NaN, inf) are invalid: the sigma_D map is NaN there, and a frame whose
amplitude is invalid at every pixel of valid depth is refused (``FrameError`` naming the amplitude file).

Amplitude frames are paired by the depth frame's stem (``AmplitudeSource``): from a folder (the depth frame's
sub-folder mirrored, then the folder itself), from a template with ``{stem}`` (e.g. ``amp/{stem}_amp.png``), or
from a glob pattern (``amp/*.png``) whose matches are keyed by stem. A template's ``{stem:OLD=NEW}`` is the stem
with its one occurrence of ``OLD`` replaced by ``NEW``: a camera that names both files of a frame, e.g. the ADI
ADTF3175D SDK's ``frame_mode2_depth_000123.npy`` and ``frame_mode2_ab_000123.npy``, pairs with
``adi/{stem:depth=ab}.npy``. A file that is the amplitude of a depth frame is not itself a depth frame
(``drop_amplitude_files``: the SDK writes both into one folder).
"""

from __future__ import annotations

import glob as _glob
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.data_modules.io import (
    MIN_MEDIAN_DEPTH_MM,
    PNG16_MAX_MM,
    DataFileError,
    read_amplitude,
    read_array,
    read_image,
    refuse_8bit_depth,
)

__all__ = [
    "DEPTH_FRAME_SUFFIXES",
    "Frame",
    "FrameInput",
    "AmplitudeSource",
    "drop_amplitude_files",
    "find_frames",
    "read_depth_frame",
    "load_frame",
    "make_frame",
    "checked_amplitude",
    "depth_values_mm",
    "FrameError",
    "MIN_MEDIAN_DEPTH_MM",
    "LIKELY_UNITS",
    "check_depth_units_mm",
    "outside_training_depths",
    "plausible_depth_range_mm",
]

DEPTH_FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".exr")
#: recordings (``inference.recordings``): files ``find_frames`` leaves to ``find_recordings``
RECORDING_SUFFIXES = (".mkv", ".bag")
AMPLITUDE_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".exr")


#: the units a frame refused by ``check_depth_units_mm`` is tried in, (mm per stored unit, name), in this order: the
#: error names the first whose scaled median lies in the plausible range
LIKELY_UNITS: tuple[tuple[float, str], ...] = ((1000.0, "metres"), (10.0, "centimetres"), (0.1, "0.1 mm units"))


class FrameError(ValueError):
    """A frame (or its amplitude) cannot be used; the message names the file and what was expected."""


@dataclass(frozen=True)
class FrameInput:
    """A depth frame on disk and its output name: ``rel`` is the path relative to the input folder (the file
    name for a file given directly); outputs mirror it."""

    path: Path
    rel: Path

    @property
    def rel_stem(self) -> Path:
        return self.rel.with_suffix("")


@dataclass
class Frame:
    """A depth frame in memory: ``depth_mm`` float32 (H, W) with 0 at invalid pixels, ``valid`` bool (H, W),
    ``amplitude`` float32 (H, W) in its own units (0 where not finite, the network's input) or None, and
    ``amplitude_valid`` bool (H, W): where the amplitude was finite (None: everywhere). The sigma_D map is NaN
    (invalid) where the amplitude is not valid (``outputs.frame_sigma``)."""

    depth_mm: np.ndarray
    valid: np.ndarray
    amplitude: np.ndarray | None = None
    name: str = ""
    amplitude_valid: np.ndarray | None = None


def _is_candidate(path: Path) -> bool:
    return path.is_file() and not path.name.startswith(".") and path.suffix.lower() in DEPTH_FRAME_SUFFIXES


def find_frames(inputs: Sequence[str | Path], exclude: Iterable[str | Path] = ()) -> list[FrameInput]:
    """Depth frames of ``inputs`` (files, or folders searched recursively), in a stable order; files under any
    ``exclude`` folder (e.g. the output folder) are left out. Missing inputs are an error."""
    excluded = [Path(e).expanduser().resolve() for e in exclude]

    def skipped(path: Path) -> bool:
        resolved = path.resolve()
        return any(resolved == e or e in resolved.parents for e in excluded)

    frames: list[FrameInput] = []
    for item in inputs:
        root = Path(item).expanduser()
        if root.is_dir():
            found = sorted(
                p
                for p in root.rglob("*")
                if _is_candidate(p)
                and not skipped(p)
                and not any(part.startswith(".") for part in p.relative_to(root).parts)
            )
            frames += [FrameInput(p, p.relative_to(root)) for p in found]
        elif root.is_file():
            if root.suffix.lower() in RECORDING_SUFFIXES:
                continue  # a recording: inference.recordings.find_recordings
            if root.suffix.lower() not in DEPTH_FRAME_SUFFIXES:
                raise FrameError(
                    f"input file {root} has suffix {root.suffix!r}; expected a depth frame "
                    f"({', '.join(DEPTH_FRAME_SUFFIXES)}) or a recording ({', '.join(RECORDING_SUFFIXES)}, a ROS 2 "
                    "bag folder)"
                )
            frames.append(FrameInput(root, Path(root.name)))
        else:
            raise FrameError(f"input not found: {root} (expected a depth frame or a folder of them)")
    return frames


def read_depth_frame(path: str | Path, depth_scale_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(depth_mm float32 with 0 at invalid pixels, valid bool) of one depth frame; see the module docstring."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in DEPTH_FRAME_SUFFIXES:
        raise FrameError(f"depth file {path} has suffix {suffix!r}; expected one of {', '.join(DEPTH_FRAME_SUFFIXES)}")
    if not depth_scale_mm > 0:
        raise FrameError(f"depth scale must be > 0 mm per stored unit, got {depth_scale_mm}")
    try:
        if suffix in (".png", ".tif", ".tiff"):
            image = read_image(path, what="depth", allowed_dtypes=(np.uint8, np.uint16, np.float32))
            if image.dtype == np.uint8:
                raise FrameError(
                    f"depth file {path} is an 8-bit image: it cannot hold depth in millimetres; "
                    "expected a single-channel 16-bit PNG (mm, 0 = invalid), .npy or .exr"
                )
            raw = image
        else:
            raw = read_array(path, what="depth")
            refuse_8bit_depth(raw, path)  # a uint8/int8 .npy is no depth in mm either
    except DataFileError as exc:
        raise FrameError(str(exc)) from exc
    except OSError as exc:
        raise FrameError(f"depth file {path} could not be read: {exc}") from exc
    if raw.dtype == np.bool_:
        raise FrameError(f"depth file {path} is boolean; expected depth values")
    return depth_values_mm(
        raw,
        depth_scale_mm,
        f"depth file {path}",
        f"taken with --depth-scale-mm {float(depth_scale_mm):g}",
        "check the file's units (--depth-scale-mm) and mark invalid pixels 0 or NaN",
    )


def depth_values_mm(
    values: np.ndarray, mm_per_unit: float, what: str, units: str, advice: str
) -> tuple[np.ndarray, np.ndarray]:
    """(depth_mm float32 with 0 at invalid pixels, valid bool) of stored depth ``values`` times ``mm_per_unit``
    (computed in float64): NaN, inf, 0 and negative values are invalid, and a valid depth beyond ``PNG16_MAX_MM``
    is a ``FrameError`` naming ``what`` (the file or the recording's frame), the count and the largest, the
    ``units`` it was taken in and the ``advice``. The one rule of frame files and recordings (a 32FC1 "no return"
    coded as FLT_MAX metres is refused here, not cast to an infinite valid depth)."""
    depth = np.asarray(values).astype(np.float64) * float(mm_per_unit)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
        beyond = valid & (depth > PNG16_MAX_MM)
    if beyond.any():
        raise FrameError(
            f"{what}: {int(beyond.sum())} valid pixel(s) deeper than {PNG16_MAX_MM} mm (the largest "
            f"{float(depth[beyond].max()):.4g} mm, {units}); no time-of-flight camera measures that far and a "
            f"16-bit millimetre PNG cannot hold it: {advice}"
        )
    return np.where(valid, depth, 0.0).astype(np.float32), valid


def checked_amplitude(
    amplitude: np.ndarray, depth_mm: np.ndarray, valid: np.ndarray, what: str, depth_what: str
) -> tuple[np.ndarray, np.ndarray]:
    """(amplitude float32 with 0 where it is not finite, amplitude_valid bool) of a depth frame's amplitude, or a
    ``FrameError`` naming ``what`` (the amplitude file / message) and ``depth_what`` (its depth frame) when its
    shape differs from the depth's or it holds no finite value at any pixel of valid depth (an IR stream dropped
    and saved as float NaN: a sigma_D map from it would be plausible and wrong). The one check of frame files,
    recordings and ``tofdenoise.denoise``."""
    amp = np.asarray(amplitude)
    if amp.shape != depth_mm.shape:
        raise FrameError(f"{what} has shape {amp.shape}; expected {depth_mm.shape} like its {depth_what}")
    amp_valid = np.isfinite(amp)
    if valid.any() and not (amp_valid & valid).any():
        raise FrameError(
            f"{what} (for {depth_what}) holds no finite value where the depth is valid ({int((~amp_valid).sum())} "
            f"of {amp.size} values are NaN or inf); expected the frame's amplitude: a sigma_D map or the network's "
            "signal channel cannot come from it"
        )
    return np.where(amp_valid, amp, 0.0).astype(np.float32), amp_valid


def make_frame(
    depth_mm: np.ndarray,
    valid: np.ndarray,
    amplitude: np.ndarray | None,
    name: str,
    amplitude_what: str = "amplitude",
    depth_what: str = "depth frame",
) -> Frame:
    """A ``Frame`` of a depth map (``depth_values_mm``) and its amplitude or None (``checked_amplitude``): how frame
    files (``load_frame``) and recordings (``RecordingFrame.frame``) become the frames the command restores."""
    amp_valid = None
    if amplitude is not None:
        amplitude, amp_valid = checked_amplitude(amplitude, depth_mm, valid, amplitude_what, depth_what)
    return Frame(depth_mm=depth_mm, valid=valid, amplitude=amplitude, name=name, amplitude_valid=amp_valid)


#: a template's stem field: ``{stem}`` or ``{stem:OLD=NEW}`` (OLD non-empty; neither holds ``{``, ``}``, ``=`` or ``/``)
_STEM_FIELD = re.compile(r"\{stem(?::(?P<old>[^{}=/]+)=(?P<new>[^{}=/]*))?\}")


class AmplitudeSource:
    """Where amplitude frames are found: a folder, a ``{stem}`` / ``{stem:OLD=NEW}`` template or a glob pattern
    (module docstring)."""

    def __init__(self, spec: str | Path):
        self.spec = str(spec)
        path = Path(self.spec).expanduser()
        self.folder: Path | None = path if path.is_dir() else None
        self.template = None
        if self.folder is None and "{stem" in self.spec:
            if "{stem" in _STEM_FIELD.sub("", self.spec):
                raise FrameError(
                    f"--amplitude {self.spec}: a stem field is {{stem}} or {{stem:OLD=NEW}} (the stem with OLD "
                    "replaced by NEW, e.g. 'adi/{stem:depth=ab}.npy'; OLD and NEW without {, }, = or /)"
                )
            self.template = self.spec
        self.by_stem: dict[str, list[Path]] | None = None
        if self.folder is None and self.template is None:
            if not _glob.has_magic(self.spec):
                raise FrameError(
                    f"--amplitude {self.spec}: not a folder, a template with {{stem}} or {{stem:OLD=NEW}}, or a glob "
                    "pattern"
                )
            self.by_stem = {}
            for match in sorted(_glob.glob(str(path), recursive=True)):
                p = Path(match)
                if p.is_file() and p.suffix.lower() in AMPLITUDE_SUFFIXES:
                    self.by_stem.setdefault(p.stem, []).append(p)
            if not self.by_stem:
                raise FrameError(f"--amplitude {self.spec}: the pattern matches no amplitude file")

    def _fill(self, frame: FrameInput) -> Path:
        """The template with every stem field of it filled for ``frame``."""
        assert self.template is not None
        stem = frame.path.stem

        def field(match: re.Match[str]) -> str:
            old, new = match.group("old"), match.group("new")
            if old is None:
                return stem
            count = stem.count(old)
            if count != 1:
                raise FrameError(
                    f"no amplitude file for depth frame {frame.path}: {{stem:{old}={new}}} needs {old!r} once in "
                    f"the stem {stem!r}, found {count} time(s) (write a longer OLD, e.g. {{stem:_{old}_=_{new}_}})"
                )
            return stem.replace(old, new)

        return Path(_STEM_FIELD.sub(field, self.template)).expanduser()

    def find(self, frame: FrameInput) -> Path:
        """The amplitude file of ``frame``; FrameError when there is none or more than one."""
        stem = frame.path.stem
        if self.template is not None:
            candidate = self._fill(frame)
            if candidate.is_file() and candidate.resolve() == frame.path.resolve():
                raise FrameError(
                    f"--amplitude {self.spec} gives depth frame {frame.path} itself as its amplitude; the "
                    "template must name another file (e.g. {stem:depth=ab})"
                )
            if candidate.is_file():
                return candidate
            raise FrameError(f"no amplitude file for depth frame {frame.path}: {candidate} does not exist")
        if self.by_stem is not None:
            found = self.by_stem.get(stem, [])
            where = f"files matching {self.spec}"
        else:
            assert self.folder is not None
            found = []
            for folder in (self.folder / frame.rel.parent, self.folder):
                found = [
                    p
                    for p in sorted(folder.glob(f"{_glob.escape(stem)}.*"))
                    if p.is_file() and p.suffix.lower() in AMPLITUDE_SUFFIXES and p.resolve() != frame.path.resolve()
                ]
                if found:
                    break
            where = f"{self.folder} (and {self.folder / frame.rel.parent})"
        if not found:
            raise FrameError(
                f"no amplitude file for depth frame {frame.path}: expected {stem}.<"
                f"{'|'.join(s.lstrip('.') for s in AMPLITUDE_SUFFIXES)}> in {where}"
            )
        if len(found) > 1:
            raise FrameError(
                f"depth frame {frame.path} has {len(found)} amplitude candidates: "
                f"{', '.join(str(p) for p in found)}; keep one"
            )
        return found[0]


def drop_amplitude_files(frames: Sequence[FrameInput], amplitude: AmplitudeSource | None) -> list[FrameInput]:
    """``frames`` without the files that are the amplitude of one of them: a camera that writes depth and amplitude
    into one folder (``frame_mode2_depth_000123.npy``, ``frame_mode2_ab_000123.npy``) gives both as inputs."""
    if amplitude is None:
        return list(frames)
    paired = set()
    for frame in frames:
        try:
            paired.add(amplitude.find(frame).resolve())
        except FrameError:  # reported for that frame when it is processed
            pass
    return [frame for frame in frames if frame.path.resolve() not in paired]


def load_frame(frame: FrameInput, depth_scale_mm: float = 1.0, amplitude: AmplitudeSource | None = None) -> Frame:
    """Read a depth frame and (when ``amplitude`` is given) its paired amplitude frame of the same shape."""
    depth, valid = read_depth_frame(frame.path, depth_scale_mm)
    amp, amp_path = None, None
    if amplitude is not None:
        amp_path = amplitude.find(frame)
        try:
            amp = read_amplitude(amp_path)
        except (DataFileError, OSError) as exc:
            raise FrameError(
                f"amplitude file {amp_path} (for depth frame {frame.path}) could not be read: {exc}"
            ) from exc
    return make_frame(
        depth, valid, amp, frame.rel_stem.as_posix(), f"amplitude file {amp_path}", f"depth frame {frame.path}"
    )


def plausible_depth_range_mm(calib: Any = None) -> tuple[float, float]:
    """(nearest, farthest) median valid depth [mm] that ``check_depth_units_mm`` takes as millimetres: the nearest
    depth of the training scenes (``DEFAULT_MIN_DEPTH_MM``) and the unambiguous range of ``calib`` (a
    ``SensorCalibration``; None: the default calibration), beyond which the sensor measures no depth."""
    from tofdenoise.data_modules.sources.procedural import DEFAULT_MIN_DEPTH_MM
    from tofdenoise.physics.calibration import default_calibration

    calib = default_calibration() if calib is None else calib
    return DEFAULT_MIN_DEPTH_MM, float(calib.unambiguous_range_mm)


def check_depth_units_mm(
    frame: Frame,
    path: str | Path,
    depth_range_mm: tuple[float, float] | None = None,
    option: str = "--depth-scale-mm ",
) -> None:
    """FrameError naming the median, the likely unit and ``--depth-scale-mm`` when the frame's valid depths lie
    mostly outside ``depth_range_mm`` (``plausible_depth_range_mm()`` by default): their median below its nearest
    or beyond its farthest depth, i.e. more than half of them out of the range on that side. Implausible in
    millimetres: a depth map in metres or centimetres, or one counting 0.1 mm. ``option``: the setting that gives
    the units, as written before its value (the command's ``--depth-scale-mm ``; the API's ``depth_scale_mm=``)."""
    if not frame.valid.any():
        return
    near, far = plausible_depth_range_mm() if depth_range_mm is None else depth_range_mm
    median_mm = float(np.median(frame.depth_mm[frame.valid]))
    if near <= median_mm <= far:
        return
    side = "nearer than" if median_mm < near else "beyond"
    bound = near if median_mm < near else far
    likely = [(scale, name) for scale, name in LIKELY_UNITS if near <= median_mm * scale <= far]
    given = option.rstrip(" =")  # the setting's name, without the separator before its value
    if likely:
        scale, name = likely[0]
        hint = f"looks like {name}: pass {option}{scale:g}"
    else:
        hint = f"give the file's units with {given} (e.g. 1000 for metres, 10 for cm, 0.1 for 0.1 mm units)"
    raise FrameError(
        f"depth file {path}: median valid depth {median_mm:.4g} is implausible in millimetres (more than half of "
        f"the valid depths lie {side} {bound:.0f} mm; taken as mm: {near:.0f} mm, the training scenes' nearest "
        f"depth, to {far:.0f} mm, the sensor's unambiguous range); {hint} ({option}1 if it is mm)"
    )


def outside_training_depths(frame: Frame, range_mm: tuple[float, float] | None) -> str | None:
    """A one-line note when more than half of the frame's valid depths lie outside ``range_mm``, the (nearest,
    farthest) depths the checkpoint was trained on; None otherwise (or when the range is unknown)."""
    from tofdenoise.training.depth_range import outside_fraction

    if range_mm is None or not frame.valid.any():
        return None
    share = outside_fraction(frame.depth_mm, frame.valid, range_mm)
    if share <= 0.5:
        return None
    values = frame.depth_mm[frame.valid]
    low, high = range_mm
    return (
        f"{100 * share:.0f} % of its valid depths ({float(values.min()):.0f}-{float(values.max()):.0f} mm, median "
        f"{float(np.median(values)):.0f} mm) lie outside {low:.0f}-{high:.0f} mm, the depths the checkpoint was "
        "trained on: its restoration there is an extrapolation"
    )
