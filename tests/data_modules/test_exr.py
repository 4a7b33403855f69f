"""The built-in OpenEXR reader: a real file from CPython's test data, and files written here (NONE/ZIPS/ZIP)."""

from __future__ import annotations

import glob
import struct
import zlib

import cv2
import numpy as np
import pytest

from tofdenoise.data_modules.exr import read_exr_channels
from tofdenoise.data_modules.io import DataFileError, read_depth_mm


def _attr(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def _zip_pack(raw: bytes) -> bytes:
    """OpenEXR ZIP encoding: split even/odd bytes, delta predictor (+128), zlib."""
    a = np.frombuffer(raw, np.uint8)
    t = np.concatenate([a[0::2], a[1::2]]).astype(np.int64)
    p = t.copy()
    p[1:] = (t[1:] - t[:-1] + 128) & 0xFF
    return zlib.compress(p.astype(np.uint8).tobytes())


def write_exr(path, channels: dict[str, np.ndarray], compression: int) -> None:
    """Minimal scanline EXR writer (compression 0 NONE, 2 ZIPS, 3 ZIP); arrays float16 -> HALF, float32 -> FLOAT."""
    names = sorted(channels)
    h, w = channels[names[0]].shape
    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", 1 if channels[n].dtype == np.float16 else 2, 0, 1, 1)
                      for n in names) + b"\0"
    header = (struct.pack("<ii", 20000630, 2) + _attr("channels", "chlist", chlist)
              + _attr("compression", "compression", bytes([compression]))
              + _attr("dataWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1))
              + _attr("displayWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1))
              + _attr("lineOrder", "lineOrder", b"\0") + _attr("pixelAspectRatio", "float", struct.pack("<f", 1))
              + _attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
              + _attr("screenWindowWidth", "float", struct.pack("<f", 1)) + b"\0")
    lines = 16 if compression == 3 else 1
    chunks = []
    for y in range(0, h, lines):
        raw = b"".join(channels[n][row].astype(channels[n].dtype.newbyteorder("<")).tobytes()
                       for row in range(y, min(y + lines, h)) for n in names)
        data = raw if compression == 0 else _zip_pack(raw)
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


def test_real_exr_file_matches_its_png_twin():
    found = sorted(glob.glob("/root/.pyenv/versions/*/lib/python3*/test/imghdrdata/python.exr"))
    if not found:
        pytest.skip("CPython's imghdr test images are not on this machine")
    channels = read_exr_channels(found[0])
    png = cv2.imread(found[0].replace(".exr", ".png"), cv2.IMREAD_UNCHANGED)
    assert set(channels) == {"R", "G", "B", "A"} and channels["R"].shape == (16, 16)
    assert np.corrcoef(channels["R"].ravel(), png[..., 2].ravel().astype(float))[0, 1] > 0.999


@pytest.mark.parametrize("compression", [0, 2, 3])
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
