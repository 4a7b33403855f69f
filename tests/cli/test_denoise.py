"""tofdenoise denoise: formats, outputs (PNG16 / npy / sigma / preview), bad inputs, exit codes, atomic writes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

import tofdenoise
from tofdenoise.cli.denoise import main
from tofdenoise.data_modules.io import depth_mm_to_png16, read_depth_mm
from tofdenoise.inference.denoise import load_restorer, sigma_map_mm
from tofdenoise.physics.calibration import resolve_calibration, save_calibration


def frame(seed: int, h: int = 36, w: int = 48) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    d = np.rint(800 + 4 * x + 3 * y + rng.normal(0, 5, (h, w))).astype(np.float32)
    d[5:11, 8:16] = 0
    return d


@pytest.fixture
def frames_dir(tmp_path, write_exr):
    src = tmp_path / "frames"
    (src / "sub").mkdir(parents=True)
    amp = tmp_path / "amp"
    (amp / "sub").mkdir(parents=True)
    cv2.imwrite(str(src / "a.png"), frame(0).astype(np.uint16))
    np.save(src / "sub" / "b.npy", np.where(frame(1) > 0, frame(1), np.nan))
    write_exr(src / "sub" / "c.exr", frame(2))
    for rel in ("a", "sub/b", "sub/c"):
        np.save(amp / f"{rel}.npy", np.random.default_rng(3).uniform(100, 3000, (36, 48)).astype(np.float32))
    return src, amp


def test_png_npy_exr_frames_equal_the_python_api(frames_dir, restorer_ckpt, tmp_path, capsys):
    src, amp = frames_dir
    calib_file = save_calibration(resolve_calibration(None), tmp_path / "calib.yaml") or tmp_path / "calib.yaml"
    out = tmp_path / "out"
    code = main(
        [
            str(src),
            "--ckpt",
            str(restorer_ckpt),
            "--out",
            str(out),
            "--amplitude",
            str(amp),
            "--sensor",
            str(calib_file),
            "--npy",
            "--previews",
            "--device",
            "cpu",
            "--quiet",
        ]
    )
    err = capsys.readouterr().err
    assert code == 0, err
    assert "3 frame(s) done, 0 skipped, 0 failed" in err and "s/frame" in err
    model = load_restorer(restorer_ckpt)
    calib = resolve_calibration(calib_file)
    for rel, path in (("a", src / "a.png"), ("sub/b", src / "sub" / "b.npy"), ("sub/c", src / "sub" / "c.exr")):
        depth = read_depth_mm(path)
        api = tofdenoise.denoise(depth, model)
        np.testing.assert_array_equal(np.load(out / f"{rel}.npy"), api)
        written = cv2.imread(str(out / f"{rel}.png"), cv2.IMREAD_UNCHANGED)
        assert written.dtype == np.uint16
        np.testing.assert_array_equal(written, depth_mm_to_png16(api))
        valid = np.isfinite(depth) & (depth > 0)
        assert np.all(written[~valid] == 0)  # holes stay invalid
        sigma = np.load(out / f"{rel}_sigma_mm.npy")
        expected = sigma_map_mm(np.where(valid, depth, 0), valid, np.load(amp / f"{rel}.npy"), calib)
        np.testing.assert_array_equal(sigma, expected)
        preview = cv2.imread(str(out / f"{rel}_preview.png"))
        assert preview is not None and preview.shape[1] > 3 * 48
    assert not list(out.rglob(".*.tmp*"))  # atomic writes leave no temporary file


def test_fill_holes_and_depth_scale(frames_dir, restorer_ckpt, tmp_path, capsys):
    src, _ = frames_dir
    out = tmp_path / "filled"
    assert (
        main(
            [
                str(src / "a.png"),
                "--ckpt",
                str(restorer_ckpt),
                "--out",
                str(out),
                "--fill-holes",
                "--npy",
                "--depth-scale-mm",
                "0.5",
                "--quiet",
            ]
        )
        == 0
    )
    depth = read_depth_mm(src / "a.png", scale_mm=0.5)
    expected = tofdenoise.denoise(depth, load_restorer(restorer_ckpt), fill_holes=True)
    np.testing.assert_array_equal(np.load(out / "a.npy"), expected)
    assert np.all(np.load(out / "a.npy")[5:11, 8:16] != 0)


def test_bad_frames_fail_alone_and_are_listed(frames_dir, restorer_ckpt, tmp_path, capsys):
    src, amp = frames_dir
    cv2.imwrite(str(src / "eight.png"), np.full((36, 48), 9, np.uint8))
    cv2.imwrite(str(src / "colour.png"), np.full((36, 48, 3), 900, np.uint16))
    (src / "broken.npy").write_bytes(b"garbage")
    cv2.imwrite(str(src / "odd.png"), frame(4).astype(np.uint16))
    np.save(amp / "odd.npy", np.ones((10, 10), np.float32))  # another shape
    cv2.imwrite(str(src / "noamp.png"), frame(5).astype(np.uint16))
    np.save(amp / "eight.npy", np.ones((36, 48), np.float32))
    np.save(amp / "colour.npy", np.ones((36, 48), np.float32))
    np.save(amp / "broken.npy", np.ones((36, 48), np.float32))
    out = tmp_path / "out"
    code = main([str(src), "--ckpt", str(restorer_ckpt), "--out", str(out), "--amplitude", str(amp), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1
    assert "3 frame(s) done, 0 skipped, 5 failed" in err
    for name, why in (
        ("eight.png", "8-bit"),
        ("colour.png", "channels"),
        ("broken.npy", "could not be read"),
        ("odd.png", "shape"),
        ("noamp.png", "no amplitude file"),
    ):
        line = next(line for line in err.splitlines() if f"FAILED {src / name}" in line)
        assert why in line, line
        assert not (out / f"{Path(name).stem}.png").exists()
    assert (out / "a.png").is_file() and (out / "sub" / "b.png").is_file()


def test_startup_errors_exit_2(frames_dir, restorer_ckpt, tmp_path, capsys, make_restorer_ckpt):
    src, _ = frames_dir
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"zzz")
    assert main([str(src), "--ckpt", str(junk), "--out", str(tmp_path / "o")]) == 2
    assert "junk.ckpt" in capsys.readouterr().err
    signal_ckpt = make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True})
    assert main([str(src), "--ckpt", str(signal_ckpt), "--out", str(tmp_path / "o")]) == 2
    assert "--amplitude" in capsys.readouterr().err
    assert main([str(tmp_path / "nope"), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path / "o")]) == 2
    assert "input not found" in capsys.readouterr().err
    assert main([str(src), "--ckpt", str(restorer_ckpt), "--out", str(tmp_path / "o"), "--sensor", "default"]) == 2
    assert "--sensor needs --amplitude" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_amplitude_folder_inside_the_input_folder_is_not_read_as_depth(frames_dir, restorer_ckpt, tmp_path, capsys):
    src, amp = frames_dir
    inner = src / "amp"
    inner.mkdir()
    for p in amp.rglob("*.npy"):
        target = inner / p.relative_to(amp)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(p.read_bytes())
    out = tmp_path / "out"
    assert main([str(src), "--ckpt", str(restorer_ckpt), "--out", str(out), "--amplitude", str(inner), "--quiet"]) == 0
    assert "3 frame(s) done, 0 skipped, 0 failed" in capsys.readouterr().err
    assert not (out / "amp").exists()


def test_output_never_overwrites_the_input(frames_dir, restorer_ckpt, capsys):
    src, _ = frames_dir
    before = (src / "a.png").read_bytes()
    assert main([str(src / "a.png"), "--ckpt", str(restorer_ckpt), "--out", str(src), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"--out {src / 'a.png'} would replace the input {src / 'a.png'}" in err
    assert (src / "a.png").read_bytes() == before


def test_npy_output_that_would_replace_the_npy_input_is_refused_before_any_write(frames_dir, restorer_ckpt, capsys):
    """issue 23 case 1: --npy f/b.npy --out f wrote the restored map over the input frame, exit 0."""
    src, _ = frames_dir
    folder = src / "sub"
    before = {p: p.read_bytes() for p in folder.iterdir()}
    code = main([str(folder / "b.npy"), "--ckpt", str(restorer_ckpt), "--out", str(folder), "--npy", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "tofdenoise denoise: error: --out" in err
    assert str(folder / "b.npy") in err and "would replace the input" in err
    assert {p: p.read_bytes() for p in folder.iterdir()} == before  # nothing written, nothing replaced


def test_an_output_that_would_replace_another_frames_amplitude_is_refused(frames_dir, restorer_ckpt, tmp_path, capsys):
    src, amp = frames_dir
    before = (amp / "a.npy").read_bytes()
    args = [str(src / "a.png"), "--ckpt", str(restorer_ckpt), "--out", str(amp), "--amplitude", str(amp), "--npy"]
    assert main([*args, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"would replace the input {amp / 'a.npy'}" in err and (amp / "a.npy").read_bytes() == before
    assert not (amp / "a.png").exists()


def test_two_inputs_of_one_output_name_are_refused_before_any_write(frames_dir, restorer_ckpt, tmp_path, capsys):
    """Two cameras' folders numbering their frames alike, or a.png beside a.npy: restoring one and skipping the
    other ended with exit status 0 and half the frames; now exit 2, both inputs named, nothing written."""
    src, _ = frames_dir
    cam_a, cam_b = tmp_path / "camA", tmp_path / "camB"
    for cam in (cam_a, cam_b):
        cam.mkdir()
        (cam / "frame_000.png").write_bytes((src / "a.png").read_bytes())
    out = tmp_path / "out"
    assert main([str(cam_a), str(cam_b), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "tofdenoise denoise: error:" in err
    assert str(cam_a / "frame_000.png") in err and str(cam_b / "frame_000.png") in err and not out.exists()
    np.save(cam_a / "frame_000.npy", np.load(src / "sub" / "b.npy"))  # one folder, one name, two formats
    assert main([str(cam_a), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(cam_a / "frame_000.png") in err and str(cam_a / "frame_000.npy") in err and not out.exists()
    # separate --out folders, as the message says: both restored
    assert main([str(cam_b), "--ckpt", str(restorer_ckpt), "--out", str(out / "b"), "--quiet"]) == 0
    assert "1 frame(s) done, 0 skipped, 0 failed" in capsys.readouterr().err


def test_a_float_frame_in_metres_is_refused_unless_the_scale_is_given(frames_dir, restorer_ckpt, tmp_path, capsys):
    """issue 23 case 4: a float .npy in metres (a Kinect frame / 1000) was written as 0-2 "mm", exit 0."""
    metres = tmp_path / "metres"
    metres.mkdir()
    np.save(metres / "k.npy", (frame(7) / 1000.0).astype(np.float32))
    out = tmp_path / "out"
    assert main([str(metres), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    line = next(line for line in err.splitlines() if "FAILED" in line)
    assert str(metres / "k.npy") in line and "--depth-scale-mm" in line and "implausible in millimetres" in line
    assert not out.exists() or not list(out.rglob("*.png"))
    args = [str(metres), "--ckpt", str(restorer_ckpt), "--out", str(out), "--depth-scale-mm", "1000", "--quiet"]
    assert main(args) == 0
    restored = read_depth_mm(out / "k.png")
    assert np.median(restored[restored > 0]) > 500  # millimetres


def test_a_failed_write_leaves_no_partial_file(frames_dir, restorer_ckpt, tmp_path, monkeypatch, capsys):
    src, _ = frames_dir
    import tofdenoise.atomic as atomic

    real = atomic.os.replace

    def failing_replace(a, b):
        if str(b).endswith("_preview.png"):
            raise OSError("disk full")
        return real(a, b)

    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    out = tmp_path / "out"
    assert main([str(src / "a.png"), "--ckpt", str(restorer_ckpt), "--out", str(out), "--previews", "--quiet"]) == 1
    assert "disk full" in capsys.readouterr().err
    assert not (out / "a_preview.png").exists() and not list(out.glob(".*tmp*"))


def test_the_denoise_verb_runs_this_main():
    from tofdenoise.cli.main import VERBS

    assert VERBS["denoise"].module == "denoise" and VERBS["denoise"].grammar == "options" and callable(main)


def test_time_per_frame_gives_the_first_frame_apart():
    from tofdenoise.cli.denoise import timing_text

    assert timing_text([]) == "n/a s/frame"
    assert timing_text([2.5]) == "2.500 s/frame (one frame, one-time set-up included)"
    # a 40 s first frame (a kernel built on first use) must not read as 14 s/frame
    assert timing_text([40.0, 0.25, 0.35]) == "0.300 s/frame after the first (40.000 s, one-time set-up included)"


def test_ctrl_c_ends_with_a_summary_and_complete_outputs(frames_dir, restorer_ckpt, tmp_path, monkeypatch, capsys):
    """Ctrl-C on the second frame: the first frame's outputs are complete, the summary says what was done and how
    to go on, exit status 130 (128 + SIGINT), no traceback."""
    import tofdenoise.inference.denoise as inference

    src, amp = frames_dir
    real = inference.restore_frame
    calls = []

    def interrupted_on_second(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(inference, "restore_frame", interrupted_on_second)
    out = tmp_path / "out"
    code = main([str(src), "--ckpt", str(restorer_ckpt), "--out", str(out), "--amplitude", str(amp), "--quiet"])
    err = capsys.readouterr().err
    assert code == 130
    assert "interrupted (Ctrl-C) after 1 of 3 frame(s): 1 frame(s) done, 0 skipped, 0 failed" in err
    assert "run the same command again" in err and "Traceback" not in err
    assert (out / "a.png").is_file() and not list(out.rglob(".*tmp*"))


def test_a_short_write_names_the_output_folder_and_the_likely_cause(
    frames_dir, restorer_ckpt, tmp_path, monkeypatch, capsys
):
    """numpy's 'N requested and M written' names no file: the failure line adds the output folder."""
    import tofdenoise.inference.outputs as outputs

    def short_write(*a, **k):
        raise OSError("368640 requested and 55264 written")

    monkeypatch.setattr(outputs, "write_frame_outputs", short_write)
    src, _ = frames_dir
    out = tmp_path / "out"
    assert main([str(src / "a.png"), "--ckpt", str(restorer_ckpt), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert f"could not write its outputs under {out}: 368640 requested and 55264 written (disk full?)" in err


def test_adi_depth_and_ab_files_in_one_folder_pair_by_a_stem_substitution(tmp_path, make_restorer_ckpt, capsys):
    """The ADI ADTF3175D SDK's own names: frame_mode2_depth_NNNNNN.npy with frame_mode2_ab_NNNNNN.npy in one
    folder; a depth frame without its ab file fails alone, with one line naming it and the file looked for."""
    signal_ckpt = make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True})
    adi = tmp_path / "adi"
    adi.mkdir()
    amps = {}
    for i in (7, 8):
        np.save(adi / f"frame_mode2_depth_{i:06d}.npy", frame(i))
        amps[i] = np.random.default_rng(i).uniform(100, 3000, (36, 48)).astype(np.float32)
        np.save(adi / f"frame_mode2_ab_{i:06d}.npy", amps[i])
    np.save(adi / "frame_mode2_depth_000009.npy", frame(9))
    out = tmp_path / "out"
    code = main(
        [str(adi), "--ckpt", str(signal_ckpt), "--out", str(out), "--npy", "--quiet"]
        + ["--amplitude", str(adi / "{stem:depth=ab}.npy")]
    )
    err = capsys.readouterr().err
    assert code == 1 and "2 frame(s) done, 0 skipped, 1 failed" in err, err
    model = load_restorer(signal_ckpt)
    for i in (7, 8):
        expected = tofdenoise.denoise(frame(i), model, amplitude=amps[i])
        np.testing.assert_array_equal(np.load(out / f"frame_mode2_depth_{i:06d}.npy"), expected)
    assert not list(out.glob("frame_mode2_ab_*"))
    failed = [line for line in err.splitlines() if "FAILED" in line]
    assert len(failed) == 1
    assert str(adi / "frame_mode2_depth_000009.npy") in failed[0]
    assert str(adi / "frame_mode2_ab_000009.npy") in failed[0]


def test_ply_from_the_kinects_own_calibration_json(tmp_path, restorer_ckpt, capsys):
    """--intrinsics takes the Azure Kinect's calibration.json: a 320 x 288 frame (NFOV 2x2 binned) gets that depth
    mode's intrinsics, computed here by hand from the unitised parameters."""
    import json

    params = [0.5, 0.51, 0.49, 0.492, 0.6, -2.9, 1.6, 0.5, -2.7, 1.5, 0.0, 0.0, -1e-4, 5e-5]
    depth_camera = {
        "Intrinsics": {"ModelParameterCount": 14, "ModelParameters": params, "ModelType": "BrownConrady"},
        "Location": "CALIBRATION_CameraLocationD0",
        "MetricRadius": 1.74,
        "SensorHeight": 1024,
        "SensorWidth": 1024,
    }
    calibration = tmp_path / "calibration.json"
    calibration.write_text(json.dumps({"CalibrationInformation": {"Cameras": [depth_camera]}}))
    d = frame(3, 288, 320)
    cv2.imwrite(str(tmp_path / "k.png"), d.astype(np.uint16))
    out = tmp_path / "out"
    args = [str(tmp_path / "k.png"), "--ckpt", str(restorer_ckpt), "--out", str(out), "--npy", "--ply", "--quiet"]
    assert main([*args, "--intrinsics", str(calibration)]) == 0, capsys.readouterr().err
    data = (out / "k.ply").read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    points = np.frombuffer(data[end:], dtype="<f4").reshape(-1, 3)
    restored_m = np.load(out / "k.npy").astype(np.float64) / 1000.0
    v, u = np.nonzero(restored_m > 0)
    z = restored_m[v, u]
    fx, fy, cx, cy = 0.49 * 512, 0.492 * 512, 0.5 * 512 - 96 - 0.5, 0.51 * 512 - 90 - 0.5
    expected = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=1)
    np.testing.assert_allclose(points, expected, rtol=1e-6, atol=1e-7)


def test_frames_mostly_outside_the_training_depths_are_named_in_the_summary(tmp_path, restorer_ckpt, capsys):
    """A checkpoint records the depths it was trained on; a frame whose valid depths lie mostly beyond them (an
    ADI ADTF3175D frame reaching 7.5 m) is restored and named in the summary; one inside is not. A checkpoint
    without the record says the range is unknown."""
    import torch

    from tofdenoise.training.depth_range import DEPTH_RANGE_KEY, TrainingDepthRange

    trained = TrainingDepthRange()
    depths = torch.from_numpy(np.random.default_rng(0).uniform(300, 2400, (4, 1, 64, 64)).astype(np.float32))
    trained.update(depths, torch.ones_like(depths))
    content = torch.load(restorer_ckpt, map_location="cpu", weights_only=True)
    content[DEPTH_RANGE_KEY] = trained.record()
    ckpt = tmp_path / "ranged.ckpt"
    torch.save(content, ckpt)
    src = tmp_path / "frames"
    src.mkdir()
    np.save(src / "near.npy", frame(0))
    y, x = np.mgrid[0:36, 0:48]
    far = (5000.0 + 50 * x + 10 * y).astype(np.float32)  # 5.0-7.7 m
    far[:4, :4] = 1200.0
    np.save(src / "far.npy", far)
    args = [str(src), "--out", str(tmp_path / "out"), "--depth-scale-mm", "1", "--quiet"]
    assert main([*args, "--ckpt", str(ckpt)]) == 0
    err = capsys.readouterr().err
    assert "2 frame(s) done" in err
    lines = [line.strip() for line in err.splitlines()]
    low, high = trained.range_mm
    assert f"trained on depths {low:.0f}-{high:.0f} mm: 1 frame(s) lie mostly outside them" in lines
    outside = [line for line in lines if line.startswith("outside the training depths")]
    assert len(outside) == 1 and str(src / "far.npy") in outside[0]
    assert "99 % of its valid depths" in outside[0] and "extrapolation" in outside[0]
    assert (tmp_path / "out" / "far.png").is_file()
    # a checkpoint without the record: the range is unknown, the frames are restored all the same
    assert main([*args[:1], "--out", str(tmp_path / "out2"), *args[3:], "--ckpt", str(restorer_ckpt)]) == 0
    err = capsys.readouterr().err
    assert "does not record the depths it was trained on" in err and "outside the training depths" not in err


def test_the_summary_says_whether_the_frames_ran_whole_or_in_tiles(frames_dir, restorer_ckpt, tmp_path, capsys):
    src, amp = frames_dir
    args = [str(src), "--ckpt", str(restorer_ckpt), "--amplitude", str(amp), "--quiet"]
    assert main([*args, "--out", str(tmp_path / "whole")]) == 0
    lines = [line.strip() for line in capsys.readouterr().err.splitlines()]
    tiling = [line for line in lines if line.startswith("tiling:")]
    assert len(tiling) == 1 and tiling[0].startswith("tiling: 3 whole frame(s) (the largest, 48 x 36, needs about ")
    assert " budget)" in tiling[0] or "memory budget unknown" in tiling[0]
    assert main([*args, "--out", str(tmp_path / "tiles"), "--tile", "40"]) == 0
    lines = [line.strip() for line in capsys.readouterr().err.splitlines()]
    assert "tiling: 3 frame(s) in tiles of 40 px (--tile 40)" in lines
    # a tile that leaves no stride on the backbone's multiple (4) after the overlap (32 px) is refused up front,
    # not frame by frame
    assert main([*args, "--out", str(tmp_path / "bad"), "--tile", "35"]) == 2
    err = capsys.readouterr().err
    assert "--tile must be at least 36 px for this checkpoint (its tile overlap tiling.overlap_px = 32" in err
    assert "padding multiple of 4 px" in err and "got 35" in err
    assert not (tmp_path / "bad").exists()
