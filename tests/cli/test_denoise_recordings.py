"""tofdenoise denoise and LightningCLI predict on recordings (Kinect .mkv, ROS 1 / ROS 2 bags): the same restored
depth as the Python API, metres TIFF and PLY outputs, damaged recordings and missing topics write nothing."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import tofdenoise
from tofdenoise.cli.denoise import main
from tofdenoise.inference.camera import Intrinsics, kinect_depth_intrinsics, points_m
from tofdenoise.inference.denoise import load_restorer
from tofdenoise.inference.outputs import depth_mm_to_m
from tofdenoise.inference.predict import main as predict_main

H, W = 24, 32
K = [40.0, 0.0, 15.5, 0.0, 41.0, 11.5, 0.0, 0.0, 1.0]


def depth_stack(t: int = 3, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W]
    d = np.rint(900 + 5 * x + 3 * y + rng.normal(0, 4, (t, H, W))).astype(np.uint16)
    d[:, 4:8, 6:12] = 0
    return d


def ir_stack(t: int = 3) -> np.ndarray:
    return np.random.default_rng(9).integers(50, 4000, (t, H, W)).astype(np.uint16)


def files_under(folder) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


def read_ply_points(path) -> np.ndarray:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return np.frombuffer(data[end:], dtype="<f4").reshape(-1, 3)


def test_bag_frames_are_restored_like_the_python_api_with_metres_and_points(
    tmp_path, recording_files, restorer_ckpt, capsys
):
    d = depth_stack()
    bag = recording_files.write_bag(tmp_path / "rec.bag", 1, d, amplitude=ir_stack(), camera_info=(K, W, H))
    out = tmp_path / "out"
    code = main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(out), "--npy", "--depth-m", "--ply", "--quiet"])
    assert code == 0, capsys.readouterr().err
    assert "3 frame(s) done, 0 skipped, 0 failed" in capsys.readouterr().err
    names = [f"rec/frame_{i:06d}" for i in range(3)]
    outputs = [f"{n}{s}" for n in names for s in (".npy", ".ply", ".png", "_depth_m.tiff")]
    assert files_under(out) == sorted(outputs + ["rec/frames.csv"])
    model = load_restorer(restorer_ckpt)
    for i, name in enumerate(names):
        expected = tofdenoise.denoise(d[i].astype(np.float32), model)
        np.testing.assert_array_equal(np.load(out / f"{name}.npy"), expected)
        metres = cv2.imread(str(out / f"{name}_depth_m.tiff"), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(np.isnan(metres), d[i] == 0)
        assert np.array_equal(metres[d[i] > 0], depth_mm_to_m(expected)[d[i] > 0])
        points = read_ply_points(out / f"{name}.ply")
        assert len(points) == int((d[i] > 0).sum())
        np.testing.assert_array_equal(points, points_m(metres, Intrinsics(40.0, 41.0, 15.5, 11.5, W, H)))


def test_kinect_mkv_and_ros2_bag_in_one_run(tmp_path, recording_files, restorer_ckpt, capsys):
    src = tmp_path / "in"
    src.mkdir()
    d = depth_stack(2)
    recording_files.write_kinect_mkv(src / "kin.mkv", d, ir_stack(2))
    m = np.where(d > 0, d.astype(np.float64) / 1000.0, np.nan).astype(np.float32)
    recording_files.write_bag(src / "ros2", 2, m, "32FC1")
    out = tmp_path / "out"
    assert main([str(src), "--ckpt", str(restorer_ckpt), "--out", str(out), "--npy", "--quiet"]) == 0
    assert "4 frame(s) done" in capsys.readouterr().err
    model = load_restorer(restorer_ckpt)
    for i in range(2):
        np.testing.assert_array_equal(
            np.load(out / "kin" / f"frame_{i:06d}.npy"), tofdenoise.denoise(d[i].astype(np.float32), model)
        )
        depth_mm = np.where(np.isfinite(m[i]), m[i].astype(np.float64) * 1000.0, 0).astype(np.float32)
        np.testing.assert_array_equal(np.load(out / "ros2" / f"frame_{i:06d}.npy"), tofdenoise.denoise(depth_mm, model))


def test_a_bag_without_the_depth_topic_and_a_truncated_mkv_fail_alone_and_write_nothing(
    tmp_path, recording_files, restorer_ckpt, capsys
):
    src = tmp_path / "in"
    src.mkdir()
    d = depth_stack(8)
    recording_files.write_bag(src / "nodepth.bag", 1, d, depth_topic="/tof/range")
    full = recording_files.write_kinect_mkv(tmp_path / "full.mkv", d, ir_stack(8))
    (src / "cut.mkv").write_bytes(full.read_bytes()[: int(full.stat().st_size * 0.6)])
    cv2.imwrite(str(src / "ok.png"), d[0])
    out = tmp_path / "out"
    code = main([str(src), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1
    assert "1 frame(s) done, 0 skipped, 2 failed" in err
    bag = src / "nodepth.bag"
    assert f"FAILED {bag}: recording {bag}: no sensor_msgs/Image or CompressedImage topic" in err
    assert "/tof/range (sensor_msgs/msg/Image)" in err and "--depth-stream" in err
    assert f"FAILED {src / 'cut.mkv'}: recording {src / 'cut.mkv'} is truncated" in err
    assert files_under(out) == ["ok.png"]  # nothing of either recording, no temporary file


def test_recording_start_up_errors_exit_2_and_the_recording_folder_guard(
    tmp_path, recording_files, restorer_ckpt, capsys, make_restorer_ckpt
):
    d = depth_stack(2)
    bag = recording_files.write_bag(tmp_path / "b2", 2, d)
    before = files_under(bag)
    # OUT/b2 would be the bag folder itself
    assert main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path), "--quiet"]) == 2
    assert "the output folder holds the input" in capsys.readouterr().err
    assert files_under(bag) == before
    cv2.imwrite(str(tmp_path / "f.png"), d[0])
    assert main([str(tmp_path / "f.png"), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path / "o"), "--ply"]) == 2
    assert "--ply needs the camera intrinsics" in capsys.readouterr().err
    # a bag without CameraInfo and --ply: that recording fails, naming --intrinsics
    assert main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path / "o"), "--ply", "--quiet"]) == 1
    assert "has no camera intrinsics" in capsys.readouterr().err and not (tmp_path / "o").exists()
    # a signal-channel model and a recording without amplitude stream
    signal_ckpt = make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True})
    assert main([str(bag), "--ckpt", str(signal_ckpt), "--out", str(tmp_path / "o2"), "--quiet"]) == 1
    assert "has no amplitude / IR stream" in capsys.readouterr().err and not (tmp_path / "o2").exists()
    # --intrinsics of another size: every frame fails, nothing written
    intr = tmp_path / "cam.yaml"
    intr.write_text("fx: 40\nfy: 41\ncx: 15.5\ncy: 11.5\nwidth: 64\nheight: 48\n")
    args = [str(bag), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path / "o3"), "--ply", "--intrinsics", str(intr)]
    assert main([*args, "--quiet"]) == 1
    assert "describe a 64 x 48 image" in capsys.readouterr().err and not (tmp_path / "o3").exists()


def test_lightningcli_predict_on_a_recording_equals_the_command(tmp_path, recording_files, restorer_ckpt):
    d = depth_stack(2)
    mkv = recording_files.write_kinect_mkv(tmp_path / "kin.mkv", d, ir_stack(2))
    intr = tmp_path / "cam.yaml"
    intr.write_text(f"fx: 40\nfy: 41\ncx: 15.5\ncy: 11.5\nwidth: {W}\nheight: {H}\n")
    cli_out, lit_out = tmp_path / "cli", tmp_path / "lit"
    args = ["--npy", "--depth-m", "--ply", "--intrinsics", str(intr), "--quiet"]
    assert main([str(mkv), "--ckpt", str(restorer_ckpt), "--out", str(cli_out), *args]) == 0
    predict_main(
        [
            "predict",
            "--ckpt_path",
            str(restorer_ckpt),
            "--data.inputs",
            f"[{mkv}]",
            "--trainer.callbacks",
            "tofdenoise.inference.FramesPredictionWriter",
            "--trainer.callbacks.out_dir",
            str(lit_out),
            "--trainer.callbacks.npy",
            "true",
            "--trainer.callbacks.depth_m",
            "true",
            "--trainer.callbacks.ply",
            "true",
            "--trainer.callbacks.intrinsics",
            str(intr),
            "--trainer.accelerator",
            "cpu",
            "--trainer.enable_progress_bar",
            "false",
        ]
    )
    names = files_under(cli_out)
    assert names == files_under(lit_out) and len(names) == 9 and "kin/frames.csv" in names
    for rel in names:
        a, b = cli_out / rel, lit_out / rel
        if rel.endswith(".npy"):
            np.testing.assert_array_equal(np.load(a), np.load(b), err_msg=rel)
        else:
            assert a.read_bytes() == b.read_bytes(), rel


def test_frames_datamodule_refuses_a_damaged_recording_before_predicting(tmp_path, recording_files):
    from tofdenoise.inference.predict import FramesDataModule
    from tofdenoise.inference.recordings import RecordingError

    full = recording_files.write_kinect_mkv(tmp_path / "full.mkv", depth_stack(8))
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(full.read_bytes()[: int(full.stat().st_size * 0.6)])
    with pytest.raises(RecordingError, match="cut.mkv is truncated: its Matroska segment declares"):
        FramesDataModule(inputs=[str(cut)])


def test_ply_with_a_kinect_mkv_and_frames_without_intrinsics_fails_only_those_frames(
    tmp_path, recording_files, restorer_ckpt, capsys
):
    """--ply over an .mkv (its calibration.json gives the intrinsics) and frame files (none): each frame file fails
    with one line, the recording's frames are written, the exit status is 1 (a frame failed)."""
    y, x = np.mgrid[0:288, 0:320]
    d = np.rint(900 + 2 * x + y + np.random.default_rng(1).normal(0, 4, (2, 288, 320))).astype(np.uint16)
    src = tmp_path / "in"
    src.mkdir()
    recording_files.write_kinect_mkv(
        src / "kin.mkv", d, depth_mode="NFOV_2X2BINNED", calibration=recording_files.kinect_calibration_json()
    )
    for name in ("a.png", "b.png"):
        cv2.imwrite(str(src / name), depth_stack(1)[0])
    out = tmp_path / "out"
    code = main([str(src), "--ckpt", str(restorer_ckpt), "--out", str(out), "--ply", "--npy", "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "2 frame(s) done, 0 skipped, 2 failed" in err, err
    failed = [line for line in err.splitlines() if "FAILED" in line]
    assert len(failed) == 2
    for name, line in zip(("a.png", "b.png"), failed):
        assert str(src / name) in line and "--intrinsics" in line
    outputs = [f"kin/frame_{i:06d}.{ext}" for i in range(2) for ext in ("npy", "ply", "png")]
    assert files_under(out) == outputs + ["kin/frames.csv"]
    binned = kinect_depth_intrinsics(recording_files.kinect_calibration_json(), "NFOV_2X2BINNED", "x")
    restored_m = depth_mm_to_m(np.load(out / "kin" / "frame_000001.npy"))
    np.testing.assert_array_equal(read_ply_points(out / "kin" / "frame_000001.ply"), points_m(restored_m, binned))


# --------------------------------------------------------------------------------------- the audit of recordings
DEPTH_TOPIC, IR_TOPIC = "/c/depth/image_raw", "/c/ir/image_raw"
STAMPS = [1_700_000_000_000_000_000 + i * 33_333_333 for i in range(5)]


def wall(value, h: int = H, w: int = W, dtype=np.uint16) -> np.ndarray:
    return np.full((h, w), value, dtype)


def table_rows(path) -> list[list[str]]:
    import csv

    return list(csv.reader(path.read_text().splitlines()))


def test_repeated_stamps_write_every_frame_with_its_stamp_and_a_signal_model_fails_them_in_one_line(
    tmp_path, recording_files, restorer_ckpt, make_restorer_ckpt, capsys
):
    """Whole-second stamps, IR one frame late: 2-3 of 5 frames came out (exit 0), with the previous frame's IR.
    Now all 5 (the IR, unused by this model, not read), frames.csv lists them with their stamp and frame_id, the
    summary warns of the shared stamp; a signal-channel model gets no frame's amplitude: one FAILED line."""
    stamp = 100 * 10**9
    d = [(DEPTH_TOPIC, stamp, wall(1000 + 100 * i), "16UC1") for i in range(5)]
    ir = [(IR_TOPIC, stamp, wall(100 * (i + 1)), "mono16") for i in range(5)]
    order = [d[0], d[1], ir[0], d[2], ir[1], d[3], ir[2], d[4], ir[3], ir[4]]
    bag = recording_files.write_image_bag(tmp_path / "coarse.bag", 1, order)
    out = tmp_path / "out"
    assert main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(out), "--npy", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "5 frame(s) done, 0 skipped, 0 failed" in err
    assert f"recording {bag}: depth {DEPTH_TOPIC}, amplitude not read (neither the model nor --sensor uses it)" in err
    assert f"5 of 5 frame(s) written, with their timestamps in {out / 'coarse' / 'frames.csv'}" in err
    assert "warning: recording" in err and "5 of its 5 depth frames share a timestamp" in err
    model = load_restorer(restorer_ckpt)
    for i in range(5):
        expected = tofdenoise.denoise(wall(1000 + 100 * i).astype(np.float32), model)
        np.testing.assert_array_equal(np.load(out / "coarse" / f"frame_{i:06d}.npy"), expected)
    assert table_rows(out / "coarse" / "frames.csv") == [["frame", "stamp_ns", "stream", "frame_id"]] + [
        [f"frame_{i:06d}", str(stamp), DEPTH_TOPIC, "depth"] for i in range(5)
    ]
    signal = make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True})
    assert main([str(bag), "--ckpt", str(signal), "--out", str(tmp_path / "o2"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "0 frame(s) done, 0 skipped, 1 failed" in err and not (tmp_path / "o2").exists()
    assert f"FAILED {bag}: recording {bag}: none of its 5 depth frame(s) has a usable amplitude in {IR_TOPIC}" in err
    assert "shared by 5 depth and 5 amplitude frame(s)" in err and "ambiguous" in err


def test_a_frame_without_a_usable_amplitude_fails_alone_naming_why(
    tmp_path, recording_files, make_restorer_ckpt, capsys
):
    """A signal-channel model: frame 1 without IR of its stamp, frame 2's IR of another size (it stopped the whole
    recording in the middle), frame 3's IR all NaN (restored as NaN, an all-0 PNG, "done", exit 0): each fails
    alone with its reason, exit 1; the others are restored with their own IR, as the Python API restores them."""
    irs = {0: wall(300, dtype=np.float32), 2: wall(300, 2 * H, 2 * W, np.float32), 3: wall(np.nan, dtype=np.float32)}
    irs[4] = (np.arange(H * W).reshape(H, W) + 50).astype(np.float32)
    irs[4][:4] = np.nan
    msgs = []
    for i in range(5):
        msgs.append((DEPTH_TOPIC, STAMPS[i], wall(1000 + 10 * i), "16UC1"))
        if i in irs:
            msgs.append((IR_TOPIC, STAMPS[i], irs[i], "32FC1"))
    bag = recording_files.write_image_bag(tmp_path / "ir.bag", 1, msgs)
    signal = make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True})
    out = tmp_path / "out"
    assert main([str(bag), "--ckpt", str(signal), "--out", str(out), "--npy", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "2 frame(s) done, 0 skipped, 3 failed" in err
    failed = [line.strip() for line in err.splitlines() if "FAILED" in line]
    assert failed[0].startswith(f"FAILED {bag} frame 1: no amplitude frame of its timestamp ({STAMPS[1]} ns)")
    assert failed[1].startswith(f"FAILED {bag} frame 2: the amplitude frame of its timestamp ({STAMPS[2]} ns)")
    assert f"is {2 * W} x {2 * H} pixels; expected {W} x {H} like its depth" in failed[1]
    assert failed[2].startswith(f"FAILED {bag} frame 3: amplitude message of {IR_TOPIC} at {STAMPS[3]} ns")
    assert "holds no finite value where the depth is valid" in failed[2]
    assert files_under(out) == ["ir/frame_000000.npy", "ir/frame_000000.png", "ir/frame_000004.npy"] + [
        "ir/frame_000004.png",
        "ir/frames.csv",
    ]
    assert [row[0] for row in table_rows(out / "ir" / "frames.csv")[1:]] == ["frame_000000", "frame_000004"]
    model = load_restorer(signal)
    for i in (0, 4):
        expected = tofdenoise.denoise(wall(1000 + 10 * i).astype(np.float32), model, amplitude=irs[i])
        assert np.isfinite(expected).all()
        np.testing.assert_array_equal(np.load(out / "ir" / f"frame_{i:06d}.npy"), expected)


def test_an_amplitude_stream_of_another_size_fails_the_recording_up_front_or_is_not_read(
    tmp_path, recording_files, restorer_ckpt, make_restorer_ckpt, capsys
):
    msgs = []
    for i in range(3):
        msgs.append((DEPTH_TOPIC, STAMPS[i], wall(1000 + 10 * i), "16UC1"))
        msgs.append((IR_TOPIC, STAMPS[i], wall(300, 2 * H, 2 * W), "mono16"))
    bag = recording_files.write_image_bag(tmp_path / "irsize.bag", 1, msgs)
    assert main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path / "o1"), "--quiet"]) == 0
    assert "3 frame(s) done, 0 skipped, 0 failed" in capsys.readouterr().err
    signal = make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True})
    assert main([str(bag), "--ckpt", str(signal), "--out", str(tmp_path / "o2"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert len([line for line in err.splitlines() if "FAILED" in line]) == 1 and not (tmp_path / "o2").exists()
    assert f"none of its 3 depth frame(s) has a usable amplitude in {IR_TOPIC}" in err


def test_32fc1_far_values_fail_their_frame_and_the_others_are_written(tmp_path, recording_files, restorer_ckpt, capsys):
    """FLT_MAX metres (a "no return" code) was kept as an infinite valid depth, 1e6 m as a valid 1e9 mm: exit 0.
    Now each such frame fails with the count and the largest, like a frame file beyond 65535 mm."""
    m = np.full((3, H, W), 1.25, np.float32)
    m[0, 0, :4] = np.finfo(np.float32).max
    m[2, 0, :2] = 1e6
    bag = recording_files.write_bag(tmp_path / "far.bag", 1, m, "32FC1")
    out = tmp_path / "out"
    assert main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "1 frame(s) done, 0 skipped, 2 failed" in err
    assert f"FAILED {bag} frame 0: recording {bag} frame 0, topic /camera/depth/image_raw at" in err
    assert "4 valid pixel(s) deeper than 65535 mm (the largest 3.403e+41 mm, 32FC1 metres x 1000)" in err
    assert "2 valid pixel(s) deeper than 65535 mm (the largest 1e+09 mm" in err
    assert files_under(out) == ["far/frame_000001.png", "far/frames.csv"]


def test_ply_takes_the_intrinsics_of_the_depth_topic_only_and_says_which(
    tmp_path, recording_files, restorer_ckpt, capsys
):
    """The colour camera's CameraInfo (the only one) projected the depth; now --ply without the depth topic's own
    CameraInfo fails naming the topics, and the one used is named in the summary."""
    s = STAMPS[0]
    colour = [("/cam/color/camera_info", [300.0, 0, 16, 0, 300.0, 12, 0, 0, 1], W, H)]
    bag = recording_files.write_image_bag(
        tmp_path / "colour.bag", 1, [("/cam/depth/image_raw", s, wall(1000), "16UC1")], colour
    )
    assert main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path / "o1"), "--ply", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert f"FAILED {bag}: recording {bag} has no camera intrinsics: no CameraInfo of its depth topic" in err
    assert "expected /cam/depth/camera_info; its CameraInfo topics: /cam/color/camera_info" in err
    assert "--ply needs --intrinsics FILE" in err and not (tmp_path / "o1").exists()
    own = [("/cam/depth/camera_info", [40.0, 0, 15.5, 0, 41.0, 11.5, 0, 0, 1], W, H)]
    two = [
        ("/cam/depth/image_raw", s, wall(1000), "16UC1"),
        ("/cam/aligned_depth_to_color/image_raw", s, wall(2000), "16UC1"),
    ]
    bag = recording_files.write_image_bag(tmp_path / "two.bag", 1, two, own)
    out = tmp_path / "o2"
    args = [str(bag), "--ckpt", str(restorer_ckpt), "--out", str(out), "--ply", "--npy", "--quiet"]
    assert main(args) == 1  # the default depth topic (aligned, sorted first) has no CameraInfo of its own
    assert "no CameraInfo of its depth topic /cam/aligned_depth_to_color/image_raw" in capsys.readouterr().err
    assert main([*args, "--depth-stream", "/cam/depth/image_raw"]) == 0
    err = capsys.readouterr().err
    assert f"intrinsics from {bag} /cam/depth/camera_info: fx 40, fy 41, cx 15.5, cy 11.5, {W} x {H} px" in err
    restored_m = depth_mm_to_m(np.load(out / "two" / "frame_000000.npy"))
    expected = points_m(restored_m, Intrinsics(40.0, 41.0, 15.5, 11.5, W, H))
    np.testing.assert_array_equal(read_ply_points(out / "two" / "frame_000000.ply"), expected)


def test_an_uncalibrated_camera_info_matters_only_to_ply_without_intrinsics(
    tmp_path, recording_files, restorer_ckpt, capsys
):
    bag = recording_files.write_bag(tmp_path / "z.bag", 1, depth_stack(2), camera_info=([0.0] * 9, W, H))
    base = [str(bag), "--ckpt", str(restorer_ckpt), "--quiet"]
    assert main([*base, "--out", str(tmp_path / "o1")]) == 0
    assert "2 frame(s) done" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "o2"), "--ply"]) == 1
    err = capsys.readouterr().err
    assert "CameraInfo /camera/depth/camera_info has K = " in err and "all zero" in err and "--intrinsics" in err
    intr = tmp_path / "cam.yaml"
    intr.write_text(f"fx: 40\nfy: 41\ncx: 15.5\ncy: 11.5\nwidth: {W}\nheight: {H}\n")
    out = tmp_path / "o3"
    assert main([*base, "--out", str(out), "--ply", "--npy", "--intrinsics", str(intr)]) == 0
    assert f"intrinsics from --intrinsics {intr}" in capsys.readouterr().err
    restored_m = depth_mm_to_m(np.load(out / "z" / "frame_000001.npy"))
    expected = points_m(restored_m, Intrinsics(40.0, 41.0, 15.5, 11.5, W, H))
    np.testing.assert_array_equal(read_ply_points(out / "z" / "frame_000001.ply"), expected)


def test_a_frame_file_in_a_recordings_output_folder_is_refused_before_anything_is_written(
    tmp_path, recording_files, restorer_ckpt, capsys
):
    """data/take1.bag and data/take1/frame_000000.png (an earlier export) both wrote out/take1/: exit 0 with
    the outputs mixed. Now exit 2 naming both, nothing written."""
    data = tmp_path / "data"
    (data / "take1").mkdir(parents=True)
    bag = recording_files.write_bag(data / "take1.bag", 1, depth_stack(2))
    cv2.imwrite(str(data / "take1" / "frame_000000.png"), depth_stack(1)[0])
    out = tmp_path / "out"
    assert main([str(data), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{data / 'take1' / 'frame_000000.png'} and the recording {bag} would both write into" in err
    assert not out.exists()
    nested = tmp_path / "nested"
    (nested / "a").mkdir(parents=True)
    recording_files.write_bag(nested / "a.bag", 1, depth_stack(1))
    recording_files.write_bag(nested / "a" / "b.bag", 1, depth_stack(1))
    assert main([str(nested), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 2
    assert "the output folder of one inside the other's" in capsys.readouterr().err and not out.exists()


def test_depth_scale_mm_with_a_recording_is_refused(tmp_path, recording_files, restorer_ckpt, capsys):
    """--depth-scale-mm was ignored for recordings without a word (their units are their encoding's)."""
    bag = recording_files.write_bag(tmp_path / "r.bag", 1, depth_stack(1))
    cv2.imwrite(str(tmp_path / "f.png"), depth_stack(1)[0])
    out = tmp_path / "out"
    args = [str(bag), str(tmp_path / "f.png"), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]
    assert main([*args, "--depth-scale-mm", "0.25"]) == 2
    err = capsys.readouterr().err
    assert f"--depth-scale-mm 0.25 does not apply to recordings ({bag})" in err and "32FC1: metres" in err
    assert not out.exists()
    from tofdenoise.inference.predict import FramesDataModule

    with pytest.raises(ValueError, match="depth_scale_mm 0.25 does not apply to recordings"):
        FramesDataModule(inputs=[str(bag)], depth_scale_mm=0.25)


def test_the_kinect_table_holds_the_device_timestamps(tmp_path, recording_files, restorer_ckpt):
    from tofdenoise.inference.recordings import open_recording

    mkv = recording_files.write_kinect_mkv(tmp_path / "k.mkv", depth_stack(3), ir_stack(3))
    out = tmp_path / "out"
    assert main([str(mkv), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 0
    stamps = [f.stamp_ns for f in open_recording(mkv).frames()]
    assert stamps[0] == 0 and stamps[2] > stamps[1] > 0
    rows = table_rows(out / "k" / "frames.csv")
    assert rows == [["frame", "stamp_ns", "stream", "frame_id"]] + [
        [f"frame_{i:06d}", str(stamps[i]), "DEPTH", ""] for i in range(3)
    ]


@pytest.mark.parametrize("stop", ["error", "ctrl-c"])
def test_a_recording_cut_short_while_read_says_which_frames_were_not_written(
    tmp_path, recording_files, restorer_ckpt, capsys, monkeypatch, stop
):
    """A read error past the check (a file changed or damaged under the command) ended the recording with a line
    that did not say how much was missing; now the FAILED line lists the frames not written, and the table (also
    after Ctrl-C) lists those that were."""
    from tofdenoise.inference.recordings import BagRecording, RecordingError

    bag = recording_files.write_bag(tmp_path / "cut.bag", 1, depth_stack(5))
    original = BagRecording.frames

    def two_then_stop(self):
        for item in original(self):
            if item.index == 2:
                raise RecordingError("disk gone") if stop == "error" else KeyboardInterrupt
            yield item

    monkeypatch.setattr(BagRecording, "frames", two_then_stop)
    out = tmp_path / "out"
    code = main([str(bag), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == (1 if stop == "error" else 130)
    if stop == "error":
        assert f"FAILED {bag}: disk gone (3 of its 5 frame(s) not read and not written: 2, 3, 4)" in err
    assert f"recording {bag}: depth /camera/depth/image_raw" in err and "2 of 5 frame(s) written" in err
    assert [row[0] for row in table_rows(out / "cut" / "frames.csv")[1:]] == ["frame_000000", "frame_000001"]
