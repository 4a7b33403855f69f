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
PREFERRED_CHANNELS = ("Z", "depth", "Depth", "Y", "R", "V")


class ExrError(ValueError):
    pass


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


def read_exr_depth(path: str | Path) -> np.ndarray:
    """The depth-like channel of an EXR (Z, depth, Y, R, V, or the only/first channel) as float32 (H, W)."""
    channels = read_exr_channels(path)
    for name in PREFERRED_CHANNELS:
        if name in channels:
            return channels[name]
    for name in channels:
        if name.split(".")[-1] in PREFERRED_CHANNELS:
            return channels[name]
    return channels[sorted(channels)[0]]
