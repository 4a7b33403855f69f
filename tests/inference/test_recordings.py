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
