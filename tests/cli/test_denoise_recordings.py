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
    assert files_under(out) == sorted(f"{n}{s}" for n in names for s in (".npy", ".ply", ".png", "_depth_m.tiff"))
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
    assert names == files_under(lit_out) and len(names) == 8
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
    assert files_under(out) == [f"kin/frame_{i:06d}.{ext}" for i in range(2) for ext in ("npy", "ply", "png")]
    binned = kinect_depth_intrinsics(recording_files.kinect_calibration_json(), "NFOV_2X2BINNED", "x")
    restored_m = depth_mm_to_m(np.load(out / "kin" / "frame_000001.npy"))
    np.testing.assert_array_equal(read_ply_points(out / "kin" / "frame_000001.ply"), points_m(restored_m, binned))
