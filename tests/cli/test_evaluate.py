"""tofdenoise evaluate: hand-computed metrics from files, validity rules, and errors that name the file."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tofdenoise.cli.evaluate import main
from tofdenoise.evaluation import evaluate_dirs


def _png16(path: Path, depth_mm: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), depth_mm.astype(np.uint16))


def _npy(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, arr)


@pytest.fixture
def dirs(tmp_path):
    ref = np.full((20, 30), 1000.0)
    ref[0, :] = 0  # invalid reference row (30 px)
    _png16(tmp_path / "ref" / "a.png", ref)
    ref_b = np.where(ref > 0, ref + 500, 0)
    _png16(tmp_path / "ref" / "b.png", ref_b)
    pa = ref + 2.0
    pa[5, 5] = np.nan  # a non-finite prediction pixel does not count
    _npy(tmp_path / "pred" / "a.npy", pa)
    _png16(tmp_path / "pred" / "b.png", ref_b + 10)  # 10 mm off, also where the reference is invalid
    return tmp_path


def test_metrics_from_png_and_npy_files(dirs):
    out = dirs / "res" / "eval.json"
    assert main(["--pred", str(dirs / "pred"), "--ref", str(dirs / "ref"), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert set(res["mean"]) == {"psnr_db", "mae_mm", "mse_mm2", "ssim"}
    a, b = res["images"]["a"], res["images"]["b"]
    assert a["valid_px"] == 20 * 30 - 30 - 1 and b["valid_px"] == 20 * 30 - 30
    assert a["mae_mm"] == pytest.approx(2.0) and a["mse_mm2"] == pytest.approx(4.0)
    assert b["mae_mm"] == pytest.approx(10.0) and b["psnr_db"] == pytest.approx(40.0)
    assert res["mean"]["mae_mm"] == pytest.approx(6.0)
    assert res["mean"]["psnr_db"] == pytest.approx((10 * math.log10(1e6 / 4) + 40.0) / 2)
    assert res["mae_mm_pooled"] == pytest.approx((2.0 * 569 + 10.0 * 570) / (569 + 570))
    assert res["mean"]["mae_mm"] != pytest.approx(res["mae_mm_pooled"])
    assert res["num_images"] == 2 and res["skipped"] == []
    assert 0.9 < res["mean"]["ssim"] <= 1.0


def test_mask_folder_restricts_pixels_and_empty_images_are_skipped(dirs):
    mask_a = np.zeros((20, 30), np.uint8)
    mask_a[10:, :] = 255
    _png16(dirs / "mask" / "b.png", np.zeros((20, 30)))  # nothing to evaluate in b
    assert cv2.imwrite(str(dirs / "mask" / "a.png"), mask_a)
    res = evaluate_dirs(dirs / "pred", dirs / "ref", dirs / "mask")
    assert res["images"]["a"]["valid_px"] == 10 * 30
    assert res["images"]["b"]["valid_px"] == 0 and res["images"]["b"]["mae_mm"] is None
    assert res["skipped"] == ["b"] and res["num_images"] == 1
    assert res["mean"]["mae_mm"] == pytest.approx(2.0)


def _err(dirs, capsys, *extra) -> str:
    rc = main(["--pred", str(dirs / "pred"), "--ref", str(dirs / "ref"), "--out", str(dirs / "o.json"), *extra])
    assert rc == 2
    assert not (dirs / "o.json").exists()
    return capsys.readouterr().err


def test_missing_and_extra_counterparts_are_named(dirs, capsys):
    (dirs / "pred" / "b.png").unlink()
    err = _err(dirs, capsys)
    assert "no prediction for reference file" in err and str(dirs / "ref" / "b.png") in err
    _png16(dirs / "pred" / "b.png", np.full((20, 30), 1000.0))
    _png16(dirs / "pred" / "c.png", np.full((20, 30), 1000.0))
    assert "c.png has no reference counterpart" in _err(dirs, capsys)


def test_shape_mismatch_names_both_files(dirs, capsys):
    _png16(dirs / "pred" / "b.png", np.full((20, 31), 1000.0))
    err = _err(dirs, capsys)
    assert "b.png has shape (20, 31)" in err and "ref/b.png" in err


def test_8bit_png_depth_is_rejected(dirs, capsys):
    assert cv2.imwrite(str(dirs / "pred" / "b.png"), np.full((20, 30), 200, np.uint8))
    err = _err(dirs, capsys)
    assert "b.png" in err and "uint8" in err and "uint16" in err


def test_unreadable_file_and_empty_dir_and_duplicate_stems(dirs, capsys):
    (dirs / "pred" / "b.png").write_bytes(b"not a png at all")
    assert "b.png could not be decoded" in _err(dirs, capsys)
    _png16(dirs / "pred" / "b.png", np.full((20, 30), 1000.0))
    _npy(dirs / "pred" / "b.npy", np.full((20, 30), 1000.0))
    assert "two files for 'b'" in _err(dirs, capsys)
    shutil.rmtree(dirs / "pred")
    (dirs / "pred").mkdir()
    assert "holds no depth file" in _err(dirs, capsys)
    shutil.rmtree(dirs / "pred")
    assert "prediction folder not found" in _err(dirs, capsys)


def test_boolean_npy_is_a_dtype_error(dirs, capsys):
    (dirs / "pred" / "a.npy").unlink()
    _npy(dirs / "pred" / "a.npy", np.ones((20, 30), bool))
    assert "a.npy is boolean" in _err(dirs, capsys)


def test_the_evaluate_verb_runs_this_main(capsys):
    """``tofdenoise evaluate`` is this module's ``main`` (tests/cli/test_main.py checks every verb)."""
    from tofdenoise.cli.main import VERBS
    from tofdenoise.cli.main import main as tofdenoise

    assert VERBS["evaluate"].module == "evaluate" and VERBS["report"].module == "report"
    with pytest.raises(SystemExit) as exc:
        tofdenoise(["evaluate", "--help"])
    assert exc.value.code == 0 and "usage: tofdenoise evaluate" in capsys.readouterr().out


@pytest.mark.parametrize("out", ["pred/b.png", "pred/b.json", "ref/a.png", "result.png", "pred"])
def test_out_that_would_replace_an_input_is_refused(dirs, capsys, out):
    before = {p: p.read_bytes() for p in dirs.rglob("*") if p.is_file()}
    assert main(["--pred", str(dirs / "pred"), "--ref", str(dirs / "ref"), "--out", str(dirs / out)]) == 2
    err = capsys.readouterr().err
    assert "tofdenoise evaluate: error: --out" in err and str(dirs / out) in err and "Traceback" not in err
    assert {p: p.read_bytes() for p in dirs.rglob("*") if p.is_file()} == before


def test_nan_predictions_are_counted_as_failures_not_rewards(tmp_path, capsys):
    ref = np.full((10, 10), 1000.0)
    good = ref + 4.0
    good[:5] = ref[:5] + 40.0  # the hard half: 40 mm off
    _png16(tmp_path / "ref" / "s0.png", ref)
    _png16(tmp_path / "ref" / "s1.png", ref)
    _npy(tmp_path / "honest" / "s0.npy", good)
    _npy(tmp_path / "honest" / "s1.npy", good)
    cheat = good.copy()
    cheat[:5] = np.nan  # gives up where it is hard
    _npy(tmp_path / "cheat" / "s0.npy", cheat)
    _npy(tmp_path / "cheat" / "s1.npy", np.full_like(ref, np.nan))  # gives up everywhere

    honest = evaluate_dirs(tmp_path / "honest", tmp_path / "ref")
    assert honest["nan_px"] == 0 and honest["failed"] == [] and honest["mean"]["mae_mm"] == pytest.approx(22.0)
    assert (
        main(["--pred", str(tmp_path / "cheat"), "--ref", str(tmp_path / "ref"), "--out", str(tmp_path / "cheat.json")])
        == 0
    )
    err = capsys.readouterr().err
    assert "warning: 150 pixel(s)" in err and "2 image(s)" in err and "failed" in err
    res = json.loads((tmp_path / "cheat.json").read_text())
    assert res["nan_px"] == 150
    assert res["images"]["s0"]["nan_px"] == 50 and res["images"]["s0"]["valid_px"] == 50
    assert res["images"]["s0"]["mae_mm"] == pytest.approx(4.0)
    # the all-NaN image is a failure row (not "skipped", which means no valid reference pixel)
    assert res["failed"] == ["s1"] and res["skipped"] == []
    assert res["images"]["s1"]["nan_px"] == 100 and res["images"]["s1"]["mae_mm"] is None
    assert res["num_images"] == 1


def test_holes_of_a_prediction_file_are_missing_depth_not_a_depth_of_zero(tmp_path, capsys):
    """0 in a 16-bit PNG (what ``tofdenoise denoise`` writes at its holes) and 0 or below in a float map are pixels
    without a prediction: the same result as NaN there (counted in nan_px, left out, warned), never |0 - ref|."""
    ref = np.full((10, 10), 1000.0)
    pred = ref + 4.0
    pred[:3] = 0  # 30 holes where the reference is valid
    _png16(tmp_path / "ref" / "s0.png", ref)
    _png16(tmp_path / "png" / "s0.png", pred)
    _npy(tmp_path / "npy" / "s0.npy", np.where(pred > 0, pred, -1.0))  # a float map marking holes below 0
    _npy(tmp_path / "nan" / "s0.npy", np.where(pred > 0, pred, np.nan))
    results = {name: evaluate_dirs(tmp_path / name, tmp_path / "ref") for name in ("png", "npy", "nan")}
    for name, res in results.items():
        row = res["images"]["s0"]
        assert (row["valid_px"], row["nan_px"], res["nan_px"]) == (70, 30, 30), name
        assert row["mae_mm"] == pytest.approx(4.0), name  # scored as 0 mm, the 30 holes gave (30 * 1000 + 280) / 100
    out = tmp_path / "png.json"
    assert main(["--pred", str(tmp_path / "png"), "--ref", str(tmp_path / "ref"), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "warning: 30 pixel(s) to evaluate hold no predicted depth" in captured.err and "s0" in captured.err
    assert "30 px without a predicted depth" in captured.out
    # a prediction without a depth anywhere it is scored is a failure row, not an image scored at 1000 mm
    _png16(tmp_path / "empty" / "s0.png", np.zeros_like(ref))
    empty = evaluate_dirs(tmp_path / "empty", tmp_path / "ref")
    assert empty["failed"] == ["s0"] and empty["num_images"] == 0 and empty["images"]["s0"]["mae_mm"] is None


def test_sub_folders_are_matched_by_their_path_as_denoise_mirrors_them(tmp_path, capsys):
    """``tofdenoise denoise`` mirrors its inputs' sub-folders under --out; evaluate pairs every file by its path
    below the folder (no file left out), and a missing counterpart in a sub-folder is an error naming it."""
    ref = np.full((8, 8), 1000.0)
    for name, off in (("s0", 1.0), ("day1/s0", 3.0), ("day1/s1", 5.0)):
        _png16(tmp_path / "ref" / f"{name}.png", ref)
        _npy(tmp_path / "pred" / f"{name}.npy", ref + off)
    res = evaluate_dirs(tmp_path / "pred", tmp_path / "ref")
    assert res["num_images"] == 3 and sorted(res["images"]) == ["day1/s0", "day1/s1", "s0"]
    assert res["images"]["day1/s1"]["mae_mm"] == pytest.approx(5.0) and res["mean"]["mae_mm"] == pytest.approx(3.0)
    (tmp_path / "pred" / "day1" / "s1.npy").unlink()
    out = tmp_path / "eval.json"
    assert main(["--pred", str(tmp_path / "pred"), "--ref", str(tmp_path / "ref"), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no prediction for reference file" in err and "day1/s1" in err and not out.exists()


def test_a_checkpoint_on_a_capture_set_scores_the_reference_as_its_run_did_and_the_truth(
    tmp_path, capsys, data_cache, tiny
):
    """``--ckpt --captures --sensor``: against the references it gives the run's own ``real`` test numbers exactly,
    with the run's ``data.real_min_count`` (1 here, not the default 2 of 4 frames: 5 pixels of scene_0001 have one
    valid frame); ``--min-count`` scores with another without rewriting the cached reference; against the simulated
    set's rendered truth, the per-image MAE computed here by hand from the public ``denoise`` API. A set whose scenes
    lack the truth gives ``truth: null``; a set with it in some scenes only, or a wrong combination of options,
    exits 2 naming what is wrong."""
    from tofdenoise.cli.sensor import main as sensor_main
    from tofdenoise.cli.train import run
    from tofdenoise.config import compose_config
    from tofdenoise.data_modules.real_captures import load_real_scene
    from tofdenoise.inference.denoise import denoise, load_restorer
    from tofdenoise.physics.calibration import load_calibration

    realset, run_dir = tmp_path / "realset", tmp_path / "run"
    args = ["realset", "--out", str(realset), "--scenes", "2", "--frames", "4", "--height", "32", "--width", "48"]
    assert sensor_main(args) == 0
    captures, sensor = realset / "captures", realset / "calibration.yaml"
    for k in (1, 2, 3):  # a block of 32 pixels valid in the first of the 4 frames only, in both scenes
        for scene in ("scene_0000", "scene_0001"):
            path = captures / scene / "hiexp" / f"depth_mm_{k:03d}.png"
            depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            depth[10:14, 10:18] = 0
            assert cv2.imwrite(str(path), depth)
    overrides = [f"++data.sensor={sensor}", f"++data.real_dir={captures}", "trainer.max_epochs=1", "logger=csv"]
    run(compose_config(tiny(run_dir, data_cache) + overrides + ["++data.real_min_count=1"]))
    recorded = json.loads((run_dir / "metrics.json").read_text())["real"]
    ckpt, out = run_dir / "checkpoints" / "best.ckpt", tmp_path / "eval.json"
    capsys.readouterr()

    assert main(["--ckpt", str(ckpt), "--captures", str(captures), "--sensor", str(sensor), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "2 images (0 without valid pixels) against the references (a reference pixel needs 1 frames valid; " in (
        printed
    )
    assert "2 images against the rendered truth (a simulated set)" in printed
    result = json.loads(out.read_text())
    assert result["scenes"] == 2 and result["checkpoint"] == str(ckpt)
    assert result["min_count"] == {"value": 1, "from": f"{ckpt} (data.real_min_count of its run)"}
    assert sum(row["valid_px"] for row in result["reference"]["images"].values()) == recorded["valid_px"]
    for key in ("psnr_db", "mae_mm", "mse_mm2", "ssim"):
        assert result["reference"]["mean"][key] == pytest.approx(recorded[key], rel=1e-9, abs=1e-9)
    model, calib = load_restorer(ckpt, "cpu"), load_calibration(sensor)
    # --min-count 4: fewer reference pixels, from the same cache (derived, not rewritten)
    caches = {p: p.read_bytes() for p in captures.glob("*/reference*")}
    strict = tmp_path / "strict.json"
    argv = ["--ckpt", str(ckpt), "--captures", str(captures), "--sensor", str(sensor), "--min-count", "4"]
    assert main([*argv, "--out", str(strict)]) == 0
    strict_result = json.loads(strict.read_text())
    assert strict_result["min_count"] == {"value": 4, "from": "--min-count"}
    assert {p: p.read_bytes() for p in caches} == caches
    for scene in sorted(p for p in captures.iterdir() if p.is_dir()):
        masks = [(load_real_scene(scene, calib, m)["mask"] > 0).sum() for m in (1, 2, 4)]
        assert result["reference"]["images"][scene.name]["valid_px"] == masks[0]
        assert strict_result["reference"]["images"][scene.name]["valid_px"] == masks[2]
    fewer = [
        result["reference"]["images"][n]["valid_px"] - r["valid_px"]
        for n, r in strict_result["reference"]["images"].items()
    ]
    assert min(fewer) >= 30  # the block of one valid frame (less its invalid input pixels), and a few more
    assert main([*argv[:-1], "0", "--out", str(strict)]) == 2
    assert "--min-count must be >= 1, got 0" in capsys.readouterr().err
    for scene in sorted(p for p in captures.iterdir() if p.is_dir()):
        sample = load_real_scene(scene, calib, 1)
        pred = denoise(sample["noisy"], model, amplitude=sample["amplitude"], device="cpu")
        truth = np.load(scene / "ground_truth_depth_mm.npy")
        scored = (sample["mask"] > 0) & np.isfinite(truth) & (truth > 0)
        row = result["truth"]["images"][scene.name]
        assert row["valid_px"] == int(scored.sum()) > 0
        assert row["mae_mm"] == pytest.approx(float(np.abs(pred[scored] - truth[scored]).mean()), rel=1e-5)
        # the references and the input frames against the same truth pixels
        ref_row = result["reference_vs_truth"]["images"][scene.name]
        ref_mae = float(np.abs(sample["clean"][scored] - truth[scored]).mean())
        assert ref_row["valid_px"] == row["valid_px"] and ref_row["mae_mm"] == pytest.approx(ref_mae, rel=1e-6)
        in_mae = float(np.abs(sample["noisy"][scored] - truth[scored]).mean())
        assert result["input"]["truth"]["images"][scene.name]["mae_mm"] == pytest.approx(in_mae, rel=1e-6)
    # the input against the references: the run's raw numbers
    assert result["input"]["reference"]["mean"]["mae_mm"] == pytest.approx(recorded["raw"]["mae_mm"], rel=1e-9)
    assert result["truth"]["mean"]["mae_mm"] > 0

    # the truth in one scene only: an error naming the scenes without it, nothing written
    (captures / "scene_0001" / "ground_truth_depth_mm.npy").unlink()
    out2 = tmp_path / "eval2.json"
    assert main(["--ckpt", str(ckpt), "--captures", str(captures), "--sensor", str(sensor), "--out", str(out2)]) == 2
    err = capsys.readouterr().err
    assert "1 of 2 scene(s) have no ground_truth_depth_mm.npy (scene_0001)" in err and not out2.exists()
    # no truth at all (a real camera's set): the reference score only
    (captures / "scene_0000" / "ground_truth_depth_mm.npy").unlink()
    assert main(["--ckpt", str(ckpt), "--captures", str(captures), "--sensor", str(sensor), "--out", str(out2)]) == 0
    no_truth = json.loads(out2.read_text())
    assert no_truth["truth"] is None and no_truth["reference_vs_truth"] is None and no_truth["input"]["truth"] is None
    assert "rendered truth" not in capsys.readouterr().out

    # an --out that would replace a scene's reference cache is refused before anything is restored
    cache = captures / "scene_0000" / "reference.json"
    before = cache.read_bytes()
    assert main(["--ckpt", str(ckpt), "--captures", str(captures), "--sensor", str(sensor), "--out", str(cache)]) == 2
    assert "reference.json" in capsys.readouterr().err and cache.read_bytes() == before
    for argv, message in (
        (["--ckpt", str(ckpt), "--captures", str(captures)], "missing --sensor"),
        (
            ["--ckpt", str(ckpt), "--captures", str(captures), "--sensor", str(sensor), "--pred", str(tmp_path)],
            "not both",
        ),
        ([], "give --pred DIR --ref DIR"),
        (["--ckpt", str(tmp_path / "nope.ckpt"), "--captures", str(captures), "--sensor", str(sensor)], "not found"),
    ):
        assert main([*argv, "--out", str(tmp_path / "x.json")]) == 2
        assert message in capsys.readouterr().err


def test_edge_jump_scores_the_pixels_at_a_depth_step_apart(tmp_path, capsys):
    """``--edge-jump-mm``: the pixels next to a reference depth step (2 columns of 20 at a 300 mm step) are scored
    apart from the rest: a prediction 20 mm off there and 2 mm off elsewhere gives edge MAE 20, off-edge MAE 2,
    the whole image (2 x 20 + 18 x 2) / 20 = 3.8 mm, and an edge share of 10 %."""
    ref = np.full((10, 20), 1000.0)
    ref[:, 10:] = 1300.0
    pred = ref + 2.0
    pred[:, 9:11] = ref[:, 9:11] + 20.0
    _npy(tmp_path / "ref" / "s.npy", ref)
    _npy(tmp_path / "pred" / "s.npy", pred)
    out = tmp_path / "e.json"
    argv = ["--pred", str(tmp_path / "pred"), "--ref", str(tmp_path / "ref"), "--out", str(out)]
    assert main([*argv, "--edge-jump-mm", "50"]) == 0
    assert "edge px 10.0 %: MAE 20.000 mm; off-edge MAE 2.000 mm" in capsys.readouterr().out
    result = json.loads(out.read_text())
    regions = result["regions"]
    assert result["mean"]["mae_mm"] == pytest.approx(3.8)
    assert regions["edge_jump_mm"] == 50.0 and regions["edge_px_share"] == pytest.approx(0.1)
    assert regions["edge"]["mean"]["mae_mm"] == pytest.approx(20.0)
    assert regions["off_edge"]["mean"]["mae_mm"] == pytest.approx(2.0)
    assert regions["edge"]["images"]["s"]["valid_px"] == 20 and regions["off_edge"]["images"]["s"]["valid_px"] == 180
    # a step below the jump: no edge pixel, the edge region is empty (its image skipped), off-edge is the image
    assert main([*argv, "--edge-jump-mm", "400"]) == 0
    regions = json.loads(out.read_text())["regions"]
    assert regions["edge_px_share"] == 0.0 and regions["edge"]["skipped"] == ["s"]
    assert regions["off_edge"]["mean"]["mae_mm"] == pytest.approx(3.8)
    # without the option, no regions
    assert main(argv) == 0 and "regions" not in json.loads(out.read_text())
    assert main([*argv, "--edge-jump-mm", "0"]) == 2
    assert "--edge-jump-mm must be > 0, got 0.0" in capsys.readouterr().err


def test_a_run_scored_again_gives_its_recorded_test_numbers_and_where_the_error_sits(
    tmp_path, capsys, data_cache, tiny
):
    """``--run``: the run's synthetic and simulator-noised sets rebuilt from its config.yaml and restored with its
    best checkpoint give the run's recorded test numbers (restored and raw); the edge and off-edge regions split
    every image's pixels; a set the run did not have, a missing run, or --sets without --run exit 2 naming it."""
    from tofdenoise.cli.train import run
    from tofdenoise.config import compose_config

    run_dir = tmp_path / "run"
    run(compose_config(tiny(run_dir, data_cache) + ["trainer.max_epochs=1", "logger=csv"]))
    recorded = json.loads((run_dir / "metrics.json").read_text())
    out = tmp_path / "again.json"
    capsys.readouterr()
    assert main(["--run", str(run_dir), "--device", "cpu", "--edge-jump-mm", "50", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("precision 32-true (from ") and "\nsynthetic: " in printed
    assert "\nsimulated: " in printed and "off-edge MAE" in printed
    result = json.loads(out.read_text())
    assert result["checkpoint"] == str(run_dir / "checkpoints" / "best.ckpt")
    assert sorted(result["sets"]) == ["simulated", "synthetic"]
    for name, scored in result["sets"].items():
        assert scored["inputs_as_recorded"] is True
        for key in ("psnr_db", "mae_mm", "mse_mm2", "ssim"):
            assert scored["restored"]["mean"][key] == pytest.approx(recorded[name][key], rel=1e-9, abs=1e-9)
            assert scored["input"]["mean"][key] == pytest.approx(recorded[name]["raw"][key], rel=1e-9, abs=1e-9)
        regions = scored["restored"]["regions"]
        for stem, row in scored["restored"]["images"].items():
            edge_px = regions["edge"]["images"][stem]["valid_px"]
            assert edge_px + regions["off_edge"]["images"][stem]["valid_px"] == row["valid_px"]
            # the whole image's MAE is the pixel-weighted mean of its two regions'
            parts = [
                (regions[r]["images"][stem]["mae_mm"] or 0.0) * regions[r]["images"][stem]["valid_px"]
                for r in ("edge", "off_edge")
            ]
            assert sum(parts) / row["valid_px"] == pytest.approx(row["mae_mm"], rel=1e-9)
    # the errors, each naming what is wrong, nothing written
    bad = tmp_path / "bad.json"
    assert main(["--run", str(run_dir), "--sets", "real", "--out", str(bad)]) == 2
    assert f"run {run_dir}: its metrics.json has no real set: it was tested on synthetic, simulated" in (
        capsys.readouterr().err
    )
    assert main(["--run", str(tmp_path / "nope"), "--out", str(bad)]) == 2
    assert "no config.yaml (the run's resolved config); expected a finished run" in capsys.readouterr().err
    assert main(["--run", str(run_dir), "--sets", "train", "--out", str(bad)]) == 2
    assert "unknown test set(s) train" in capsys.readouterr().err
    assert main(["--pred", str(tmp_path), "--ref", str(tmp_path), "--sets", "synthetic", "--out", str(bad)]) == 2
    assert "--sets goes with --run" in capsys.readouterr().err
    assert main(["--run", str(run_dir), "--ckpt", str(result["checkpoint"]), "--out", str(bad)]) == 2
    assert "give --run alone, without --ckpt" in capsys.readouterr().err
    assert not bad.exists()
    # a record whose test inputs this code does not rebuild (here: its raw number edited) is flagged, not passed off
    recorded["synthetic"]["raw"]["mae_mm"] += 1.0
    (run_dir / "metrics.json").write_text(json.dumps(recorded))
    assert main(["--run", str(run_dir), "--sets", "synthetic", "--device", "cpu", "--out", str(out)]) == 0
    assert "synthetic: the rebuilt inputs do not score as the run's recorded raw numbers" in capsys.readouterr().err
    assert json.loads(out.read_text())["sets"]["synthetic"]["inputs_as_recorded"] is False


def test_a_bf16_run_scored_again_at_its_own_precision_gives_its_recorded_numbers(tmp_path, capsys, data_cache, tiny):
    """A run tested at ``trainer.precision=bf16-mixed`` (bf16 autocast, here on the CPU) is restored again at that
    precision, so ``--run`` gives its recorded numbers; ``--precision 32-true`` (what ``--run`` did whatever the run
    had, before 2026-11-29) gives other numbers, and the JSON says which precision was used."""
    from tofdenoise.cli.train import run
    from tofdenoise.config import compose_config

    run_dir = tmp_path / "run"
    overrides = ["trainer.max_epochs=1", "logger=csv", "trainer.precision=bf16-mixed"]
    run(compose_config(tiny(run_dir, data_cache) + overrides))
    recorded = json.loads((run_dir / "metrics.json").read_text())
    out, fp32 = tmp_path / "again.json", tmp_path / "fp32.json"
    capsys.readouterr()
    assert main(["--run", str(run_dir), "--device", "cpu", "--sets", "synthetic", "--out", str(out)]) == 0
    assert f"precision bf16-mixed (from {run_dir / 'config.yaml'} (trainer.precision))" in capsys.readouterr().out
    result = json.loads(out.read_text())
    assert result["precision"] == {"value": "bf16-mixed", "from": f"{run_dir / 'config.yaml'} (trainer.precision)"}
    scored = result["sets"]["synthetic"]
    assert scored["inputs_as_recorded"] is True
    for key in ("psnr_db", "mae_mm", "mse_mm2", "ssim"):
        assert scored["restored"]["mean"][key] == pytest.approx(recorded["synthetic"][key], rel=1e-9, abs=1e-9)
    argv = ["--run", str(run_dir), "--device", "cpu", "--sets", "synthetic", "--precision", "32-true"]
    assert main([*argv, "--out", str(fp32)]) == 0
    other = json.loads(fp32.read_text())
    assert other["precision"] == {"value": "32-true", "from": "--precision"}
    off = abs(other["sets"]["synthetic"]["restored"]["mean"]["mae_mm"] - recorded["synthetic"]["mae_mm"])
    assert off > 1e-6  # float32 is not the run's precision: not its numbers
    assert main([*argv[:-1], "fp8", "--out", str(fp32)]) == 2
    assert "precision 'fp8' is not one of 32-true, bf16-mixed" in capsys.readouterr().err
    assert main(["--pred", str(tmp_path), "--ref", str(tmp_path), "--precision", "32-true", "--out", str(fp32)]) == 2
    assert "--precision goes with --run" in capsys.readouterr().err
