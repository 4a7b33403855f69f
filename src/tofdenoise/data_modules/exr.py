"""A small OpenEXR reader (scanline images; NONE, RLE, ZIPS and ZIP compression; HALF/FLOAT/UINT channels).

OpenCV reads EXR only when built with OpenEXR *and* ``OPENCV_IO_ENABLE_OPENEXR=1`` is set before ``cv2`` is
imported; the ``opencv-python-headless`` wheels do not always include the codec. Depth maps exported by
renderers (Blender, etc.) are single-part scanline files, usually ZIP/ZIPS-compressed or uncompressed, which
this module decodes with numpy and zlib only. Tiled, multi-part, deep and PIZ/PXR24/B44/DWA files are
rejected with a clear error (convert them to ``.npy``).

Format facts used (OpenEXR file layout): magic 20000630, version 2; header attributes ``name\\0type\\0size value``
ending with an empty name; ``chlist`` entries ``name\\0 pixel_type(int32) pLinear(u8) 3 reserved xSampling
ySampling``; then an offset table (uint64 per chunk) and chunks ``y(int32) size(int32) data``; within a chunk,
each scanline holds every channel's row in channel-name order. ZIP(S) data: zlib stream, then a byte predictor
(t[i] = t[i-1] + t[i] - 128) and the two byte halves interleaved.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

MAGIC = 20000630
PIXEL_DTYPES = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}
COMPRESSIONS = {
    0: "NONE",
    1: "RLE",
    2: "ZIPS",
    3: "ZIP",
    4: "PIZ",
    5: "PXR24",
    6: "B44",
    7: "B44A",
    8: "DWAA",
    9: "DWAB",
}
LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16}
#: the depth channel's names, best first, as the last part of a layered name (``ViewLayer.Depth.Z`` ends in ``Z``):
#: ``Z`` (plain, or in a layer named depth), then any name with a part ``depth`` (``depth``, ``Depth.V``), then
#: ``<layer>.Z``, then ``Y``, ``R``, ``V`` (a depth map saved as a grey or colour image). See ``depth_channel``.
PREFERRED_CHANNELS = ("Z", "depth", "Depth", "Y", "R", "V")
#: layers whose X/Y/Z (or R/G/B) are no depth and no amplitude: Blender's normal, vector, position and mist passes
VECTOR_PASSES = ("normal", "vector", "position", "mist", "denoising normal", "denoising albedo", "uv")
#: name parts that mark an amplitude (IR / active brightness) channel, matched case-insensitively
AMPLITUDE_PARTS = ("amplitude", "amp", "intensity", "ir")
#: ITU-R BT.601 luma weights of R, G, B: OpenCV's COLOR_BGR2GRAY, which converts a colour amplitude PNG
GREY_WEIGHTS = (0.299, 0.587, 0.114)


class ExrError(ValueError):
    pass


class ExrChannelError(ExrError):
    """The file was read, but which of its channels to take is not clear (or the named one is absent)."""


def _cstring(data: bytes, pos: int) -> tuple[str, int]:
    end = data.index(b"\x00", pos)
    return data[pos:end].decode("latin-1"), end + 1


def parse_header(data: bytes, path: Path) -> tuple[dict, int]:
    if len(data) < 8 or struct.unpack_from("<i", data, 0)[0] != MAGIC:
        raise ExrError(f"EXR file {path} does not start with the OpenEXR magic number")
    version = struct.unpack_from("<i", data, 4)[0]
    if version & 0xFF != 2:
        raise ExrError(f"EXR file {path} has format version {version & 0xFF}; expected 2")
    if version & (0x200 | 0x800 | 0x1000):
        raise ExrError(
            f"EXR file {path} is tiled, deep or multi-part; only single-part scanline files are read "
            "(convert it to .npy)"
        )
    pos = 8
    header: dict = {}
    while True:
        name, pos = _cstring(data, pos)
        if not name:
            break
        kind, pos = _cstring(data, pos)
        size = struct.unpack_from("<i", data, pos)[0]
        pos += 4
        value = data[pos : pos + size]
        pos += size
        if kind == "chlist":
            channels = []
            cpos = 0
            while value[cpos : cpos + 1] not in (b"\x00", b""):
                cname, cpos = _cstring(value, cpos)
                ptype, _plinear, xs, ys = struct.unpack_from("<iB3xii", value, cpos)
                cpos += 16
                channels.append((cname, ptype, xs, ys))
            header["channels"] = channels
        elif kind == "compression":
            header["compression"] = value[0]
        elif kind == "box2i" and name == "dataWindow":
            header["dataWindow"] = struct.unpack("<4i", value)
    for key in ("channels", "compression", "dataWindow"):
        if key not in header:
            raise ExrError(f"EXR file {path} has no '{key}' header attribute")
    return header, pos


def _undo_predictor_and_interleave(raw: bytes) -> bytes:
    t = np.frombuffer(raw, dtype=np.uint8).astype(np.int64)
    if t.size == 0:
        return b""
    t[1:] -= 128
    t = (np.cumsum(t) & 0xFF).astype(np.uint8)
    half = (t.size + 1) // 2
    out = np.empty_like(t)
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()


def _rle_decode(data: bytes, expected: int) -> bytes:
    out = bytearray()
    pos = 0
    while pos < len(data) and len(out) < expected:
        count = struct.unpack_from("<b", data, pos)[0]
        pos += 1
        if count < 0:
            out += data[pos : pos - count]
            pos -= count
        else:
            out += data[pos : pos + 1] * (count + 1)
            pos += 1
    return bytes(out)


def read_exr_channels(path: str | Path) -> dict[str, np.ndarray]:
    """All channels of a scanline EXR as float32 arrays (H, W)."""
    path = Path(path)
    data = path.read_bytes()
    try:
        header, pos = parse_header(data, path)
    except (struct.error, ValueError, IndexError) as exc:
        if isinstance(exc, ExrError):
            raise
        raise ExrError(f"EXR file {path} has a truncated or malformed header") from exc
    compression = header["compression"]
    if compression not in LINES_PER_CHUNK:
        raise ExrError(
            f"EXR file {path} uses {COMPRESSIONS.get(compression, compression)} compression; this reader "
            "handles NONE, RLE, ZIPS and ZIP (convert the file to .npy or re-save it with ZIP)"
        )
    x0, y0, x1, y1 = header["dataWindow"]
    width, height = x1 - x0 + 1, y1 - y0 + 1
    channels = sorted(header["channels"], key=lambda c: c[0])
    for name, ptype, xs, ys in channels:
        if ptype not in PIXEL_DTYPES or xs != 1 or ys != 1:
            raise ExrError(
                f"EXR file {path} channel {name!r} has pixel type {ptype} / sampling {xs}x{ys}; expected "
                "HALF, FLOAT or UINT without subsampling"
            )
    lines = LINES_PER_CHUNK[compression]
    chunks = (height + lines - 1) // lines
    try:
        offsets = struct.unpack_from(f"<{chunks}Q", data, pos)
    except struct.error as exc:
        raise ExrError(f"EXR file {path} is truncated (offset table)") from exc
    row_bytes = sum(width * PIXEL_DTYPES[p].itemsize for _, p, _, _ in channels)
    out = {name: np.zeros((height, width), dtype=np.float32) for name, _, _, _ in channels}
    for offset in offsets:
        try:
            y, size = struct.unpack_from("<ii", data, offset)
        except struct.error as exc:
            raise ExrError(f"EXR file {path} is truncated (chunk at byte {offset})") from exc
        payload = data[offset + 8 : offset + 8 + size]
        if len(payload) != size:
            raise ExrError(f"EXR file {path} is truncated (chunk at line {y})")
        n_lines = min(lines, y1 - y + 1)
        expected = n_lines * row_bytes
        if compression == 0 or size == expected:
            raw = payload
        elif compression == 1:
            raw = _undo_predictor_and_interleave(_rle_decode(payload, expected))
        else:
            try:
                raw = _undo_predictor_and_interleave(zlib.decompress(payload))
            except zlib.error as exc:
                raise ExrError(f"EXR file {path}: corrupt ZIP data at line {y}") from exc
        if len(raw) != expected:
            raise ExrError(f"EXR file {path}: chunk at line {y} holds {len(raw)} bytes; expected {expected}")
        cursor = 0
        for line in range(n_lines):
            row = y - y0 + line
            for name, ptype, _, _ in channels:
                dtype = PIXEL_DTYPES[ptype]
                nbytes = width * dtype.itemsize
                out[name][row] = np.frombuffer(raw, dtype=dtype, count=width, offset=cursor)
                cursor += nbytes
    return out


def _parts(name: str) -> list[str]:
    return name.split(".")


def _layer(name: str) -> str:
    """The layer part of a channel name (``ViewLayer.Depth.Z`` -> ``ViewLayer.Depth``; ``Z`` -> "")."""
    return name.rpartition(".")[0]


def _is_vector_pass(name: str) -> bool:
    parts = _parts(name)
    return len(parts) > 1 and parts[-2].lower() in VECTOR_PASSES


def _has_depth_part(name: str) -> bool:
    return any(part.lower() == "depth" for part in _parts(name))


def _depth_rank(name: str) -> int | None:
    """0 best; None: not a depth channel by its name."""
    if _is_vector_pass(name):
        return None
    last = _parts(name)[-1]
    if name == "Z" or (last == "Z" and _has_depth_part(name)):
        return 0
    if _has_depth_part(name):
        return 1
    return {"Z": 2, "Y": 3, "R": 4, "V": 5}.get(last)


def _is_depth_like(name: str) -> bool:
    """A channel that holds depth by its name (never an amplitude): ``Z``, ``*.Z``, any name with a part depth."""
    return _depth_rank(name) in (0, 1, 2)


def _how_to_choose(kind: str, setting: str | None) -> str:
    where = setting or f"data.source_kwargs.{kind}_channel for the folder source"
    return f"name the {kind} channel ({where}) or save the {kind} alone (.npy)"


def _named(channels: dict[str, np.ndarray], channel: str, kind: str, path: Path) -> np.ndarray:
    if channel not in channels:
        raise ExrChannelError(
            f"EXR file {path} has no channel {channel!r} (the {kind} channel asked for); its channels: "
            f"{', '.join(sorted(channels))}"
        )
    return channels[channel]


def depth_channel(names: list[str], path: str | Path = "EXR", setting: str | None = None) -> str:
    """The depth channel among ``names``: the best rank of ``_depth_rank`` over all channels (``PREFERRED_CHANNELS``:
    ``ViewLayer.Depth.Z`` before ``ViewLayer.Combined.R``), the only channel when none ranks. Two channels at the best
    rank (two layers' ``Depth.Z``), or several channels none of which ranks, are an ``ExrChannelError`` naming them
    and ``setting`` (the option that names the channel)."""
    ranked: dict[int, list[str]] = {}
    for name in sorted(names):
        rank = _depth_rank(name)
        if rank is not None:
            ranked.setdefault(rank, []).append(name)
    if ranked:
        best = ranked[min(ranked)]
        if len(best) == 1:
            return best[0]
        raise ExrChannelError(
            f"EXR file {path} has {len(best)} channels that could be the depth: {', '.join(best)}; "
            + _how_to_choose("depth", setting)
        )
    if len(names) == 1:
        return names[0]
    raise ExrChannelError(
        f"EXR file {path} has no depth channel (Z, *.Depth.*, depth, Y, R or V) among {', '.join(sorted(names))}; "
        + _how_to_choose("depth", setting)
    )


def amplitude_channels(names: list[str], path: str | Path = "EXR", setting: str | None = None) -> list[str]:
    """The amplitude channel(s) among ``names``, never a depth channel (``Z``, ``*.Z``, a name with a part depth):
    a name with a part in ``AMPLITUDE_PARTS`` (``IR``, ``amplitude``, ``intensity``, ``amp``), else ``Y`` (grey),
    else the ``R``, ``G``, ``B`` of one layer (returned as three names: converted to grey with ``GREY_WEIGHTS``, as a
    colour amplitude PNG is), else the only channel left (alpha ``A`` aside). Several candidates at the first rank
    that has any, or none at all, are an ``ExrChannelError`` naming the channels and ``setting``."""
    usable = [n for n in sorted(names) if not _is_depth_like(n) and not _is_vector_pass(n)]
    tagged = [n for n in usable if any(part.lower() in AMPLITUDE_PARTS for part in _parts(n))]
    grey = [n for n in usable if _parts(n)[-1] == "Y"]
    layers = sorted(
        {_layer(n) for n in usable if all(f"{_layer(n)}{'.' if _layer(n) else ''}{c}" in usable for c in "RGB")}
    )
    colour = [[f"{layer}{'.' if layer else ''}{c}" for c in "RGB"] for layer in layers]
    rest = [n for n in usable if _parts(n)[-1] != "A"]
    for candidates in ([[n] for n in tagged], [[n] for n in grey], colour, [[n] for n in rest]):
        if len(candidates) == 1:
            return candidates[0]
        if candidates:
            shown = ", ".join("+".join(c) for c in candidates)
            raise ExrChannelError(
                f"EXR file {path} has {len(candidates)} channels that could be the amplitude: {shown}; "
                + _how_to_choose("amplitude", setting)
            )
    depth_like = [n for n in sorted(names) if _is_depth_like(n)]
    raise ExrChannelError(
        f"EXR file {path} has no amplitude channel among {', '.join(sorted(names))}"
        + (f" ({', '.join(depth_like)}: depth, never read as amplitude)" if depth_like else "")
        + "; "
        + _how_to_choose("amplitude", setting)
    )


def read_exr_depth(path: str | Path, channel: str | None = None, setting: str | None = None) -> np.ndarray:
    """The depth channel of an EXR as float32 (H, W): ``channel`` when given (its full name), else
    ``depth_channel``'s choice (``ExrChannelError`` when it is ambiguous)."""
    channels = read_exr_channels(path)
    if channel is not None:
        return _named(channels, channel, "depth", Path(path))
    return channels[depth_channel(list(channels), path, setting)]


def read_exr_amplitude(path: str | Path, channel: str | None = None, setting: str | None = None) -> np.ndarray:
    """The amplitude of an EXR as float32 (H, W): ``channel`` when given, else ``amplitude_channels``' choice (one
    channel, or one layer's R, G, B converted to grey); never a depth channel by its name."""
    channels = read_exr_channels(path)
    if channel is not None:
        return _named(channels, channel, "amplitude", Path(path))
    chosen = amplitude_channels(list(channels), path, setting)
    if len(chosen) == 1:
        return channels[chosen[0]]
    r, g, b = (channels[name].astype(np.float64) for name in chosen)
    return (GREY_WEIGHTS[0] * r + GREY_WEIGHTS[1] * g + GREY_WEIGHTS[2] * b).astype(np.float32)
