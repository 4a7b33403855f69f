"""`tofdenoise-sensor simulate-captures` / `build-reference` end to end on tiny sizes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tofdenoise.cli.sensor import main


def run(argv):
    return main([str(a) for a in argv])


def test_simulate_captures_writes_the_documented_format(tmp_path, capsys):
    out = tmp_path / "set"
    assert run(["simulate-captures", "--out", out, "--scenes", 2, "--frames", 6, "--height", 24, "--width", 32,
                "--seed", 3, "--quiet"]) == 0
    assert "2 scene(s) written" in capsys.readouterr().out
    readme = (out / "README.md").read_text()
    assert "Simulated" in readme and "NOT real data" in readme
    scene = out / "scene_0000"
    depth = cv2.imread(str(scene / "input_depth_mm.png"), cv2.IMREAD_UNCHANGED)
    amp = cv2.imread(str(scene / "input_amplitude.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and depth.shape == (24, 32) and amp.dtype == np.uint16
    for k in range(6):
        assert cv2.imread(str(scene / "hiexp" / f"depth_mm_{k:03d}.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
        assert cv2.imread(str(scene / "hiexp" / f"saturated_{k:03d}.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint8
    ref = np.load(scene / "reference_depth_mm.npy")
    gt = np.load(scene / "ground_truth_depth_mm.npy")
    assert ref.dtype == np.float32
    valid = (depth > 0) & np.isfinite(ref)
    input_error = np.abs(depth[valid] - gt[valid]).mean()
    reference_error = np.abs(ref[valid] - gt[valid]).mean()
    assert input_error > 1.0  # a noisy input (tap-level shot/read noise, quantisation)
    assert reference_error < 0.7 * input_error  # averaged high-exposure frames are cleaner
    # same seed -> same set; resumable: completed scenes are skipped
    assert run(["simulate-captures", "--out", out, "--scenes", 2, "--frames", 6, "--height", 24, "--width", 32,
                "--seed", 3, "--quiet"]) == 0
    assert "0 scene(s) written, 2 already complete" in capsys.readouterr().out
    again = tmp_path / "again"
    run(["simulate-captures", "--out", again, "--scenes", 1, "--frames", 6, "--height", 24, "--width", 32,
         "--seed", 3, "--quiet"])
    np.testing.assert_array_equal(cv2.imread(str(again / "scene_0000" / "input_depth_mm.png"), -1), depth)


def test_build_reference_command(tmp_path, capsys):
    out = tmp_path / "set"
    run(["simulate-captures", "--out", out, "--scenes", 2, "--frames", 4, "--height", 16, "--width", 16, "--quiet"])
    capsys.readouterr()
    assert run(["build-reference", out]) == 0
    text = capsys.readouterr().out
    assert "2 scene(s): 0 reference(s) rebuilt, 2 up to date" in text
    assert run(["build-reference", out, "--min-count", 4, "--quiet"]) == 0
    assert "2 reference(s) rebuilt" in capsys.readouterr().out
    assert run(["build-reference", out / "scene_0001", "--force", "--quiet"]) == 0  # one scene folder
    assert "1 scene(s): 1 reference(s) rebuilt" in capsys.readouterr().out


def test_build_reference_bad_folder(tmp_path, capsys):
    assert run(["build-reference", tmp_path / "missing"]) == 2
    assert "SCENES_DIR" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run(["simulate-captures"])  # --out is required
