"""The built-in OpenEXR reader: a committed fixture file (fixtures/depth_rle.exr, RLE, FLOAT/HALF/UINT channels),
and files written here (NONE/RLE/ZIPS/ZIP)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from tofdenoise.data_modules.exr import read_exr_channels
from tofdenoise.data_modules.io import DataFileError, read_depth_mm


def _attr(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


FIXTURE = Path(__file__).resolve().parent / "fixtures" / "depth_rle.exr"
PIXEL_TYPES = {np.dtype(np.uint32): 0, np.dtype(np.float16): 1, np.dtype(np.float32): 2}


def _predict(raw: bytes) -> bytes:
    """OpenEXR's ZIP/RLE preprocessing: split even/odd bytes, then a delta predictor (+128)."""
    a = np.frombuffer(raw, np.uint8)
    t = np.concatenate([a[0::2], a[1::2]]).astype(np.int64)
    p = t.copy()
    p[1:] = (t[1:] - t[:-1] + 128) & 0xFF
    return p.astype(np.uint8).tobytes()


def _zip_pack(raw: bytes) -> bytes:
    return zlib.compress(_predict(raw))


def _rle_pack(raw: bytes) -> bytes:
    """OpenEXR RLE: after the predictor, a run of 3..128 equal bytes -> (count - 1, byte); other bytes go as
    literals -> (-n, n bytes), n <= 127."""
    a, out, i = _predict(raw), bytearray(), 0
    while i < len(a):
        run = 1
        while i + run < len(a) and a[i + run] == a[i] and run < 128:
            run += 1
        if run >= 3:
            out += struct.pack("<bB", run - 1, a[i])
            i += run
            continue
        j = i
        while j < len(a) and j - i < 127 and not (j + 2 < len(a) and a[j] == a[j + 1] == a[j + 2]):
            j += 1
        out += struct.pack("<b", -(j - i)) + a[i:j]
        i = j
    return bytes(out)


def write_exr(path, channels: dict[str, np.ndarray], compression: int) -> None:
    """Minimal scanline EXR writer (compression 0 NONE, 1 RLE, 2 ZIPS, 3 ZIP); arrays uint32 -> UINT,
    float16 -> HALF, float32 -> FLOAT."""
    names = sorted(channels)
    h, w = channels[names[0]].shape
    chlist = (
        b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", PIXEL_TYPES[channels[n].dtype], 0, 1, 1) for n in names)
        + b"\0"
    )
    header = (
        struct.pack("<ii", 20000630, 2)
        + _attr("channels", "chlist", chlist)
        + _attr("compression", "compression", bytes([compression]))
        + _attr("dataWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1))
        + _attr("displayWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1))
        + _attr("lineOrder", "lineOrder", b"\0")
        + _attr("pixelAspectRatio", "float", struct.pack("<f", 1))
        + _attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
        + _attr("screenWindowWidth", "float", struct.pack("<f", 1))
        + b"\0"
    )
    lines = 16 if compression == 3 else 1
    chunks = []
    for y in range(0, h, lines):
        raw = b"".join(
            channels[n][row].astype(channels[n].dtype.newbyteorder("<")).tobytes()
            for row in range(y, min(y + lines, h))
            for n in names
        )
        data = raw if compression == 0 else _rle_pack(raw) if compression == 1 else _zip_pack(raw)
        if len(data) >= len(raw):
            data = raw  # stored uncompressed when compression does not help (as OpenEXR does)
        chunks.append(struct.pack("<ii", y, len(data)) + data)
    offset = len(header) + 8 * len(chunks)
    table = b""
    for chunk in chunks:
        table += struct.pack("<Q", offset)
        offset += len(chunk)
    with open(path, "wb") as handle:
        handle.write(header + table + b"".join(chunks))


def fixture_channels() -> dict[str, np.ndarray]:
    """What fixtures/depth_rle.exr holds (written once with ``write_exr(FIXTURE, fixture_channels(), 1)``)."""
    yy, xx = np.mgrid[0:12, 0:20]
    depth = (1000.0 + 12.5 * xx + 250.0 * yy).astype(np.float32)
    depth[:3] = 1500.0  # equal rows: long runs for RLE
    depth[5, 7] = np.nan
    amplitude = (0.001 * (xx + 20 * yy)).astype(np.float16)
    label = (xx // 4 + 7 * yy).astype(np.uint32)
    return {"Z": depth, "A": amplitude, "L": label}


def test_committed_exr_fixture_reads_back():
    """A file on disk (not written by this run): a reader change that breaks RLE, HALF or UINT shows here."""
    expected = fixture_channels()
    channels = read_exr_channels(FIXTURE)
    assert sorted(channels) == ["A", "L", "Z"] and channels["Z"].shape == (12, 20)
    assert all(c.dtype == np.float32 for c in channels.values())
    np.testing.assert_array_equal(channels["Z"], expected["Z"])  # NaN in the same place
    np.testing.assert_array_equal(channels["A"], expected["A"].astype(np.float32))
    np.testing.assert_array_equal(channels["L"], expected["L"].astype(np.float32))
    assert channels["Z"][0, 19] == 1500.0 and channels["Z"][11, 19] == np.float32(1000.0 + 12.5 * 19 + 250.0 * 11)
    np.testing.assert_array_equal(read_depth_mm(FIXTURE), expected["Z"])  # the "Z" channel is the depth
    data = FIXTURE.read_bytes()
    assert data[data.index(b"compression\0compression\0") + 28] == 1  # RLE, as the file name says


@pytest.mark.parametrize("compression", [0, 1, 2, 3])
def test_written_exr_round_trips(tmp_path, compression):
    rng = np.random.default_rng(compression)
    depth = rng.uniform(300, 3000, size=(37, 21)).astype(np.float32)
    depth[:10] = 1234.5  # compressible rows
    extra = rng.uniform(0, 1, size=(37, 21)).astype(np.float16)
    path = tmp_path / "d.exr"
    write_exr(path, {"Z": depth, "A": extra}, compression)
    channels = read_exr_channels(path)
    np.testing.assert_array_equal(channels["Z"], depth)
    np.testing.assert_array_equal(channels["A"], extra.astype(np.float32))
    np.testing.assert_array_equal(read_depth_mm(path), depth)  # the "Z" channel is the depth


def test_folder_source_reads_exr_depth(tmp_path):
    from tofdenoise.data_modules.sources.folder import FolderSource

    depth = np.full((12, 16), 1.5, np.float32)  # metres
    depth[0, 0] = np.nan
    write_exr(tmp_path / "d.exr", {"Y": depth}, 3)
    np.save(tmp_path / "a.npy", np.ones((12, 16), np.float32))
    (tmp_path / "list.txt").write_text("d.exr a.npy\n")
    sample = FolderSource(tmp_path, depth_unit_mm=1000.0).load("d")
    assert sample.depth_mm[1, 1] == pytest.approx(1500.0) and not sample.valid[0, 0]


def test_unsupported_exr_variant_is_explained(tmp_path):
    path = tmp_path / "piz.exr"
    write_exr(path, {"Z": np.ones((4, 4), np.float32)}, 0)
    data = bytearray(path.read_bytes())
    marker = data.index(b"compression\0compression\0") + len(b"compression\0compression\0") + 4
    data[marker] = 4  # PIZ
    path.write_bytes(bytes(data))
    with pytest.raises(DataFileError, match="PIZ compression.*OPENCV_IO_ENABLE_OPENEXR"):
        read_depth_mm(path)
    path.write_bytes(bytes(data[:30]))
    with pytest.raises(DataFileError, match="piz.exr"):
        read_depth_mm(path)
