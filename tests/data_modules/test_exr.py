"""The built-in OpenEXR reader: a committed fixture file (fixtures/depth_rle.exr, RLE, FLOAT/HALF/UINT channels),
and files written here (NONE/RLE/ZIPS/ZIP)."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from tofdenoise.data_modules.exr import read_exr_channels
from tofdenoise.data_modules.io import DataFileError, read_amplitude, read_depth_mm


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


def _blender(h=24, w=32, seed=0):
    """A Blender multilayer render: colour, alpha, normals and the depth pass (metres), as Blender names them."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.5, 3.0, (h, w)).astype(np.float32)
    colour = rng.uniform(0, 1, (h, w)).astype(np.float32)
    channels = {f"ViewLayer.Combined.{c}": colour for c in "RGB"}
    channels["ViewLayer.Combined.A"] = np.ones_like(colour)
    channels.update({f"ViewLayer.Normal.{c}": rng.uniform(-1, 1, (h, w)).astype(np.float32) for c in "XYZ"})
    channels["ViewLayer.Depth.Z"] = z
    return channels, z, colour


def test_layered_depth_pass_wins_over_colour(tmp_path):
    """``ViewLayer.Combined.R`` sorts before ``ViewLayer.Depth.Z``; the reader took the colour as depth (median
    503.9 mm for a true 1825.7). The depth channel is chosen by its suffix across all channels, Z first."""
    from tofdenoise.data_modules.exr import depth_channel
    from tofdenoise.data_modules.sources.folder import FolderSource

    channels, z, _ = _blender()
    write_exr(tmp_path / "r0.exr", channels, 3)
    np.save(tmp_path / "a0.npy", np.random.default_rng(1).uniform(1, 100, z.shape).astype(np.float32))
    (tmp_path / "list.txt").write_text("r0.exr a0.npy\n")
    sample = FolderSource(tmp_path, depth_unit_mm=1000).load("r0")
    np.testing.assert_allclose(sample.depth_mm, z * np.float32(1000), rtol=1e-6)
    assert np.median(sample.depth_mm) == pytest.approx(1825.7, abs=0.1)
    assert depth_channel(list(channels)) == "ViewLayer.Depth.Z"
    # suffix order over every channel: Z, then a part "depth", then <layer>.Z, Y, R, V; vector passes never
    assert depth_channel(["Z", "depth", "Y"]) == "Z"
    assert depth_channel(["ViewLayer.Combined.R", "ViewLayer.depth"]) == "ViewLayer.depth"
    assert depth_channel(["RenderLayer.Combined.R", "RenderLayer.Z"]) == "RenderLayer.Z"
    assert depth_channel(["ViewLayer.Normal.Z", "ViewLayer.Combined.R"]) == "ViewLayer.Combined.R"
    assert depth_channel(["B", "G", "R"]) == "R" and depth_channel(["Y"]) == "Y" and depth_channel(["L"]) == "L"


def test_ambiguous_depth_layers_are_an_error_naming_the_channels_and_the_setting(tmp_path):
    from tofdenoise.data_modules.sources.folder import FolderSource

    near = np.full((8, 10), 1200.0, np.float32)
    far = np.full((8, 10), 2500.0, np.float32)
    write_exr(tmp_path / "two.exr", {"Left.Depth.Z": near, "Right.Depth.Z": far, "Left.Combined.R": near / 1e4}, 3)
    write_exr(tmp_path / "none.exr", {"mask": near, "label": far}, 0)
    np.save(tmp_path / "a.npy", np.ones((8, 10), np.float32))
    (tmp_path / "list.txt").write_text("two.exr a.npy\nnone.exr a.npy\n")
    with pytest.raises(DataFileError) as info:
        FolderSource(tmp_path).load("two")
    message = str(info.value)
    assert "two.exr has 2 channels that could be the depth: Left.Depth.Z, Right.Depth.Z" in message
    assert "data.source_kwargs.depth_channel" in message
    with pytest.raises(DataFileError, match=r"none.exr has no depth channel .* among label, mask"):
        FolderSource(tmp_path).load("none")
    right = FolderSource(tmp_path, depth_channel="Right.Depth.Z").load("two")
    assert np.all(right.depth_mm == 2500.0)
    assert FolderSource(tmp_path, depth_channel="mask").load("none").depth_mm[0, 0] == 1200.0
    with pytest.raises(DataFileError, match=r"two.exr has no channel 'Depth.Z' \(the depth channel asked for\)"):
        FolderSource(tmp_path, depth_channel="Depth.Z").load("two")
    described = FolderSource(tmp_path, depth_channel="Right.Depth.Z").describe()
    assert described["depth_channel"] == "Right.Depth.Z" and described["amplitude_channel"] is None


def test_exr_amplitude_is_never_the_depth_channel(tmp_path):
    """An RGB (IR) + Z render listed as both depth and amplitude: the amplitude was Z, the depth itself (so sigma_D
    came from the depth). The amplitude takes its own channels: here R, G, B, converted to grey as a colour PNG is."""
    from tofdenoise.data_modules.exr import amplitude_channels
    from tofdenoise.data_modules.sources.folder import FolderSource

    rng = np.random.default_rng(0)
    z = rng.uniform(500, 3000, (24, 32)).astype(np.float32)
    ir = rng.uniform(0, 1, (24, 32)).astype(np.float32)
    write_exr(tmp_path / "v0.exr", {"R": ir, "G": ir, "B": ir, "Z": z}, 3)
    (tmp_path / "list.txt").write_text("v0.exr v0.exr\n")
    sample = FolderSource(tmp_path).load("v0")
    np.testing.assert_array_equal(sample.depth_mm, z)
    np.testing.assert_allclose(sample.amplitude, ir, rtol=1e-6)
    assert not np.allclose(sample.amplitude, z)
    # a colour amplitude: the weights of OpenCV's COLOR_BGR2GRAY (what a colour amplitude PNG gets)
    g = rng.uniform(0, 1, (24, 32)).astype(np.float32)
    write_exr(tmp_path / "c.exr", {"R": ir, "G": g, "B": 1 - ir, "Z": z}, 0)
    expected = cv2.cvtColor(np.dstack([1 - ir, g, ir]), cv2.COLOR_BGR2GRAY)
    np.testing.assert_allclose(read_amplitude(tmp_path / "c.exr"), expected, rtol=1e-5, atol=1e-6)
    # the preference: a part IR / amplitude / intensity, then Y, then one layer's R, G, B, then the only one left
    assert amplitude_channels(["IR", "Y", "Z"]) == ["IR"]
    assert amplitude_channels(["ViewLayer.Depth.Z", "ViewLayer.IR.Y", "ViewLayer.Combined.Y"]) == ["ViewLayer.IR.Y"]
    assert amplitude_channels(["Y", "R", "G", "B", "Z"]) == ["Y"]
    assert amplitude_channels(["A", "B", "G", "R", "depth"]) == ["R", "G", "B"]
    assert amplitude_channels(["L", "Z"]) == ["L"]


def test_exr_amplitude_without_one_clear_channel_is_an_error(tmp_path):
    from tofdenoise.data_modules.sources.folder import FolderSource

    z = np.full((6, 8), 1500.0, np.float32)
    write_exr(tmp_path / "z.exr", {"Z": z}, 0)
    write_exr(tmp_path / "two.exr", {**{f"a.{c}": z / 3 for c in "RGB"}, **{f"b.{c}": z / 5 for c in "RGB"}}, 0)
    with pytest.raises(DataFileError, match=r"z.exr has no amplitude channel among Z \(Z: depth, never read as amp"):
        read_amplitude(tmp_path / "z.exr", what="folder amplitude")
    np.save(tmp_path / "d.npy", z)
    (tmp_path / "list.txt").write_text("d.npy two.exr\n")
    with pytest.raises(DataFileError) as info:
        FolderSource(tmp_path).load("d")
    assert "two.exr has 2 channels that could be the amplitude: a.R+a.G+a.B, b.R+b.G+b.B" in str(info.value)
    assert "data.source_kwargs.amplitude_channel" in str(info.value)
    assert np.all(FolderSource(tmp_path, amplitude_channel="b.G").load("d").amplitude == 300.0)


def test_opencv_fallback_takes_a_colour_result_only_when_it_is_clear(tmp_path, monkeypatch):
    """A variant the built-in reader refuses (PIZ) goes to OpenCV, which returns colour channels without names (its
    channel 0 is B): taken when the channels are equal, converted to grey for an amplitude, refused for a depth."""
    import tofdenoise.data_modules.io as io

    path = tmp_path / "piz.exr"
    write_exr(path, {"Z": np.ones((4, 4), np.float32)}, 0)
    data = bytearray(path.read_bytes())
    data[data.index(b"compression\0compression\0") + len(b"compression\0compression\0") + 4] = 4  # PIZ
    path.write_bytes(bytes(data))
    bgr = np.dstack([np.full((4, 4), v, np.float32) for v in (100.0, 2000.0, 3000.0)])
    monkeypatch.setattr(io.cv2, "imread", lambda *args: bgr)
    with pytest.raises(DataFileError, match="piz.exr.*colour channels only, which differ"):
        read_depth_mm(path)
    assert read_amplitude(path)[0, 0] == pytest.approx(0.114 * 100 + 0.587 * 2000 + 0.299 * 3000, rel=1e-6)
    with pytest.raises(DataFileError, match="channel 'IR' cannot be chosen"):
        read_amplitude(path, exr_channel="IR")
    monkeypatch.setattr(io.cv2, "imread", lambda *args: np.dstack([bgr[:, :, 1]] * 3))
    assert np.all(read_depth_mm(path) == 2000.0)
