"""Recordings as frame sources: Azure-Kinect-like .mkv (big-endian b16g tracks, calibration.json) and ROS 1 / ROS 2
bags (16UC1 mm, 32FC1 m; raw and image_transport's compressedDepth / compressed), written by the tests themselves;
exact pixel round trips, stream choice, damaged files."""

from __future__ import annotations

import builtins
import shutil

import numpy as np
import pytest

from tofdenoise.inference.camera import kinect_depth_intrinsics
from tofdenoise.inference.frames import find_frames
from tofdenoise.inference.recordings import RecordingError, find_recordings, matroska_missing_bytes, open_recording

H, W = 12, 16
K = [500.0, 0.0, 7.5, 0.0, 502.0, 5.5, 0.0, 0.0, 1.0]


def depth_stack_mm(t: int = 4, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.integers(300, 65535, (t, H, W)).astype(np.uint16)  # high bytes != low bytes: endianness shows
    d[:, 2:4, 3:6] = 0
    return d


def ir_stack(t: int = 4, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 65535, (t, H, W)).astype(np.uint16)


def test_kinect_mkv_reads_big_endian_depth_and_ir_exactly(tmp_path, recording_files):
    d, ir = depth_stack_mm(), ir_stack()
    path = recording_files.write_kinect_mkv(
        tmp_path / "rec.mkv", d, ir, calibration=recording_files.kinect_calibration_json()
    )
    raw = path.read_bytes()
    assert d[1].astype(">u2").tobytes() in raw  # the file holds big-endian samples ...
    assert d[1].astype("<u2").tobytes() not in raw  # ... not little-endian ones
    rec = open_recording(path)
    assert (rec.depth_name, rec.amplitude_name) == ("DEPTH", "IR")
    assert rec.scan() == 4
    frames = list(rec.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f in frames:
        assert f.depth_mm.dtype == np.float32 and np.array_equal(f.depth_mm, d[f.index].astype(np.float32))
        assert np.array_equal(f.valid, d[f.index] > 0)
        assert np.array_equal(f.amplitude, ir[f.index].astype(np.float32))
    assert [f.stamp_ns for f in frames] == sorted(f.stamp_ns for f in frames)


def test_kinect_calibration_gives_the_sdk_mode_intrinsics(tmp_path, recording_files):
    params = recording_files.KINECT_PARAMS
    d = np.full((3, 576, 640), 1000, np.uint16)
    path = recording_files.write_kinect_mkv(
        tmp_path / "r.mkv", d, calibration=recording_files.kinect_calibration_json()
    )
    intr = open_recording(path).intrinsics
    # NFOV unbinned: unitised parameters x 1024, crop (192, 180), half a pixel to the pixel-centre convention
    assert intr.fx == pytest.approx(params[2] * 1024) and intr.fy == pytest.approx(params[3] * 1024)
    assert intr.cx == pytest.approx(params[0] * 1024 - 192 - 0.5) and intr.cy == pytest.approx(params[1] * 1024 - 180.5)
    assert (intr.width, intr.height) == (640, 576)
    binned = kinect_depth_intrinsics(recording_files.kinect_calibration_json(), "NFOV_2X2BINNED", "x")
    assert binned.fx == pytest.approx(params[2] * 512) and binned.cx == pytest.approx(params[0] * 512 - 96 - 0.5)
    assert (binned.width, binned.height) == (320, 288)


def assert_frames_exact(rec, depth_mm: np.ndarray, amplitude: np.ndarray) -> None:
    """The recording's frames, in order, are ``depth_mm`` (0 = invalid) and ``amplitude`` bit for bit."""
    assert rec.scan() == len(depth_mm)
    frames = sorted(rec.frames(), key=lambda f: f.index)
    assert [f.index for f in frames] == list(range(len(depth_mm)))
    for f in frames:
        d = depth_mm[f.index]
        assert np.array_equal(f.depth_mm, d.astype(np.float32)) and np.array_equal(f.valid, d > 0)
        assert np.array_equal(f.amplitude, amplitude[f.index].astype(np.float32))


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("bigendian,pad", [(False, 0), (True, 6)])
def test_bag_16uc1_mm_round_trips_exactly_with_amplitude_and_camera_info(
    tmp_path, recording_files, version, bigendian, pad
):
    d, ir = depth_stack_mm(3), ir_stack(3)
    path = recording_files.write_bag(
        tmp_path / ("rec.bag" if version == 1 else "rec"),
        version,
        d,
        "16UC1",
        amplitude=ir,
        camera_info=(K, W, H),
        bigendian=bigendian,
        pad=pad,
    )
    rec = open_recording(path)
    assert (rec.depth_name, rec.amplitude_name) == ("/camera/depth/image_raw", "/camera/ir/image_raw")
    assert (rec.intrinsics.fx, rec.intrinsics.fy, rec.intrinsics.cx, rec.intrinsics.cy) == (500.0, 502.0, 7.5, 5.5)
    assert_frames_exact(rec, d, ir)


@pytest.mark.parametrize("version", [1, 2])
def test_bag_32fc1_metres_become_mm_with_nan_and_zero_invalid(tmp_path, recording_files, version):
    rng = np.random.default_rng(4)
    m = rng.uniform(0.25, 5.0, (3, H, W)).astype(np.float32)
    m[:, 0, :4] = np.nan
    m[:, 1, 0] = 0.0
    m[:, 1, 1] = -1.0
    m[:, 1, 2] = np.inf
    path = recording_files.write_bag(tmp_path / ("m.bag" if version == 1 else "m"), version, m, "32FC1")
    rec = open_recording(path)
    assert rec.amplitude_name is None and rec.intrinsics is None
    for f in rec.frames():
        src = m[f.index]
        ok = np.isfinite(src) & (src > 0)
        assert np.array_equal(f.valid, ok)
        # the documented conversion, bit for bit: float32(float64(metres) * 1000), 0 where invalid
        assert np.array_equal(f.depth_mm, np.where(ok, src.astype(np.float64) * 1000.0, 0.0).astype(np.float32))
        assert f.amplitude is None


def test_amplitude_is_paired_by_header_stamp_not_by_order(tmp_path, recording_files):
    d, ir = depth_stack_mm(3), ir_stack(3)
    path = recording_files.write_bag(tmp_path / "p.bag", 1, d, amplitude=ir)
    frames = {f.index: f for f in open_recording(path).frames()}
    for i in range(3):
        assert np.array_equal(frames[i].amplitude, ir[i].astype(np.float32))


def test_a_depth_frame_without_an_amplitude_of_its_stamp_has_none(tmp_path, recording_files):
    d, ir = depth_stack_mm(3), ir_stack(3)
    stamps = [1_000_000_000, 2_000_000_000, 3_000_000_000]
    path = recording_files.write_bag(tmp_path / "a", 2, d, amplitude=ir, stamps_ns=stamps)
    # the same bag with the IR of the middle frame moved off its depth's stamp
    import importlib

    rf = recording_files
    shutil.rmtree(path)
    typestore_mod = importlib.import_module("rosbags.typesys")
    from rosbags.rosbag2 import Writer

    ts = typestore_mod.get_typestore(typestore_mod.Stores.ROS2_HUMBLE)
    with Writer(path, version=9) as w:
        cd = w.add_connection("/camera/depth/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        ca = w.add_connection("/camera/ir/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        for i, s in enumerate(stamps):
            w.write(
                ca,
                s,
                ts.serialize_cdr(rf._image(ts, s + (5 if i == 1 else 0), ir[i], "mono16"), "sensor_msgs/msg/Image"),
            )
            w.write(cd, s, ts.serialize_cdr(rf._image(ts, s, d[i], "16UC1"), "sensor_msgs/msg/Image"))
    frames = {f.index: f for f in open_recording(path).frames()}
    assert sorted(frames) == [0, 1, 2]
    assert frames[1].amplitude is None
    assert np.array_equal(frames[0].amplitude, ir[0]) and np.array_equal(frames[2].amplitude, ir[2])


def test_streams_are_chosen_by_name_and_a_missing_one_lists_what_there_is(tmp_path, recording_files):
    d = depth_stack_mm(2)
    path = recording_files.write_bag(
        tmp_path / "t.bag", 1, d, depth_topic="/tof/range", amplitude=ir_stack(2), amplitude_topic="/tof/amplitude"
    )
    with pytest.raises(RecordingError) as err:
        open_recording(path)
    msg = str(err.value)
    assert str(path) in msg and "/tof/range" in msg and "/tof/amplitude" in msg and "--depth-stream" in msg
    rec = open_recording(path, depth="/tof/range")
    assert rec.amplitude_name == "/tof/amplitude"
    assert np.array_equal(next(rec.frames()).depth_mm, d[0].astype(np.float32))
    with pytest.raises(
        RecordingError, match=r"no amplitude \(sensor_msgs/Image or CompressedImage\) stream '/tof/ir'.*/tof/range"
    ):
        open_recording(path, depth="/tof/range", amplitude="/tof/ir")
    mkv = recording_files.write_kinect_mkv(tmp_path / "k.mkv", d)
    with pytest.raises(RecordingError, match=r"no depth stream 'RANGE'.*it has: DEPTH"):
        open_recording(mkv, depth="RANGE")
    assert open_recording(mkv).amplitude_name is None


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("codec", ["png", "rvl"])
def test_compressed_depth_bags_read_exactly_with_a_png_amplitude(tmp_path, recording_files, version, codec):
    d, ir = depth_stack_mm(3), ir_stack(3)
    path = recording_files.write_compressed_bag(
        tmp_path / ("c.bag" if version == 1 else "c"), version, d, "16UC1", codec, amplitude=ir
    )
    rec = open_recording(path)
    assert rec.depth_name == "/camera/depth/image_raw/compressedDepth"
    assert rec.amplitude_name == "/camera/ir/image_raw/compressed"
    assert_frames_exact(rec, d, ir)


def test_compressed_depth_32fc1_becomes_mm_and_a_jpeg_amplitude_is_read(tmp_path, recording_files):
    rng = np.random.default_rng(5)
    m = rng.uniform(0.3, 8.0, (2, H, W)).astype(np.float32)
    m[:, 0, :3] = np.nan
    amp = rng.integers(20, 235, (2, H, W)).astype(np.uint8)
    path = recording_files.write_compressed_bag(
        tmp_path / "f", 2, m, "32FC1", "rvl", amplitude=amp, amplitude_codec="jpeg"
    )
    rec = open_recording(path)
    for f in rec.frames():
        q, a, b = recording_files.quantise_inverse_depth(m[f.index])
        ok = q > 0
        assert np.array_equal(f.valid, ok) and not ok[0, :3].any()
        metres = (np.float32(a) / (q.astype(np.float32) - np.float32(b))).astype(np.float64)
        assert np.array_equal(f.depth_mm, np.where(ok, metres * 1000.0, 0.0).astype(np.float32))
        assert np.abs(f.depth_mm - m[f.index] * 1000)[ok].max() <= 1000 * 8.0**2 / a  # one step of 1/z
        assert f.amplitude.shape == (H, W) and np.abs(f.amplitude - amp[f.index]).mean() < 8  # JPEG: lossy


def test_a_damaged_compressed_message_fails_the_scan_naming_topic_and_stamp(tmp_path, recording_files):
    d = depth_stack_mm(3)
    good = [recording_files.compressed_depth_payload(x, "16UC1", "png") for x in d]
    path = recording_files.write_compressed_bag(tmp_path / "bad.bag", 1, d, payloads=[good[0], good[1][:40], good[2]])
    rec = open_recording(path)
    with pytest.raises(
        RecordingError, match=r"bad\.bag topic /camera/depth/image_raw/compressedDepth .*does not decode"
    ):
        rec.scan()
    # a colour JPEG stream named like depth is refused by its format, before decoding
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    jpeg = tmp_path / "colour.bag"
    with Writer(jpeg) as w:
        c = w.add_connection("/camera/depth_registered/color", "sensor_msgs/msg/CompressedImage", typestore=ts)
        msg = recording_files._compressed(ts, 10, "bgr8; jpeg compressed bgr8", recording_files.png_bytes(d[0]))
        w.write(c, 10, ts.serialize_ros1(msg, "sensor_msgs/msg/CompressedImage"))
    with pytest.raises(RecordingError, match=r"depth encoding 'bgr8'; expected 16UC1"):
        open_recording(jpeg).scan()


def test_a_truncated_mkv_is_an_error_not_a_shorter_recording(tmp_path, recording_files):
    d = depth_stack_mm(10)
    path = recording_files.write_kinect_mkv(tmp_path / "full.mkv", d, ir_stack(10))
    data = path.read_bytes()
    assert matroska_missing_bytes(path) == 0 and open_recording(path).scan() == 10
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    assert matroska_missing_bytes(cut) == len(data) - cut.stat().st_size
    with pytest.raises(
        RecordingError,
        match=rf"cut\.mkv is truncated: its Matroska segment declares {len(data) - cut.stat().st_size} more bytes",
    ):
        open_recording(cut).scan()
    # a segment of unknown size (a recorder that never closed the file): the depth track ends before the duration
    segment = data.index(bytes([0x18, 0x53, 0x80, 0x67]))
    assert data[segment + 4] == 0x01  # an 8-byte size
    unknown = data[: segment + 4] + bytes([0x01] + [0xFF] * 7) + data[segment + 12 :]
    cut.write_bytes(unknown[: int(len(unknown) * 0.6)])
    assert matroska_missing_bytes(cut) == 0
    with pytest.raises(RecordingError, match=r"cut\.mkv is truncated: track DEPTH ends at .* of its recorded"):
        open_recording(cut).scan()
    header_only = tmp_path / "head.mkv"
    header_only.write_bytes(data[:600])
    with pytest.raises(RecordingError, match=r"head\.mkv"):
        open_recording(header_only).scan()
    garbage = tmp_path / "garbage.mkv"
    garbage.write_bytes(b"not a matroska file" * 10)
    with pytest.raises(RecordingError, match=r"garbage\.mkv could not be opened as Matroska"):
        open_recording(garbage)


def test_damaged_bags_are_errors_naming_the_file(tmp_path, recording_files):
    d = depth_stack_mm(3)
    bag1 = recording_files.write_bag(tmp_path / "r1.bag", 1, d)
    cut1 = tmp_path / "cut1.bag"
    cut1.write_bytes(bag1.read_bytes()[: int(bag1.stat().st_size * 0.7)])
    with pytest.raises(RecordingError, match=r"recording .*cut1\.bag could not be opened as a ROS bag"):
        open_recording(cut1)
    bag2 = recording_files.write_bag(tmp_path / "r2", 2, d)
    db = next(bag2.glob("*.db3"))
    db.write_bytes(db.read_bytes()[: db.stat().st_size // 2])
    with pytest.raises(RecordingError, match=r"r2"):
        rec = open_recording(bag2)
        rec.scan()


def test_a_missing_extra_is_named(tmp_path, recording_files, monkeypatch):
    mkv = recording_files.write_kinect_mkv(tmp_path / "k.mkv", depth_stack_mm(2))
    real_import = builtins.__import__

    def no_av(name, *args, **kwargs):
        if name == "av" or name.startswith("av."):
            raise ImportError("No module named 'av'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_av)
    import sys

    monkeypatch.delitem(sys.modules, "av", raising=False)
    with pytest.raises(RecordingError, match=r"k\.mkv: reading it needs the package 'av'.*tofdenoise\[recordings\]"):
        open_recording(mkv)


def test_find_recordings_and_frames_split_the_inputs(tmp_path, recording_files):
    root = tmp_path / "in"
    (root / "sub").mkdir(parents=True)
    d = depth_stack_mm(2)
    recording_files.write_kinect_mkv(root / "a.mkv", d)
    recording_files.write_bag(root / "sub" / "b.bag", 1, d)
    recording_files.write_bag(root / "sub" / "c", 2, d)
    import cv2

    cv2.imwrite(str(root / "f.png"), d[0])
    found = find_recordings([root])
    assert [r.rel.as_posix() for r in found] == ["a.mkv", "sub/b.bag", "sub/c"]
    assert [r.rel_stem.as_posix() for r in found] == ["a", "sub/b", "sub/c"]
    assert [f.rel.as_posix() for f in find_frames([root])] == ["f.png"]
    assert find_frames([root / "a.mkv"]) == []  # a recording given directly is not a frame file
    assert [r.rel.as_posix() for r in find_recordings([root / "sub" / "c", root / "a.mkv"])] == ["c", "a.mkv"]
    assert find_recordings([root], exclude=[root / "sub"]) == find_recordings([root / "a.mkv"])


# ------------------------------------------------------------------ timestamps, pairing, ranges, intrinsics (audit)
DEPTH, IR = "/c/depth/image_raw", "/c/ir/image_raw"


def wall(value, h: int = H, w: int = W, dtype=np.uint16) -> np.ndarray:
    return np.full((h, w), value, dtype)


@pytest.mark.parametrize("version", [1, 2])
def test_repeated_header_stamps_keep_every_depth_frame_and_pair_no_amplitude(tmp_path, recording_files, version):
    """A driver stamping whole seconds: 5 depth frames all stamped 100 s, the IR one frame late (D0 D1 I0 D2 I1 ...).
    The reader kept 2-3 frames (a dict keyed by stamp) and gave frames 1-4 the previous frame's IR; now 5 frames in
    order, none with an amplitude (which is whose is ambiguous), and a note naming the shared stamp."""
    stamp = 100 * 10**9
    depth = [(DEPTH, stamp, wall(1000 + 100 * i), "16UC1") for i in range(5)]
    ir = [(IR, stamp, wall(100 * (i + 1)), "mono16") for i in range(5)]
    order = [depth[0], depth[1], ir[0], depth[2], ir[1], depth[3], ir[2], depth[4], ir[3], ir[4]]
    path = recording_files.write_image_bag(tmp_path / ("c.bag" if version == 1 else "c"), version, order)
    rec = open_recording(path)
    assert rec.amplitude_name == IR and rec.scan() == 5
    frames = list(rec.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [float(f.depth_mm[0, 0]) for f in frames] == [1000.0, 1100.0, 1200.0, 1300.0, 1400.0]
    assert all(f.amplitude is None and f.stamp_ns == stamp for f in frames)
    assert all("shared by 5 depth and 5 amplitude frame(s)" in f.no_amplitude for f in frames)
    assert "ambiguous" in frames[0].no_amplitude and sorted(rec.no_amplitude) == [0, 1, 2, 3, 4]
    assert len(rec.notes) == 1 and "5 of its 5 depth frames share a timestamp" in rec.notes[0]
    assert "100000000000 ns" in rec.notes[0] and "every depth frame is kept" in rec.notes[0]
    # the amplitude not used: not read at all, the same 5 depth frames
    bare = open_recording(path, use_amplitude=False)
    assert bare.amplitude_name is None and bare.scan() == 5 and bare.no_amplitude == {}
    assert [float(f.depth_mm[0, 0]) for f in bare.frames()] == [1000.0, 1100.0, 1200.0, 1300.0, 1400.0]


def test_a_shared_depth_stamp_leaves_the_other_frames_paired_and_all_frames_in_order(tmp_path, recording_files):
    """Frames 0 and 1 share a stamp with one IR message (logged after both): both kept, neither paired; frame 2
    paired. Then late, missing, early and stray IR messages: every frame comes out in index order with its own."""
    s0, s2 = 1_700_000_000_000_000_000, 1_700_000_000_066_666_666
    msgs = [(DEPTH, s0, wall(1000), "16UC1"), (DEPTH, s0, wall(1100), "16UC1"), (IR, s0, wall(500), "mono16")]
    msgs += [(DEPTH, s2, wall(1200), "16UC1"), (IR, s2, wall(600), "mono16")]
    rec = open_recording(recording_files.write_image_bag(tmp_path / "dup.bag", 1, msgs))
    frames = list(rec.frames())
    assert [(f.index, float(f.depth_mm[0, 0])) for f in frames] == [(0, 1000.0), (1, 1100.0), (2, 1200.0)]
    assert frames[0].amplitude is None and frames[1].amplitude is None
    assert "shared by 2 depth and 1 amplitude frame(s)" in frames[0].no_amplitude
    assert np.array_equal(frames[2].amplitude, wall(600, dtype=np.float32)) and frames[2].no_amplitude == ""

    s = [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(5)]
    d = [(DEPTH, s[i], wall(1000 + 100 * i), "16UC1") for i in range(5)]
    ir = [(IR, s[i], wall(10 + i), "mono16") for i in range(5)]
    # IR 1 missing, IR 3 two frames late, IR 4 before its depth, a stray IR of a stamp no depth has
    order = [d[0], ir[0], d[1], d[2], ir[2], d[3], ir[4], d[4], ir[3], (IR, s[0] + 5, wall(99), "mono16")]
    rec = open_recording(recording_files.write_image_bag(tmp_path / "late", 2, order))
    frames = list(rec.frames())
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]  # the old reader gave 0, 1, 2, 4, 3
    assert [None if f.amplitude is None else int(f.amplitude[0, 0]) for f in frames] == [10, None, 12, 13, 14]
    assert rec.no_amplitude == {1: f"no amplitude frame of its timestamp ({s[1]} ns) in {IR}"} and rec.notes == []


def test_32fc1_depths_beyond_65535_mm_fail_their_frame_as_in_a_frame_file(tmp_path, recording_files):
    """A "no return" coded as FLT_MAX metres became an infinite valid depth, 1e6 m a valid 1e9 mm; now the frame is
    refused by the frame files' rule, naming the count, the largest and the frame; NaN / 0 / -1 stay invalid."""
    d = np.full((3, H, W), 1.25, np.float32)
    d[0, 0, :4] = np.finfo(np.float32).max
    d[1, 0, :3] = 1e6
    d[2, 0, 0], d[2, 0, 1], d[2, 0, 2] = np.nan, 0.0, -1.0
    rec = open_recording(recording_files.write_bag(tmp_path / "far.bag", 1, d, "32FC1"))
    assert rec.scan() == 3  # decodable: the check of the whole recording passes, the frames fail alone
    frames = list(rec.frames())
    with pytest.raises(RecordingError, match=r"frame 0, topic /camera/depth/image_raw at \d+ ns: 4 valid pixel"):
        _ = frames[0].depth_mm
    with pytest.raises(RecordingError, match=r"3 valid pixel\(s\) deeper than 65535 mm \(the largest 1e\+09 mm"):
        frames[1].frame("x")
    assert frames[2].valid.sum() == H * W - 3 and frames[2].depth_mm[0, :3].tolist() == [0.0, 0.0, 0.0]
    assert np.all(frames[2].depth_mm[1:] == np.float32(1250.0))


def test_camera_info_comes_from_the_depth_topics_namespace_only(tmp_path, recording_files):
    """The only CameraInfo being the colour camera's was used for the depth; with two depth topics the chosen one
    got the other's. Now only <ns>/camera_info of the depth topic <ns>/image_raw, else none, saying what it has."""
    s = 1_700_000_000_000_000_000
    color = [("/cam/color/camera_info", [300.0, 0, 16, 0, 300.0, 12, 0, 0, 1], W, H)]
    one = [("/cam/depth/image_raw", s, wall(1000), "16UC1")]
    rec = open_recording(recording_files.write_image_bag(tmp_path / "color.bag", 1, one, color))
    assert rec.intrinsics is None
    assert rec.intrinsics_absent() == (
        "no CameraInfo of its depth topic /cam/depth/image_raw: expected /cam/depth/camera_info; its CameraInfo "
        "topics: /cam/color/camera_info (one of another namespace belongs to another camera or image)"
    )
    two = one + [("/cam/aligned_depth_to_color/image_raw", s, wall(2000), "16UC1")]
    own = [("/cam/depth/camera_info", [20.0, 0, 7.5, 0, 21.0, 5.5, 0, 0, 1], W, H)]
    path = recording_files.write_image_bag(tmp_path / "two.bag", 1, two, own)
    aligned = open_recording(path)
    assert aligned.depth_name == "/cam/aligned_depth_to_color/image_raw" and aligned.intrinsics is None
    depth = open_recording(path, depth="/cam/depth/image_raw")
    assert (depth.intrinsics.fx, depth.intrinsics.fy, depth.intrinsics.cx, depth.intrinsics.cy) == (20, 21, 7.5, 5.5)
    assert "/cam/depth/camera_info" in depth.intrinsics.source
    # image_transport's compressed topic of the depth belongs to the same namespace
    from tofdenoise.inference.recordings import camera_info_topic

    assert camera_info_topic("/cam/depth/image_rect_raw/compressedDepth") == "/cam/depth/camera_info"


def test_an_uncalibrated_camera_info_is_an_error_only_when_the_intrinsics_are_read(tmp_path, recording_files):
    """K all zero (a driver without a calibration file) failed opening the recording; now only reading the
    intrinsics (a point cloud) fails, naming the topic and --intrinsics."""
    path = recording_files.write_bag(tmp_path / "z.bag", 1, depth_stack_mm(2), camera_info=([0.0] * 9, W, H))
    rec = open_recording(path)
    assert rec.scan() == 2 and len(list(rec.frames())) == 2
    with pytest.raises(RecordingError, match=r"CameraInfo /camera/depth/camera_info has K = .*all zero.*--intrinsics"):
        _ = rec.intrinsics


def test_an_amplitude_of_another_size_is_named_for_its_frame_and_not_read_when_unused(tmp_path, recording_files):
    """One IR frame of another size aborted the recording in the middle (an error inside frames()); now scan()
    names that frame's amplitude as unusable, the other frames keep theirs, and unused it is not read at all."""
    s = [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(4)]
    msgs = []
    for i in range(4):
        msgs.append((DEPTH, s[i], wall(1000 + 10 * i), "16UC1"))
        msgs.append((IR, s[i], wall(300, *((2 * H, 2 * W) if i == 2 else (H, W))), "mono16"))
    path = recording_files.write_image_bag(tmp_path / "irsize.bag", 1, msgs)
    rec = open_recording(path)
    assert rec.scan() == 4
    assert rec.no_amplitude == {
        2: f"the amplitude frame of its timestamp ({s[2]} ns) in {IR} is {2 * W} x {2 * H} pixels; expected "
        f"{W} x {H} like its depth"
    }
    frames = list(rec.frames())
    assert [f.amplitude is None for f in frames] == [False, False, True, False]
    assert [float(f.depth_mm[0, 0]) for f in frames] == [1000.0, 1010.0, 1020.0, 1030.0]
    bare = open_recording(path, use_amplitude=False)
    assert bare.scan() == 4 and all(f.amplitude is None and f.no_amplitude == "" for f in bare.frames())


def test_a_recording_frame_goes_through_the_frame_files_amplitude_check(tmp_path, recording_files):
    """A 32FC1 IR frame all NaN (a dropped stream) went to the network as NaN; now ``frame()`` refuses it as
    ``load_frame`` refuses such an amplitude file, and a NaN block is invalid (0 for the network)."""
    s = [1_700_000_000_000_000_000, 1_700_000_000_033_333_333]
    ir1 = (np.arange(H * W).reshape(H, W) + 50).astype(np.float32)
    ir1[:4] = np.nan
    msgs = [(DEPTH, s[0], wall(1000), "16UC1"), (IR, s[0], np.full((H, W), np.nan, np.float32), "32FC1")]
    msgs += [(DEPTH, s[1], wall(1000), "16UC1"), (IR, s[1], ir1, "32FC1")]
    frames = list(open_recording(recording_files.write_image_bag(tmp_path / "nan.bag", 1, msgs)).frames())
    with pytest.raises(ValueError, match=rf"amplitude message of {IR} at {s[0]} ns \(for recording .*nan\.bag frame 0"):
        frames[0].frame("f0")
    f1 = frames[1].frame("f1")
    assert np.array_equal(f1.amplitude_valid, np.isfinite(ir1))
    assert np.array_equal(f1.amplitude, np.where(np.isfinite(ir1), ir1, 0).astype(np.float32))
    assert frames[1].frame("f1", amplitude=False).amplitude is None


def test_kinect_ir_is_not_read_when_unused(tmp_path, recording_files):
    d, ir = depth_stack_mm(3), ir_stack(3)
    path = recording_files.write_kinect_mkv(tmp_path / "k.mkv", d, ir, calibration=b"not json")
    rec = open_recording(path, use_amplitude=False)
    assert rec.amplitude_name is None and rec.scan() == 3
    frames = list(rec.frames())
    assert all(f.amplitude is None for f in frames) and [f.index for f in frames] == [0, 1, 2]
    assert np.array_equal(frames[1].depth_mm, d[1].astype(np.float32))
    with pytest.raises(RecordingError, match="calibration.json"):  # a bad calibration: only when read
        _ = rec.intrinsics
    paired = open_recording(path)
    assert paired.scan() == 3 and paired.no_amplitude == {}
    assert all(np.array_equal(f.amplitude, ir[f.index].astype(np.float32)) for f in paired.frames())
