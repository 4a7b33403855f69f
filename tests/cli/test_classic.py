"""tofdenoise classic: grid search of the joint bilateral filter on validation, test through DepthRestorer's
test step, the same metrics.json / per-image CSV schema as the networks, listed by tofdenoise report."""

from __future__ import annotations

import json
import math

import pytest
from omegaconf import OmegaConf

from tofdenoise.cli.classic import grid_points, run, select_best
from tofdenoise.cli.train import validate_config
from tofdenoise.config import compose_config
from tofdenoise.physics.calibration import SensorCalibration
from tofdenoise.records import RUN_KEYS, learned_status, metric_sets, read_metrics_json, read_per_image_csv


def classic_overrides(tiny, run_dir, cache, grid: dict) -> list[str]:
    base = [o for o in tiny(run_dir, cache) if not o.startswith("backbone")]
    return base + [f"classical.grid.{k}=[{','.join(str(x) for x in v)}]" for k, v in grid.items()]


def test_grid_points_order_and_errors():
    pts = grid_points({"sigma_spatial_px": [1.0, 2.0], "sigma_depth_mm": [5.0, math.inf]}, {"radius_px": 3})
    assert pts == [
        {"sigma_spatial_px": 1.0, "sigma_depth_mm": 5.0, "radius_px": 3},
        {"sigma_spatial_px": 1.0, "sigma_depth_mm": math.inf, "radius_px": 3},
        {"sigma_spatial_px": 2.0, "sigma_depth_mm": 5.0, "radius_px": 3},
        {"sigma_spatial_px": 2.0, "sigma_depth_mm": math.inf, "radius_px": 3},
    ]
    assert grid_points({"amplitude_power": 1.0}, {"radius_px": None}) == [{"amplitude_power": 1.0}]
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['sigma_range'\]"):
        grid_points({"sigma_range": [1.0]})
    with pytest.raises(ValueError, match="classical.grid.sigma_depth_mm: empty list"):
        grid_points({"sigma_depth_mm": []})
    with pytest.raises(ValueError, match="classical.grid.sigma_depth_mm: expected numbers.*'.inf'"):
        grid_points({"sigma_depth_mm": [".inf"]})
    with pytest.raises(ValueError, match="searched and also fixed"):
        grid_points({"radius_px": [2, 3]}, {"radius_px": 2})


def test_select_best_takes_the_lowest_finite_val_mae_first_of_ties():
    scores = [
        {"val_mae_mm": 3.0},
        {"val_mae_mm": math.nan},
        {"val_mae_mm": 2.5},
        {"val_mae_mm": 2.5},
        {"val_mae_mm": None},
    ]
    assert select_best(scores) == 2
    with pytest.raises(ValueError, match="no grid point has a finite val_mae_mm"):
        select_best([{"val_mae_mm": math.nan}])


def test_bad_configuration_fails_before_any_data(tmp_path, tiny):
    cfg = compose_config(
        classic_overrides(tiny, tmp_path, tmp_path / "never", {"sigma_depth_mm": [-1.0]}), config_name="classical"
    )
    with pytest.raises(ValueError, match="sigma_depth_mm must be > 0"):
        run(cfg)
    cfg = compose_config(
        classic_overrides(tiny, tmp_path, tmp_path / "never", {}) + ["classical.backbone=unet"], config_name="classical"
    )
    with pytest.raises(ValueError, match="classical.backbone: 'unet' is not a registered classical filter"):
        run(cfg)
    assert not (tmp_path / "never").exists()
    # the training entry point refuses the filter with the command to use
    cfg = compose_config(tiny(tmp_path, tmp_path / "never") + ["backbone.name=bilateral"])
    with pytest.raises(ValueError, match="classical filter without trainable parameters.*tofdenoise classic"):
        validate_config(cfg)


def test_tune_on_validation_then_test_through_the_network_path(tmp_path, data_cache, tiny, capsys):
    """Toy grid: sigma_d = 0.001 mm lets no neighbour in (the identity: val MAE = raw), 30 mm averages the
    3-12 mm noise away: the search must pick 30 mm, and the test metrics must be those of DepthRestorer.test."""
    from tofdenoise.cli.report import main as report_main
    from tofdenoise.training.metrics import DepthMetrics
    from tofdenoise.training.module import DepthRestorer

    run_dir = tmp_path / "bilateral"
    grid = {"sigma_spatial_px": [1.5], "sigma_depth_mm": [0.001, 30.0], "amplitude_power": [0.0]}
    cfg = compose_config(classic_overrides(tiny, run_dir, data_cache, grid), config_name="classical")
    result = run(cfg)
    assert result["best"] == {"sigma_spatial_px": 1.5, "sigma_depth_mm": 30.0, "amplitude_power": 0.0}

    tuning = json.loads((run_dir / "tuning.json").read_text())
    pts = tuning["points"]
    assert tuning["best_index"] == 1 and tuning["val_images"] == 2 and len(pts) == 2
    assert pts[0]["val_mae_mm"] == pytest.approx(tuning["raw"]["val_mae_mm"], rel=1e-6)  # identity
    assert pts[1]["val_mae_mm"] < 0.8 * tuning["raw"]["val_mae_mm"]
    assert pts[1]["radius_px_used"] == 3
    # the tuning scores are DepthRestorer.restore_mm + DepthMetrics on the validation images
    from hydra.utils import instantiate

    dm = instantiate(cfg.data, _convert_="all")
    dm.prepare_data()
    dm.setup("validate")
    model = DepthRestorer(
        backbone="bilateral",
        backbone_kwargs=result["best"],
        conditioning={"use_signal_channel": True, "centering": "none"},
    )
    metric = DepthMetrics()
    for batch in dm.val_dataloader():
        metric.update(model.restore_mm(batch), batch["clean"], batch["mask"], index=batch["index"])
    assert float(metric.compute()["mae_mm"]) == pytest.approx(pts[1]["val_mae_mm"], rel=1e-6)

    data = read_metrics_json(run_dir / "metrics.json")
    assert set(data) - set(metric_sets(data)) == set(RUN_KEYS)
    assert data["method_kind"] == "classical" and learned_status(data) == "classical"
    assert data["trained_steps"] == 0 and data["best_val_mae_mm"] == pytest.approx(pts[1]["val_mae_mm"])
    assert data["raw_val_mae_mm"] == pytest.approx(tuning["raw"]["val_mae_mm"])
    syn = data["synthetic"]
    assert syn["images"] == 2 and syn["mae_mm"] < 0.8 * syn["raw"]["mae_mm"]
    rows = read_per_image_csv(run_dir / "per_image" / "synthetic.csv")
    assert len(rows) == 2 and all(r["name"] for r in rows)
    assert sum(r["mae_mm"] for r in rows) / 2 == pytest.approx(syn["mae_mm"], rel=1e-9)
    info = json.loads((run_dir / "run_info.json").read_text())
    assert {
        "backbone": "bilateral",
        "method": "bilateral (classical)",
        "noise": "hetero",
        "loss": "none",
        "global_step": 0,
        "tuning": "tuning.json",
    }.items() <= info.items()
    assert info["params"]["sigma_depth_mm"] == 30.0 and (run_dir / "config.yaml").is_file()

    capsys.readouterr()
    assert report_main([str(tmp_path), "--out", str(tmp_path / "report.html")]) == 0
    row = next(r for r in capsys.readouterr().out.splitlines() if r.startswith("| bilateral (classical) "))
    assert row.startswith("| bilateral (classical) | hetero | none | classical |")


def test_real_capture_set_is_tested_like_the_networks(tmp_path, data_cache, tiny, own_camera_file):
    """With data.real_dir the chosen filter is also tested on the capture set (the "real" column)."""
    from tofdenoise.data_modules.capture_simulation import simulate_capture_set

    simulate_capture_set(tmp_path / "set", scenes=3, frames=4, height=32, width=48, seed=1)
    run_dir = tmp_path / "run"
    grid = {"sigma_spatial_px": [1.0], "sigma_depth_mm": [40.0], "amplitude_power": [0.0, 1.0]}
    own, calib_file = own_camera_file(tmp_path)  # data.sensor=<file> overrides the sensor group
    cfg = compose_config(
        classic_overrides(tiny, run_dir, data_cache, grid)
        + [f"data.real_dir={tmp_path / 'set'}", f"++data.sensor={calib_file}"],
        config_name="classical",
    )
    run(cfg)
    # config.yaml records the calibration file's camera, not the sensor group's default
    saved = OmegaConf.load(run_dir / "config.yaml")
    assert SensorCalibration.from_dict(OmegaConf.to_container(saved.sensor)).fingerprint() == own.fingerprint()
    data = read_metrics_json(run_dir / "metrics.json")
    assert sorted(metric_sets(data)) == ["real", "simulated", "synthetic"] and data["real"]["images"] == 3
    assert data["real"]["mae_mm"] < data["real"]["raw"]["mae_mm"]
    rows = read_per_image_csv(run_dir / "per_image" / "real.csv")
    assert [r["name"] for r in rows] == ["scene_0000", "scene_0001", "scene_0002"]
    # a simulated capture set has truth: the filter's predictions are scored against it, as a learned run's are
    truth = json.loads((run_dir / "real_vs_truth.json").read_text())
    assert truth["method"] == "classical" and truth["scenes"] == 3
    assert truth["reference"]["mean"]["mae_mm"] == pytest.approx(data["real"]["mae_mm"], rel=1e-4)
    assert truth["truth"]["mean"]["mae_mm"] < truth["input"]["truth"]["mean"]["mae_mm"]


def test_a_run_folder_written_by_another_process_is_refused(tmp_path, lock_holder):
    """issue 23 case 3 for the classical row: one writer per run folder (tofdenoise.run_lock)."""
    import os
    import subprocess
    import sys

    run_dir = tmp_path / "bilateral"
    with lock_holder(run_dir) as pid:
        proc = subprocess.run(
            [sys.executable, "-m", "tofdenoise.cli.classic", f"paths.run_dir={run_dir}", "experiment=smoke"],
            capture_output=True,
            text=True,
            env={**os.environ, "WANDB_MODE": "offline"},
            timeout=300,
        )
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith(f"tofdenoise classic: error: run folder {run_dir} is locked by pid {pid} ")
    assert [p.name for p in run_dir.iterdir()] == []  # released by the holder; nothing of the refused run
