"""`tofdenoise sensor simulate-captures` / `build-reference` end to end on tiny sizes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tofdenoise.cli.sensor import main


def run(argv):
    return main([str(a) for a in argv])


def simulate_args(out, scenes: int) -> list:
    """`simulate-captures` at the tiny size of these tests (6 frames of 24 x 32, seed 3), one scene at a time (the
    default is one per CPU core; the parallel run below is compared with this one)."""
    return [
        "simulate-captures",
        "--workers",
        1,
        "--out",
        out,
        "--scenes",
        scenes,
        "--frames",
        6,
        "--height",
        24,
        "--width",
        32,
        "--seed",
        3,
        "--quiet",
    ]


def test_simulate_captures_writes_the_documented_format(tmp_path, capsys):
    out = tmp_path / "set"
    assert run(simulate_args(out, scenes=2)) == 0
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
    assert run(simulate_args(out, scenes=2)) == 0
    assert "0 scene(s) written, 2 already complete" in capsys.readouterr().out
    again = tmp_path / "again"
    run(simulate_args(again, scenes=1))
    np.testing.assert_array_equal(cv2.imread(str(again / "scene_0000" / "input_depth_mm.png"), -1), depth)
    # --workers: the same scenes from two processes; a count below 1 exits 2 naming the option
    parallel = tmp_path / "parallel"
    assert run([*simulate_args(parallel, scenes=2), "--workers", 2]) == 0
    assert "2 scene(s) written" in capsys.readouterr().out
    for name in ("scene_0000", "scene_0001"):
        assert (parallel / name / "input_depth_mm.png").read_bytes() == (out / name / "input_depth_mm.png").read_bytes()
    assert run([*simulate_args(tmp_path / "bad", scenes=1), "--workers", 0]) == 2
    assert "--workers must be an integer >= 1, got 0" in capsys.readouterr().err


def test_build_reference_command(tmp_path, capsys):
    out = tmp_path / "set"
    run(["simulate-captures", "--out", out, "--scenes", 2, "--frames", 4, "--height", 16, "--width", 16, "--quiet"])
    capsys.readouterr()
    assert run(["build-reference", out]) == 0
    text = capsys.readouterr().out
    assert "2 scene(s): 0 reference(s) rebuilt, 2 up to date" in text
    # a larger threshold than the cache's (2 of 4 frames) is derived from it exactly, nothing rebuilt or rewritten
    cached = (out / "scene_0000" / "reference.json").read_bytes()
    assert run(["build-reference", out, "--min-count", 4]) == 0
    text = capsys.readouterr().out
    assert "scene_0000: up to date (min_count 4 from the cached reference at min_count 2, exactly; --force" in text
    assert "2 scene(s): 0 reference(s) rebuilt, 2 up to date" in text
    assert (out / "scene_0000" / "reference.json").read_bytes() == cached
    assert run(["build-reference", out, "--min-count", 4, "--force", "--quiet"]) == 0
    assert "2 reference(s) rebuilt" in capsys.readouterr().out
    assert run(["build-reference", out / "scene_0001", "--force", "--quiet"]) == 0  # one scene folder
    assert "1 scene(s): 1 reference(s) rebuilt" in capsys.readouterr().out


def test_build_reference_bad_folder(tmp_path, capsys):
    assert run(["build-reference", tmp_path / "missing"]) == 2
    assert "SCENES_DIR" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run(["simulate-captures"])  # --out is required


def test_simulate_calibration_then_calibrate_recovers_the_camera(tmp_path, capsys):
    """Step a) + b) of docs/camera-tutorial.md: the second camera's calibration captures (sweep, 100 dark frames,
    distance sequence) in the capture format, then `calibrate` recovers that camera, not the default one."""
    from tofdenoise.physics.calibration import load_calibration, resolve_calibration
    from tofdenoise.physics.capture_io import read_index

    caps = tmp_path / "caps"
    assert (
        run(
            [
                "simulate-calibration",
                "--sensor",
                "cam75",
                "--out",
                caps,
                "--sweep-steps",
                16,
                "--sweep-frames",
                8,
                "--distance-frames",
                30,
                "--size",
                8,
            ]
        )
        == 0
    )
    assert "next: tofdenoise sensor calibrate" in capsys.readouterr().out
    assert read_index(caps / "sweep", "sweep").modulation_frequency_hz == 75e6
    dark = read_index(caps / "dark", "dark")
    assert dark.units == "dn" and dark.adc_gain_e_per_dn == 4.0
    assert np.load(caps / "dark" / dark.stacks[0]["file"]).shape == (100, 4, 8, 8)  # 100 dark frames
    distances = [e["distance_mm"] for e in read_index(caps / "distances", "distances").stacks]
    # the working range, 300 mm to 80 % of the unambiguous range (1999 mm): a grey chart at each distance
    assert len(distances) == 10 and min(distances) == 300 and max(distances) == 1599
    out = tmp_path / "calibration.yaml"
    assert (
        run(
            [
                "calibrate",
                "--sweep",
                caps / "sweep",
                "--dark",
                caps / "dark",
                "--distances",
                caps / "distances",
                "--out",
                out,
            ]
        )
        == 0
    )
    got, true = load_calibration(out), resolve_calibration("cam75")
    assert got.modulation_frequency_hz == true.modulation_frequency_hz
    assert got.tap_response.contrast == pytest.approx(true.tap_response.contrast, abs=0.01)
    np.testing.assert_allclose(got.tap_response.cos[:2], true.tap_response.cos, atol=5e-3)  # 2nd harmonic
    np.testing.assert_allclose(got.tap_response.sin[:2], true.tap_response.sin, atol=5e-3)
    assert got.dark_mean_e == pytest.approx(true.dark_mean_e, rel=0.01)
    assert got.dark_std_e == pytest.approx(true.dark_std_e, rel=0.05)
    assert got.adc_gain_e_per_dn == true.adc_gain_e_per_dn and got.full_well_e == true.full_well_e
    assert got.range_sigma_mm is not None
    capsys.readouterr()
    assert run(["simulate-calibration", "--sensor", "cam75", "--out", caps, "--distances-mm", 500, 2500]) == 2
    assert "unambiguous range" in capsys.readouterr().err


def _mixed_pixel_set_argv(out, factor):
    """simulate-captures of the small cam75 set the mixed-pixel test compares, with --mixed-pixels factor."""
    return [
        "simulate-captures",
        "--out",
        out,
        "--scenes",
        2,
        "--frames",
        6,
        "--height",
        40,
        "--width",
        56,
        "--seed",
        5,
        "--sensor",
        "cam75",
        "--mixed-pixels",
        factor,
        "--quiet",
    ]


def test_mixed_pixels_bias_the_captured_depth_at_edges(tmp_path):
    """Step c): with --mixed-pixels 3 the pixels whose footprint spans a depth edge are flying pixels in the input
    and in the reference (a mix of both surfaces); elsewhere, and without mixing, they follow the ground truth."""
    import json

    from tofdenoise.data_modules.sources.procedural import ProceduralSource
    from tofdenoise.physics.calibration import resolve_calibration
    from tofdenoise.physics.mixed_pixels import mixed_pixel_map

    source = ProceduralSource(
        num_samples=2, height=40, width=56, seed=5, max_depth_mm=0.8 * resolve_calibration("cam75").unambiguous_range_mm
    )
    errors = {}
    for factor in (1, 3):
        out = tmp_path / f"set{factor}"
        assert run(_mixed_pixel_set_argv(out, factor)) == 0
        at_edges, elsewhere = [], []
        for scene in sorted(out.glob("scene_*")):
            info = json.loads((scene / "scene.json").read_text())
            assert info["mixed_pixels"] == factor
            gt = np.load(scene / "ground_truth_depth_mm.npy")
            ref = np.load(scene / "reference_depth_mm.npy")
            fine = source.supersampled(3).load(f"scene_{info['scene_index']:06d}")
            fine_depth = np.where(fine.valid, fine.depth_mm, 0)
            ok = np.isfinite(ref) & np.isfinite(gt)
            at_edges.append(np.abs(ref - gt)[ok & mixed_pixel_map(fine_depth, 3, rel_jump=0.2)])
            elsewhere.append(np.abs(ref - gt)[ok & ~mixed_pixel_map(fine_depth, 3)])
        errors[factor] = (float(np.median(np.concatenate(at_edges))), float(np.median(np.concatenate(elsewhere))))
    assert errors[3][0] > 5 * errors[1][0], errors  # flying pixels at depth edges
    assert errors[3][0] > 10 * errors[3][1], errors
    assert errors[3][1] < 2 * errors[1][1] + 1.0, errors  # smooth regions: mixing changes (almost) nothing
    # another --mixed-pixels is another set: the completed scenes are simulated again, not reused
    out = tmp_path / "set1"
    assert run(_mixed_pixel_set_argv(out, 3)) == 0
    assert json.loads((out / "scene_0000" / "scene.json").read_text())["mixed_pixels"] == 3
    assert run(["simulate-captures", "--out", out, "--scenes", 1, "--frames", 2, "--mixed-pixels", 0]) == 2


@pytest.mark.parametrize("command", ["simulate-calibration", "simulate-captures", "simulate-validation", "realset"])
def test_simulations_refuse_an_output_folder_that_holds_their_camera_file(tmp_path, capsys, command):
    from tofdenoise.physics.calibration import resolve_calibration, save_calibration

    camera = save_calibration(resolve_calibration("cam75"), tmp_path / "out" / "calibration.yaml")
    before = camera.read_bytes()
    option = "--sensor"
    small = {  # tiny sizes: on a command without the guard the run must end soon (and fail the test)
        "simulate-calibration": ["--sweep-steps", "2", "--sweep-frames", "2", "--dark-frames", "2", "--size", "2"],
        "simulate-captures": ["--scenes", "1", "--frames", "2", "--height", "8", "--width", "8", "--quiet"],
        "simulate-validation": ["--frames", "2", "--roi-px", "2"],
        "realset": ["--scenes", "1", "--frames", "2", "--height", "8", "--width", "8"],
    }[command]
    assert main([command, option, str(camera), "--out", str(tmp_path / "out"), *small]) == 2
    err = capsys.readouterr().err
    assert f"holds the input {camera}" in err and camera.read_bytes() == before
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["calibration.yaml"]  # nothing written
