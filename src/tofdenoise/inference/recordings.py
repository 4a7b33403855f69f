"""Camera recordings as frame sources: Azure Kinect ``.mkv`` files and ROS 1 / ROS 2 bags.

- **Azure Kinect** (``.mkv``, read with PyAV): Matroska with a ``DEPTH`` and an ``IR`` video track (track title,
  or the ``K4A_DEPTH_TRACK`` / ``K4A_IR_TRACK`` tags), both raw 16-bit grey with the FourCC ``b16g``: **big-endian**
  samples (read as little-endian they are nonsense). Depth in mm, 0 = invalid; the IR frame of the same timestamp
  is the amplitude. The recorder attaches ``calibration.json``: the depth camera's intrinsics
  (``camera.kinect_depth_intrinsics``, for the track's ``K4A_DEPTH_MODE``). Each packet is read as raw bytes and
  must hold exactly width x height samples.
- **ROS 1 ``.bag`` / ROS 2 bag folders** (``metadata.yaml`` + ``.db3`` / ``.mcap``, read with ``rosbags``):
  ``sensor_msgs/Image`` depth topics in ``16UC1`` / ``mono16`` (mm, 0 = invalid) or ``32FC1`` (metres, NaN /
  0 = invalid: ROS REP 118), with an amplitude / IR image topic paired by ``header.stamp``; a
  ``sensor_msgs/CameraInfo`` topic next to the depth topic gives the intrinsics (its ``K``).

Streams are chosen by name (``depth`` / ``amplitude``: a bag topic or a Matroska track title); by default the
depth stream is the Kinect's ``DEPTH`` track or the first image topic (sorted by name) with ``depth`` in its name,
and the amplitude the ``IR`` track or the first image topic named like ``ir`` / ``amplitude`` / ``intensity``.
A stream asked for (or expected) and absent is a ``RecordingError`` listing the streams the recording has.

``Recording.scan()`` reads the whole recording once without keeping frames and checks it (the Matroska segment
as long as its declared size and the last frame at the recorded duration: FFmpeg reads a truncated ``.mkv`` to its
end without an error; every packet complete; a damaged bag index or database; every message decodable):
the commands call it before they write anything for a recording, so a bad recording writes nothing.

PyAV and rosbags are the optional extra ``recordings`` (``pip install 'tofdenoise[recordings]'``); without them a
recording is refused with an error naming the extra.
"""

from __future__ import annotations

import importlib
import re
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from tofdenoise.inference.camera import Intrinsics, IntrinsicsError, kinect_depth_intrinsics, kinect_mode_for_size
from tofdenoise.inference.frames import RECORDING_SUFFIXES, FrameError
from tofdenoise.inference.ros_codecs import CompressedImageError, decode_compressed_image, parse_compressed_format

__all__ = [
    "RECORDING_SUFFIXES",
    "Recording",
    "RecordingError",
    "RecordingFrame",
    "RecordingInput",
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


def _paired(depth_mm: np.ndarray, amplitude: np.ndarray | None, where: str) -> np.ndarray | None:
    if amplitude is not None and amplitude.shape != depth_mm.shape:
        raise RecordingError(f"{where}: amplitude frame is {amplitude.shape}; expected {depth_mm.shape} like the depth")
    return amplitude


@dataclass(frozen=True)
class RecordingInput:
    """A recording on disk and its output name (``rel``: relative to the input folder, or its own name)."""

    path: Path
    rel: Path

    @property
    def rel_stem(self) -> Path:
        return self.rel.with_suffix("") if self.path.is_file() else self.rel


@dataclass
class RecordingFrame:
    """One frame of a recording: ``depth_mm`` float32 (H, W), 0 at invalid pixels, ``valid`` bool, ``amplitude``
    float32 or None, ``index`` (0, 1, ... in recording order), ``stamp_ns`` (its timestamp)."""

    index: int
    stamp_ns: int
    depth_mm: np.ndarray
    valid: np.ndarray
    amplitude: np.ndarray | None = None


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
    """A recording opened for reading (``open_recording``): ``depth_name``, ``amplitude_name`` (or None),
    ``intrinsics`` (or None), ``scan()`` -> frame count, ``frames()`` -> ``RecordingFrame`` in order."""

    path: Path
    depth_name: str
    amplitude_name: str | None
    intrinsics: Intrinsics | None
    #: every image stream of the recording (Kinect tracks, bag image topics), for messages that list them
    stream_names: list[str]

    @abstractmethod
    def scan(self) -> int:
        """Read the whole recording once without keeping frames; the depth frame count, or ``RecordingError``."""

    @abstractmethod
    def frames(self) -> Iterator[RecordingFrame]:
        """The depth frames (with their amplitude when there is one of the same timestamp)."""

    def describe(self) -> str:
        amp = self.amplitude_name or "none"
        return f"{self.path}: depth {self.depth_name}, amplitude {amp}"


def open_recording(path: str | Path, depth: str | None = None, amplitude: str | None = None) -> Recording:
    """The recording at ``path`` with its depth (and amplitude) stream chosen (module docstring)."""
    path = Path(path).expanduser()
    if not path.exists():
        raise RecordingError(f"recording not found: {path}")
    if path.is_file() and path.suffix.lower() == ".mkv":
        return KinectRecording(path, depth, amplitude)
    if is_recording(path):
        return BagRecording(path, depth, amplitude)
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

    def __init__(self, path: Path, depth: str | None = None, amplitude: str | None = None):
        self.path = path
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
            self._layout = {name: self._sample_layout(tracks[name]) for name in self._names()}
            self._duration = container.duration
            stream = tracks[self.depth_name]
            meta = {k.upper(): v for k, v in dict(stream.metadata).items()}
            self.depth_mode = meta.get("K4A_DEPTH_MODE")
            calibration = [a for a in container.streams.attachments if a.name == "calibration.json"]
            self.intrinsics = None
            if calibration:
                mode = self.depth_mode or kinect_mode_for_size(*self._layout[self.depth_name][1:])
                try:
                    self.intrinsics = kinect_depth_intrinsics(bytes(calibration[0].data), mode, str(path))
                except IntrinsicsError as exc:
                    raise RecordingError(str(exc)) from exc

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

    def scan(self) -> int:
        missing = matroska_missing_bytes(self.path)
        if missing:
            raise RecordingError(
                f"recording {self.path} is truncated: its Matroska segment declares {missing} more bytes than the "
                "file holds"
            )
        count, last_end, duration = 0, 0, 0
        with self._open() as container:
            for stamp, payload, duration in self._packets(container, self.depth_name):
                self._array(self.depth_name, payload, count)
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
        return count

    def frames(self) -> Iterator[RecordingFrame]:
        with self._open() as depth_container:
            amp_iter: Iterator[tuple[int, bytes | None, int]] | None = None
            amp_container = self._open() if self.amplitude_name else None
            try:
                if amp_container is not None:
                    amp_iter = self._packets(amp_container, self.amplitude_name)
                pending: tuple[int, bytes | None, int] | None = None
                for index, (stamp, payload, _) in enumerate(self._packets(depth_container, self.depth_name)):
                    raw = self._array(self.depth_name, payload, index)
                    amplitude = None
                    if amp_iter is not None:
                        while pending is None or pending[0] < stamp:
                            pending = next(amp_iter, None)
                            if pending is None:
                                amp_iter = None
                                break
                        if pending is not None and pending[0] == stamp:
                            amplitude = self._array(self.amplitude_name, pending[1], index).astype(np.float32)
                    depth_mm = raw.astype(np.float32)
                    amplitude = _paired(depth_mm, amplitude, f"recording {self.path} frame {index}")
                    yield RecordingFrame(index, stamp, depth_mm, raw > 0, amplitude)
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


def depth_message_to_mm(msg: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(depth_mm float32, 0 at invalid pixels; valid) of a depth image: 16UC1/mono16 in mm, 32FC1 in metres; a
    ``sensor_msgs/Image`` or a ``CompressedImage`` (compressedDepth PNG/RVL, or PNG of a 16-bit depth)."""
    _check_depth_encoding(_source_encoding(msg), where)
    pixels, encoding = _message_pixels(msg, where)
    _check_depth_encoding(encoding, where)
    if _DEPTH_ENCODINGS[encoding] == "mm":
        valid = pixels > 0
        return pixels.astype(np.float32), valid
    depth_mm = pixels.astype(np.float64) * 1000.0
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth_mm) & (depth_mm > 0)
    return np.where(valid, depth_mm, 0.0).astype(np.float32), valid


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

    def __init__(self, path: Path, depth: str | None = None, amplitude: str | None = None):
        self.path = path
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
            self.intrinsics = self._camera_info(reader)

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

    def _camera_info(self, reader: Any) -> Intrinsics | None:
        infos = [c for c in reader.connections if c.msgtype == self.CAMERA_INFO]
        parent = _TRANSPORT_SUFFIX.sub("", self.depth_name).rsplit("/", 1)[0]
        infos.sort(key=lambda c: (c.topic.rsplit("/", 1)[0] != parent, c.topic))
        for conn in infos[:1]:
            for _, _, raw in reader.messages(connections=[conn]):
                msg = reader.deserialize(raw, conn.msgtype)
                k = [float(v) for v in np.asarray(msg.k if hasattr(msg, "k") else msg.K).ravel()]
                try:
                    return Intrinsics(
                        k[0], k[4], k[2], k[5], int(msg.width), int(msg.height), source=f"{self.path} {conn.topic}"
                    )
                except IntrinsicsError as exc:
                    raise RecordingError(str(exc)) from exc
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

    def _stamps(self) -> tuple[list[int], set[int]]:
        depth, amp = [], set()
        with self._reader() as reader:
            for topic, msg in self._messages(reader, self._names()):
                where = f"recording {self.path} topic {topic} message {len(depth)}"
                if topic == self.depth_name:
                    depth_message_to_mm(msg, where)
                    depth.append(_stamp_ns(msg))
                else:
                    image_message_to_array(msg, where)
                    amp.add(_stamp_ns(msg))
        return depth, amp

    def _names(self) -> list[str]:
        return [self.depth_name] + ([self.amplitude_name] if self.amplitude_name else [])

    def scan(self) -> int:
        depth, _ = self._stamps()
        if not depth:
            raise RecordingError(f"recording {self.path}: depth topic {self.depth_name} holds no message")
        return len(depth)

    def frames(self) -> Iterator[RecordingFrame]:
        depth_stamps, amp_stamps = self._stamps() if self.amplitude_name else ([], set())
        paired = set(depth_stamps) & amp_stamps
        waiting_depth: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        waiting_amp: dict[int, np.ndarray] = {}
        index = 0
        with self._reader() as reader:
            for topic, msg in self._messages(reader, self._names()):
                stamp = _stamp_ns(msg)
                where = f"recording {self.path} topic {topic} at {stamp} ns"
                if topic == self.depth_name:
                    depth_mm, valid = depth_message_to_mm(msg, where)
                    if stamp in paired and stamp not in waiting_amp:
                        waiting_depth[stamp] = (index, depth_mm, valid)
                    else:
                        amp = _paired(depth_mm, waiting_amp.pop(stamp, None), where)
                        yield RecordingFrame(index, stamp, depth_mm, valid, amp)
                    index += 1
                elif stamp in paired:
                    amp = image_message_to_array(msg, where).astype(np.float32)
                    if stamp in waiting_depth:
                        i, depth_mm, valid = waiting_depth.pop(stamp)
                        yield RecordingFrame(i, stamp, depth_mm, valid, _paired(depth_mm, amp, where))
                    else:
                        waiting_amp[stamp] = amp
        for stamp, (i, depth_mm, valid) in sorted(waiting_depth.items(), key=lambda kv: kv[1][0]):
            yield RecordingFrame(i, stamp, depth_mm, valid, None)
