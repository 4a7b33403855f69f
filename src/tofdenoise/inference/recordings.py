"""Camera recordings as frame sources: Azure Kinect ``.mkv`` files and ROS 1 / ROS 2 bags.

- **Azure Kinect** (``.mkv``, read with PyAV): Matroska with a ``DEPTH`` and an ``IR`` video track (track title,
  or the ``K4A_DEPTH_TRACK`` / ``K4A_IR_TRACK`` tags), both raw 16-bit grey with the FourCC ``b16g``: **big-endian**
  samples (read as little-endian they are nonsense). Depth in mm, 0 = invalid; the IR frame of the same timestamp
  is the amplitude. The recorder attaches ``calibration.json``: the depth camera's intrinsics
  (``camera.kinect_depth_intrinsics``, for the track's ``K4A_DEPTH_MODE``). Each packet is read as raw bytes and
  must hold exactly width x height samples.
- **ROS 1 ``.bag`` / ROS 2 bag folders** (``metadata.yaml`` + ``.db3`` / ``.mcap``, read with ``rosbags``):
  ``sensor_msgs/Image`` depth topics in ``16UC1`` / ``mono16`` (mm, 0 = invalid) or ``32FC1`` (metres, NaN /
  0 = invalid: ROS REP 118), with an amplitude / IR image topic paired by ``header.stamp``; the
  ``sensor_msgs/CameraInfo`` topic of the depth topic's namespace (ROS's ``<ns>/camera_info`` beside
  ``<ns>/image_raw``) gives the intrinsics (its ``K``); a CameraInfo of another namespace (another camera) is never
  used.

Every depth message / packet is one frame (``index`` 0, 1, ... in recording order), whatever its timestamp. An
amplitude frame is paired with a depth frame only where that is unambiguous: exactly one depth and one amplitude
frame of the same timestamp, of the same size. A depth frame without one (none of its stamp, a stamp shared by
several frames, another size) has ``amplitude`` None and ``no_amplitude`` saying why; ``notes`` names shared stamps.
Opened with ``use_amplitude=False`` (a model and options that do not use it), the amplitude stream is not read at
all. The intrinsics (``intrinsics``) are read when first asked for, so an uncalibrated CameraInfo (K all zero)
matters only to a point cloud that needs it.

A frame's depth is kept as recorded (``RecordingFrame.depth``: 16-bit mm or 32FC1 metres) and becomes millimetres
by the rule of frame files (``frames.depth_values_mm``: NaN, inf, 0 and negative invalid; a valid depth beyond
65535 mm fails that frame); ``RecordingFrame.frame`` checks its amplitude as a frame file's
(``frames.checked_amplitude``).

Streams are chosen by name (``depth`` / ``amplitude``: a bag topic or a Matroska track title); by default the
depth stream is the Kinect's ``DEPTH`` track or the first image topic (sorted by name) with ``depth`` in its name,
and the amplitude the ``IR`` track or the first image topic named like ``ir`` / ``amplitude`` / ``intensity``.
A stream asked for (or expected) and absent is a ``RecordingError`` listing the streams the recording has.

``Recording.scan()`` reads the whole recording once without keeping frames and checks it (the Matroska segment
as long as its declared size and the last frame at the recorded duration: FFmpeg reads a truncated ``.mkv`` to its
end without an error; every packet complete; a damaged bag index or database; every message decodable):
the commands call it before they write anything for a recording, so a bad recording writes nothing. It also
pairs the amplitude (every amplitude message read, its size checked against its depth frame's), so which frames
have no usable amplitude is known before the first frame is written.

PyAV and rosbags are the optional extra ``recordings`` (``pip install 'tofdenoise[recordings]'``); without them a
recording is refused with an error naming the extra.
"""

from __future__ import annotations

import importlib
import re
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.inference.camera import Intrinsics, IntrinsicsError, kinect_depth_intrinsics, kinect_mode_for_size
from tofdenoise.inference.frames import RECORDING_SUFFIXES, Frame, FrameError, depth_values_mm, make_frame
from tofdenoise.inference.ros_codecs import CompressedImageError, decode_compressed_image, parse_compressed_format

__all__ = [
    "RECORDING_SUFFIXES",
    "Recording",
    "RecordingError",
    "RecordingFrame",
    "RecordingInput",
    "camera_info_topic",
    "find_recordings",
    "image_message_to_array",
    "is_recording",
    "open_recording",
]

EXTRA_HINT = "pip install 'tofdenoise[recordings]' (make venv installs it)"

_AMPLITUDE_NAME = re.compile(r"(^|[/_.\-])(ir|amplitude|intensity|ab|active_brightness)([/_.\-]|$)", re.IGNORECASE)
_TRANSPORT_SUFFIX = re.compile(r"/(compressed|compressedDepth)$")  # image_transport's topic of a compressed form
_DEPTH_ENCODINGS = {"16UC1": "mm", "mono16": "mm", "32FC1": "m"}
_IMAGE_DTYPES = {
    "16UC1": np.uint16,
    "mono16": np.uint16,
    "32FC1": np.float32,
    "8UC1": np.uint8,
    "mono8": np.uint8,
}


class RecordingError(FrameError):
    """A recording cannot be read as asked; the message names the file and what was expected."""


@dataclass(frozen=True)
class RecordingInput:
    """A recording on disk and its output name (``rel``: relative to the input folder, or its own name)."""

    path: Path
    rel: Path

    @property
    def rel_stem(self) -> Path:
        return self.rel.with_suffix("") if self.path.is_file() else self.rel


#: what a depth beyond 65535 mm in a recording is told to be (``frames.depth_values_mm``)
_RANGE_ADVICE = "a ROS depth image marks no depth with NaN or 0 (REP 118), not with a far value"


@dataclass
class RecordingFrame:
    """One frame of a recording: ``index`` (0, 1, ... in recording order), ``stamp_ns`` (its timestamp: the
    header stamp of a bag message, the Kinect's device timestamp), ``depth`` as recorded (uint16 mm, or float32
    metres with ``mm_per_unit`` 1000), ``where`` (names the frame in messages), ``amplitude`` float32 as recorded
    (NaN kept) or None, ``no_amplitude`` (why there is none, when the amplitude stream was read), ``frame_id``
    (a bag message's ``header.frame_id``; "" for a Kinect recording).

    ``depth_mm`` (float32, 0 at invalid pixels) and ``valid`` follow the frame files' rule
    (``frames.depth_values_mm``; a ``RecordingError`` for a depth beyond 65535 mm); ``frame(name)`` is the
    ``frames.Frame`` the command restores, its amplitude checked as a frame file's."""

    index: int
    stamp_ns: int
    depth: np.ndarray
    mm_per_unit: float = 1.0
    where: str = ""
    amplitude: np.ndarray | None = None
    amplitude_where: str = "amplitude"
    no_amplitude: str = ""
    frame_id: str = ""
    _mm: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False, compare=False)

    def _depth_mm_valid(self) -> tuple[np.ndarray, np.ndarray]:
        if self._mm is None:
            units = "32FC1 metres x 1000" if self.mm_per_unit != 1 else "as millimetres"
            try:
                self._mm = depth_values_mm(self.depth, self.mm_per_unit, self.where, units, _RANGE_ADVICE)
            except FrameError as exc:
                raise RecordingError(str(exc)) from None
        return self._mm

    @property
    def depth_mm(self) -> np.ndarray:
        return self._depth_mm_valid()[0]

    @property
    def valid(self) -> np.ndarray:
        return self._depth_mm_valid()[1]

    def frame(self, name: str, amplitude: bool = True) -> Frame:
        """The ``frames.Frame`` of this frame (``frames.make_frame``, as a frame file becomes one), with its
        amplitude unless ``amplitude`` is False; ``FrameError`` for a depth beyond 65535 mm, or an amplitude of
        another shape or without a finite value where the depth is valid."""
        depth_mm, valid = self._depth_mm_valid()
        amp = self.amplitude if amplitude else None
        return make_frame(depth_mm, valid, amp, name, self.amplitude_where, self.where)


def is_recording(path: str | Path) -> bool:
    """A ``.mkv`` / ``.bag`` file or a ROS 2 bag folder (one holding ``metadata.yaml``)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in RECORDING_SUFFIXES


def find_recordings(inputs: Sequence[str | Path], exclude: Iterable[str | Path] = ()) -> list[RecordingInput]:
    """Recordings among ``inputs`` (files, ROS 2 bag folders, or folders searched recursively), stable order; those
    under an ``exclude`` folder are left out."""
    excluded = [Path(e).expanduser().resolve() for e in exclude]

    def skipped(path: Path) -> bool:
        resolved = path.resolve()
        return any(resolved == e or e in resolved.parents for e in excluded)

    found: list[RecordingInput] = []
    for item in inputs:
        root = Path(item).expanduser()
        if is_recording(root) and (root.is_file() or root.is_dir()):
            found.append(RecordingInput(root, Path(root.name)))
        elif root.is_dir():
            for p in sorted(root.rglob("*")):
                rel = p.relative_to(root)
                if any(part.startswith(".") for part in rel.parts) or skipped(p) or not is_recording(p):
                    continue
                if any(is_recording(parent) for parent in p.parents if parent != root and root in parent.parents):
                    continue  # a file inside a ROS 2 bag folder
                if p.is_file() or p.is_dir():
                    found.append(RecordingInput(p, rel))
    return found


def _import(module: str, path: Path) -> Any:

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise RecordingError(
            f"recording {path}: reading it needs the package {module.split('.')[0]!r} ({exc}); {EXTRA_HINT}"
        ) from exc


class Recording(ABC):
    """A recording opened for reading (``open_recording``): ``depth_name``, ``amplitude_name`` (or None: none, or
    not read), ``intrinsics`` (or None; read when first asked for), ``scan()`` -> frame count, ``frames()`` ->
    ``RecordingFrame`` in order. After ``scan()``: ``no_amplitude`` (frame index -> why it has no amplitude, when
    the amplitude stream is read) and ``notes`` (warnings: stamps shared by several frames)."""

    path: Path
    depth_name: str
    amplitude_name: str | None
    #: every image stream of the recording (Kinect tracks, bag image topics), for messages that list them
    stream_names: list[str]
    #: after ``scan()``: depth frame index -> why it has no amplitude (only when the amplitude stream is read)
    no_amplitude: dict[int, str]
    #: after ``scan()``: warnings about the recording (stamps shared by several frames)
    notes: list[str]
    _link: dict[int, int] | None = None

    @property
    @abstractmethod
    def intrinsics(self) -> Intrinsics | None:
        """The depth camera's intrinsics the recording carries (None: none); read when first asked for, a
        ``RecordingError`` when they are there but unusable (a CameraInfo with K all zero)."""

    @abstractmethod
    def intrinsics_absent(self) -> str:
        """Why ``intrinsics`` is None, naming what was looked for and what the recording has."""

    @abstractmethod
    def scan(self) -> int:
        """Read the whole recording once without keeping frames; the depth frame count, or ``RecordingError``."""

    @abstractmethod
    def frames(self) -> Iterator[RecordingFrame]:
        """Every depth frame, in recording order (with its amplitude where it is paired unambiguously)."""

    def describe(self) -> str:
        amp = self.amplitude_name or "none"
        return f"{self.path}: depth {self.depth_name}, amplitude {amp}"

    def _paired(
        self,
        depth_stamps: Sequence[int],
        depth_shapes: Sequence[tuple[int, ...]],
        amp_stamps: Sequence[int],
        amp_shapes: Sequence[tuple[int, ...]],
    ) -> None:
        """Pair the amplitude with the depth frames by timestamp where that is unambiguous (module docstring):
        sets ``_link`` (depth index -> amplitude ordinal), ``no_amplitude`` and ``notes``."""
        depth_count, amp_count = Counter(depth_stamps), Counter(amp_stamps)
        self._link, self.no_amplitude, self.notes = {}, {}, []
        amp = self.amplitude_name
        if amp is not None:
            only = {stamp: j for j, stamp in enumerate(amp_stamps) if amp_count[stamp] == 1}
            for i, stamp in enumerate(depth_stamps):
                nd, na = depth_count[stamp], amp_count[stamp]
                if na == 0:
                    self.no_amplitude[i] = f"no amplitude frame of its timestamp ({stamp} ns) in {amp}"
                elif nd > 1 or na > 1:
                    self.no_amplitude[i] = (
                        f"its timestamp {stamp} ns is shared by {nd} depth and {na} amplitude frame(s) of {amp}: "
                        "which amplitude is its own is ambiguous"
                    )
                elif tuple(amp_shapes[only[stamp]]) != tuple(depth_shapes[i]):
                    (ah, aw), (dh, dw) = amp_shapes[only[stamp]][-2:], depth_shapes[i][-2:]
                    self.no_amplitude[i] = (
                        f"the amplitude frame of its timestamp ({stamp} ns) in {amp} is {aw} x {ah} pixels; expected "
                        f"{dw} x {dh} like its depth"
                    )
                else:
                    self._link[i] = only[stamp]
        shared = sorted(stamp for stamp, n in depth_count.items() if n > 1)
        amp_shared = sorted(stamp for stamp, n in amp_count.items() if n > 1) if amp is not None else []
        if shared or amp_shared:
            parts = []
            if shared:
                n = sum(depth_count[stamp] for stamp in shared)
                parts.append(
                    f"{n} of its {len(depth_stamps)} depth frames share a timestamp with another ({len(shared)} "
                    f"timestamp(s), the first {shared[0]} ns on {depth_count[shared[0]]} frames)"
                )
            if amp_shared:
                n = sum(amp_count[stamp] for stamp in amp_shared)
                parts.append(f"{n} amplitude frames of {amp} share a timestamp with another")
            ambiguous = sum(1 for why in self.no_amplitude.values() if "ambiguous" in why)
            tail = "every depth frame is kept, in recording order"
            if ambiguous:
                tail += f"; {ambiguous} of them get no amplitude (which one is theirs is ambiguous)"
            self.notes.append(f"recording {self.path}: {'; '.join(parts)}: {tail}")

    def _amplitude_link(self) -> dict[int, int]:
        """depth index -> amplitude ordinal (``scan()`` first when it has not run); {} without an amplitude."""
        if self.amplitude_name is None:
            return {}
        if self._link is None:
            self.scan()
        assert self._link is not None
        return self._link


def _with_amplitude(
    depth_items: Iterable[Any], amp_items: Iterable[Any], link: dict[int, int]
) -> Iterator[tuple[int, Any, Any]]:
    """(index, depth item, its amplitude item or None) in depth order, the amplitude items of ``link`` (depth index
    -> amplitude ordinal) taken from their own stream: those read ahead of their depth wait in memory (as many as
    the streams are out of step), the others are passed over."""
    wanted = set(link.values())
    waiting: dict[int, Any] = {}
    amp_iter = enumerate(amp_items)
    exhausted = not link
    for index, item in enumerate(depth_items):
        ordinal = link.get(index)
        amp = None
        if ordinal is not None:
            while ordinal not in waiting and not exhausted:
                nxt = next(amp_iter, None)
                if nxt is None:
                    exhausted = True
                elif nxt[0] in wanted:
                    waiting[nxt[0]] = nxt[1]
            amp = waiting.pop(ordinal, None)
        yield index, item, amp


def open_recording(
    path: str | Path, depth: str | None = None, amplitude: str | None = None, use_amplitude: bool = True
) -> Recording:
    """The recording at ``path`` with its depth (and amplitude) stream chosen (module docstring);
    ``use_amplitude=False``: the amplitude stream is not read (an ``amplitude`` named must still exist)."""
    path = Path(path).expanduser()
    if not path.exists():
        raise RecordingError(f"recording not found: {path}")
    if path.is_file() and path.suffix.lower() == ".mkv":
        return KinectRecording(path, depth, amplitude, use_amplitude)
    if is_recording(path):
        return BagRecording(path, depth, amplitude, use_amplitude)
    raise RecordingError(f"{path} is not a recording: expected a .mkv file, a ROS 1 .bag or a ROS 2 bag folder")


def _choose(names: Sequence[str], asked: str | None, default: str | None, what: str, option: str, path: Path) -> str:
    listing = ", ".join(names) if names else "none"
    if asked is not None:
        if asked not in names:
            raise RecordingError(f"recording {path} has no {what} stream {asked!r} ({option}); it has: {listing}")
        return asked
    if default is None:
        raise RecordingError(f"recording {path}: no {what} stream found; it has: {listing}; choose one with {option}")
    return default


# ----------------------------------------------------------------------------------------------- Azure Kinect .mkv
def _ebml_vint(data: bytes, pos: int, keep_marker: bool) -> tuple[int | None, int]:
    """(value, next position) of the EBML variable-length integer at ``pos``; value None for an unknown size
    (all value bits set) or when ``data`` ends inside it."""
    if pos >= len(data) or data[pos] == 0:
        return None, len(data)
    length = 8 - data[pos].bit_length() + 1
    if pos + length > len(data):
        return None, len(data)
    value = int.from_bytes(data[pos : pos + length], "big")
    if keep_marker:
        return value, pos + length
    value &= (1 << (7 * length)) - 1
    return (None if value == (1 << (7 * length)) - 1 else value), pos + length


def matroska_missing_bytes(path: str | Path) -> int:
    """How many bytes the Matroska Segment of ``path`` declares beyond the end of the file (0 when complete, or
    when the size is unknown, as a live recording leaves it): a recorder writes the size when it closes the file,
    so a copy cut short misses them. FFmpeg's demuxer reads such a file to its end without an error."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(4096)
    pos = 0
    for expected in (0x1A45DFA3, 0x18538067):  # EBML header, then Segment
        element, pos = _ebml_vint(head, pos, keep_marker=True)
        size, pos = _ebml_vint(head, pos, keep_marker=False)
        if element != expected or size is None:
            return 0
        if expected == 0x1A45DFA3:
            pos += size
    return max(0, pos + size - path.stat().st_size)


def _track_name(stream: Any) -> str:
    meta = {k.upper(): v for k, v in dict(stream.metadata).items()}
    if "K4A_DEPTH_TRACK" in meta:
        return "DEPTH"
    if "K4A_IR_TRACK" in meta:
        return "IR"
    return str(meta.get("TITLE", f"track{stream.index}"))


class KinectRecording(Recording):
    """An Azure Kinect recording (module docstring)."""

    def __init__(self, path: Path, depth: str | None = None, amplitude: str | None = None, use_amplitude: bool = True):
        self.path = path
        self.no_amplitude, self.notes = {}, []
        self._av = _import("av", path)
        with self._open() as container:
            tracks = {_track_name(s): s for s in container.streams.video}
            names = list(tracks)
            self.stream_names = names
            self.depth_name = _choose(
                names, depth, "DEPTH" if "DEPTH" in tracks else None, "depth", "--depth-stream", path
            )
            if amplitude is not None:
                self.amplitude_name = _choose(names, amplitude, None, "amplitude", "--amplitude-stream", path)
            else:
                self.amplitude_name = "IR" if "IR" in tracks and self.depth_name != "IR" else None
            if not use_amplitude:
                self.amplitude_name = None
            self._layout = {name: self._sample_layout(tracks[name]) for name in self._names()}
            self._duration = container.duration
            stream = tracks[self.depth_name]
            meta = {k.upper(): v for k, v in dict(stream.metadata).items()}
            self.depth_mode = meta.get("K4A_DEPTH_MODE")
            calibration = [a for a in container.streams.attachments if a.name == "calibration.json"]
            self._calibration = bytes(calibration[0].data) if calibration else None
        self._intrinsics: Intrinsics | None = None

    @property
    def intrinsics(self) -> Intrinsics | None:
        if self._calibration is None:
            return None
        if self._intrinsics is None:
            mode = self.depth_mode or kinect_mode_for_size(*self._layout[self.depth_name][1:])
            try:
                self._intrinsics = kinect_depth_intrinsics(self._calibration, mode, str(self.path))
            except IntrinsicsError as exc:
                raise RecordingError(str(exc)) from exc
        return self._intrinsics

    def intrinsics_absent(self) -> str:
        return "no calibration.json attachment"

    def _names(self) -> list[str]:
        return [self.depth_name] + ([self.amplitude_name] if self.amplitude_name else [])

    def _open(self):
        try:
            return self._av.open(str(self.path))
        except self._av.FFmpegError as exc:
            raise RecordingError(f"recording {self.path} could not be opened as Matroska: {exc}") from exc

    def _sample_layout(self, stream: Any) -> tuple[np.dtype, int, int]:
        ctx = stream.codec_context
        tag = str(ctx.codec_tag)
        if ctx.name != "rawvideo" or tag not in ("b16g", "b16G") and ctx.pix_fmt not in ("gray16be", "gray16le"):
            raise RecordingError(
                f"recording {self.path}: track {_track_name(stream)} is {ctx.name} (FourCC {tag!r}, {ctx.pix_fmt}); "
                "expected raw 16-bit grey (FourCC b16g, big-endian) as the Azure Kinect records depth and IR"
            )
        dtype = np.dtype("<u2") if ctx.pix_fmt == "gray16le" and tag not in ("b16g", "b16G") else np.dtype(">u2")
        return dtype, int(ctx.width), int(ctx.height)

    def _packets(self, container: Any, name: str) -> Iterator[tuple[int, bytes | None, int]]:
        """(stamp_ns, payload, frame duration ns) of a track's packets in order (payload None: scan only)."""
        stream = {_track_name(s): s for s in container.streams.video}[name]
        try:
            for packet in container.demux(stream):
                if packet.size == 0 or packet.pts is None:
                    continue
                base = Fraction(packet.time_base)
                stamp = int(packet.pts * base * 1_000_000_000)
                duration = int((packet.duration or 0) * base * 1_000_000_000)
                yield stamp, bytes(packet), duration
        except self._av.FFmpegError as exc:
            raise RecordingError(f"recording {self.path}: track {name} could not be read: {exc}") from exc

    def _array(self, name: str, payload: bytes, index: int) -> np.ndarray:
        dtype, width, height = self._layout[name]
        if len(payload) != width * height * 2:
            raise RecordingError(
                f"recording {self.path}: frame {index} of track {name} holds {len(payload)} bytes; expected "
                f"{width * height * 2} ({width} x {height} 16-bit samples): the file is damaged or truncated"
            )
        return np.frombuffer(payload, dtype=dtype).reshape(height, width).astype(np.uint16)

    def _shape(self, name: str) -> tuple[int, int]:
        _, width, height = self._layout[name]
        return height, width

    def scan(self) -> int:
        missing = matroska_missing_bytes(self.path)
        if missing:
            raise RecordingError(
                f"recording {self.path} is truncated: its Matroska segment declares {missing} more bytes than the "
                "file holds"
            )
        count, last_end, duration = 0, 0, 0
        stamps: list[int] = []
        with self._open() as container:
            for stamp, payload, duration in self._packets(container, self.depth_name):
                self._array(self.depth_name, payload, count)
                stamps.append(stamp)
                count += 1
                last_end = stamp + duration
        if count == 0:
            raise RecordingError(f"recording {self.path}: track {self.depth_name} holds no frame (empty or truncated)")
        if self._duration:  # container duration [us], written when the recorder closed the file (all tracks)
            total_ns = int(self._duration) * 1000
            if last_end < total_ns - 2 * max(duration, 1_000_000) - 10_000_000:
                raise RecordingError(
                    f"recording {self.path} is truncated: track {self.depth_name} ends at {last_end / 1e9:.3f} s of "
                    f"its recorded {total_ns / 1e9:.3f} s ({count} complete frames)"
                )
        amp_stamps: list[int] = []
        if self.amplitude_name is not None:
            with self._open() as container:
                for stamp, payload, _ in self._packets(container, self.amplitude_name):
                    self._array(self.amplitude_name, payload, len(amp_stamps))
                    amp_stamps.append(stamp)
        depth_shape = self._shape(self.depth_name)
        amp_shape = self._shape(self.amplitude_name) if self.amplitude_name else depth_shape
        self._paired(stamps, [depth_shape] * count, amp_stamps, [amp_shape] * len(amp_stamps))
        return count

    def frames(self) -> Iterator[RecordingFrame]:
        link = self._amplitude_link()
        amp = self.amplitude_name
        with self._open() as depth_container:
            amp_container = self._open() if link else None
            try:
                depth_packets = self._packets(depth_container, self.depth_name)
                amp_packets = self._packets(amp_container, amp) if amp_container is not None and amp else iter(())
                for index, (stamp, payload, _), amp_packet in _with_amplitude(depth_packets, amp_packets, link):
                    raw = self._array(self.depth_name, payload, index)
                    amplitude = None
                    if amp_packet is not None and amp is not None:
                        amplitude = self._array(amp, amp_packet[1], index).astype(np.float32)
                    why = self.no_amplitude.get(index, "")
                    if amp is not None and amplitude is None and not why:
                        why = f"its amplitude frame in {amp} was not found on reading the recording again"
                    yield RecordingFrame(
                        index,
                        stamp,
                        raw,
                        1.0,
                        f"recording {self.path} frame {index}, track {self.depth_name} at {stamp} ns",
                        amplitude,
                        f"amplitude frame of track {amp} at {stamp} ns",
                        why,
                    )
            finally:
                if amp_container is not None:
                    amp_container.close()


# ------------------------------------------------------------------------------------------------ ROS 1 / 2 bags
def _is_compressed(msg: Any) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def _message_pixels(msg: Any, where: str) -> tuple[np.ndarray, str]:
    """(pixels, encoding) of a ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` (``ros_codecs``)."""
    if not _is_compressed(msg):
        return image_message_to_array(msg, where), str(msg.encoding)
    try:
        pixels, encoding = decode_compressed_image(msg.data, msg.format, where)
    except CompressedImageError as exc:
        raise RecordingError(str(exc)) from None
    expected = _IMAGE_DTYPES.get(encoding)
    if expected is None or (encoding != "32FC1" and pixels.dtype != np.dtype(expected)):
        raise RecordingError(
            f"{where}: compressed image of format {str(msg.format)!r} decodes to {pixels.dtype} pixels; expected a "
            f"one-channel image in one of {', '.join(_IMAGE_DTYPES)} matching its encoding"
        )
    return pixels, encoding


def image_message_to_array(msg: Any, where: str) -> np.ndarray:
    """The pixels of a ``sensor_msgs/Image`` (one channel; ``step`` padding and ``is_bigendian`` honoured) or of a
    ``sensor_msgs/CompressedImage`` (``ros_codecs``)."""
    if _is_compressed(msg):
        return _message_pixels(msg, where)[0]
    encoding = str(msg.encoding)
    if encoding not in _IMAGE_DTYPES:
        raise RecordingError(
            f"{where}: image encoding {encoding!r} is not a one-channel depth/amplitude image; expected one of "
            f"{', '.join(_IMAGE_DTYPES)}"
        )
    dtype = np.dtype(_IMAGE_DTYPES[encoding]).newbyteorder(">" if msg.is_bigendian else "<")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < width * dtype.itemsize or data.size < height * step:
        raise RecordingError(
            f"{where}: image of {width} x {height} {encoding} has step {step} and {data.size} bytes; expected step >= "
            f"{width * dtype.itemsize} and {height * step} bytes"
        )
    rows = data[: height * step].reshape(height, step)[:, : width * dtype.itemsize]
    return np.ascontiguousarray(rows).view(dtype).reshape(height, width).astype(dtype.newbyteorder("="))


def depth_message_pixels(msg: Any, where: str) -> tuple[np.ndarray, float]:
    """(pixels as recorded, millimetres per unit) of a depth image: 16UC1/mono16 in mm (1), 32FC1 in metres (1000);
    a ``sensor_msgs/Image`` or a ``CompressedImage`` (compressedDepth PNG/RVL, or PNG of a 16-bit depth).
    ``RecordingFrame.depth_mm`` makes millimetres of them (``frames.depth_values_mm``)."""
    _check_depth_encoding(_source_encoding(msg), where)
    pixels, encoding = _message_pixels(msg, where)
    _check_depth_encoding(encoding, where)
    return pixels, (1.0 if _DEPTH_ENCODINGS[encoding] == "mm" else 1000.0)


def camera_info_topic(depth_topic: str) -> str:
    """The ``sensor_msgs/CameraInfo`` topic of a depth image topic by ROS's convention: ``<ns>/camera_info`` beside
    ``<ns>/image_raw`` (``/cam/depth/image_rect_raw`` and its ``/compressedDepth`` -> ``/cam/depth/camera_info``)."""
    base = _TRANSPORT_SUFFIX.sub("", depth_topic)
    return f"{base.rsplit('/', 1)[0]}/camera_info"


def _check_depth_encoding(encoding: str, where: str) -> None:
    if encoding not in _DEPTH_ENCODINGS:
        raise RecordingError(
            f"{where}: depth encoding {encoding!r}; expected 16UC1 or mono16 (mm, 0 = invalid) or 32FC1 (metres, "
            "NaN = invalid; ROS REP 118), as a sensor_msgs/Image or a compressedDepth / PNG CompressedImage"
        )


def _source_encoding(msg: Any) -> str:
    if not _is_compressed(msg):
        return str(msg.encoding)
    try:
        return parse_compressed_format(msg.format)[0] or "mono16"  # a bare "png": its bit depth decides, later
    except CompressedImageError:
        return str(msg.format)


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


class BagRecording(Recording):
    """A ROS 1 ``.bag`` or ROS 2 bag folder (module docstring)."""

    IMAGE = "sensor_msgs/msg/Image"
    COMPRESSED = "sensor_msgs/msg/CompressedImage"
    CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

    def __init__(self, path: Path, depth: str | None = None, amplitude: str | None = None, use_amplitude: bool = True):
        self.path = path
        self.no_amplitude, self.notes = {}, []
        self._highlevel = _import("rosbags.highlevel", path)
        with self._reader() as reader:
            images = sorted({c.topic for c in reader.connections if c.msgtype in (self.IMAGE, self.COMPRESSED)})
            self.stream_names = images
            depth_like = [t for t in images if "depth" in t.lower()]
            default = depth_like[0] if depth_like else None
            if default is None and depth is None:
                topics = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections) or "none"
                raise RecordingError(
                    f"recording {path}: no sensor_msgs/Image or CompressedImage topic with 'depth' in its name; it "
                    f"has: {topics}; "
                    "choose the depth topic with --depth-stream"
                )
            self.depth_name = _choose(
                images, depth, default, "depth (sensor_msgs/Image or CompressedImage)", "--depth-stream", path
            )
            if amplitude is not None:
                self.amplitude_name = _choose(
                    images,
                    amplitude,
                    None,
                    "amplitude (sensor_msgs/Image or CompressedImage)",
                    "--amplitude-stream",
                    path,
                )
            else:
                named = [t for t in images if t != self.depth_name and _AMPLITUDE_NAME.search(t)]
                self.amplitude_name = named[0] if named else None
            if not use_amplitude:
                self.amplitude_name = None
            #: every CameraInfo topic of the bag, and the one of the depth topic's namespace (or None)
            self.camera_info_topics = sorted({c.topic for c in reader.connections if c.msgtype == self.CAMERA_INFO})
            own = camera_info_topic(self.depth_name)
            self.camera_info_topic = own if own in self.camera_info_topics else None
        self._intrinsics: Intrinsics | None = None
        self._intrinsics_read = False

    @contextmanager
    def _reader(self) -> Iterator[Any]:
        try:
            reader = self._highlevel.AnyReader([self.path])
            reader.open()
        except Exception as exc:  # AnyReaderError: a damaged index or database, an unknown storage ...
            raise RecordingError(f"recording {self.path} could not be opened as a ROS bag: {exc}") from exc
        try:
            yield reader
        finally:
            reader.close()

    @property
    def intrinsics(self) -> Intrinsics | None:
        if not self._intrinsics_read:
            self._intrinsics = self._camera_info()
            self._intrinsics_read = True
        return self._intrinsics

    def intrinsics_absent(self) -> str:
        listing = ", ".join(self.camera_info_topics) or "none"
        own = camera_info_topic(self.depth_name)
        if self.camera_info_topic is not None:
            return f"its depth topic's CameraInfo {own} holds no message"
        return (
            f"no CameraInfo of its depth topic {self.depth_name}: expected {own}; its CameraInfo topics: {listing} "
            "(one of another namespace belongs to another camera or image)"
        )

    def _camera_info(self) -> Intrinsics | None:
        """The intrinsics of the first message of the depth topic's CameraInfo (``camera_info_topic``), or None."""
        if self.camera_info_topic is None:
            return None
        topic = self.camera_info_topic
        with self._reader() as reader:
            for _, msg in self._messages(reader, [topic]):
                k = [float(v) for v in np.asarray(msg.k if hasattr(msg, "k") else msg.K).ravel()]
                if len(k) != 9 or not any(k):
                    raise RecordingError(
                        f"recording {self.path}: CameraInfo {topic} has K = {k or '[]'} (all zero: an uncalibrated "
                        "camera); give the intrinsics with --intrinsics FILE"
                    )
                try:
                    return Intrinsics(
                        k[0], k[4], k[2], k[5], int(msg.width), int(msg.height), source=f"{self.path} {topic}"
                    )
                except IntrinsicsError as exc:
                    raise RecordingError(f"{exc}; give the intrinsics with --intrinsics FILE") from exc
        return None

    def _messages(self, reader: Any, topics: Sequence[str]) -> Iterator[tuple[str, Any]]:
        conns = [c for c in reader.connections if c.topic in topics]
        try:
            for conn, _, raw in reader.messages(connections=conns):
                yield conn.topic, reader.deserialize(raw, conn.msgtype)
        except RecordingError:
            raise
        except Exception as exc:  # a damaged chunk or database page, a message that does not deserialise
            raise RecordingError(f"recording {self.path}: topic {conns[0].topic} could not be read: {exc}") from exc

    def _names(self) -> list[str]:
        return [self.depth_name] + ([self.amplitude_name] if self.amplitude_name else [])

    def scan(self) -> int:
        depth_stamps: list[int] = []
        depth_shapes: list[tuple[int, ...]] = []
        amp_stamps: list[int] = []
        amp_shapes: list[tuple[int, ...]] = []
        with self._reader() as reader:
            for topic, msg in self._messages(reader, self._names()):
                stamp = _stamp_ns(msg)
                if topic == self.depth_name:
                    where = f"recording {self.path} topic {topic} message {len(depth_stamps)} (stamp {stamp} ns)"
                    depth_shapes.append(depth_message_pixels(msg, where)[0].shape)
                    depth_stamps.append(stamp)
                else:
                    where = f"recording {self.path} topic {topic} message {len(amp_stamps)} (stamp {stamp} ns)"
                    amp_shapes.append(image_message_to_array(msg, where).shape)
                    amp_stamps.append(stamp)
        if not depth_stamps:
            raise RecordingError(f"recording {self.path}: depth topic {self.depth_name} holds no message")
        self._paired(depth_stamps, depth_shapes, amp_stamps, amp_shapes)
        return len(depth_stamps)

    def frames(self) -> Iterator[RecordingFrame]:
        link = self._amplitude_link()
        amp = self.amplitude_name
        with self._reader() as depth_reader, self._reader() if link else nullcontext() as amp_reader:
            depth_msgs = self._messages(depth_reader, [self.depth_name])
            amp_msgs = self._messages(amp_reader, [amp]) if amp_reader is not None and amp else iter(())
            for index, (_, msg), amp_msg in _with_amplitude(depth_msgs, amp_msgs, link):
                stamp = _stamp_ns(msg)
                where = f"recording {self.path} frame {index}, topic {self.depth_name} at {stamp} ns"
                pixels, mm_per_unit = depth_message_pixels(msg, where)
                amp_where = f"amplitude message of {amp} at {stamp} ns"
                amplitude = None
                if amp_msg is not None:
                    amplitude = image_message_to_array(amp_msg[1], amp_where).astype(np.float32)
                why = self.no_amplitude.get(index, "")
                if amp is not None and amplitude is None and not why:
                    why = f"its amplitude message in {amp} was not found on reading the recording again"
                yield RecordingFrame(
                    index,
                    stamp,
                    pixels,
                    mm_per_unit,
                    where,
                    amplitude,
                    amp_where,
                    why,
                    frame_id=str(getattr(msg.header, "frame_id", "")),
                )
