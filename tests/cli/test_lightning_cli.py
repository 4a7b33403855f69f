"""LightningCLI front end: the committed configs/cli YAMLs are generated from the Hydra configs, both entry
points build the same model, and `tofdenoise fit/test/predict` run end to end."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from lightning.pytorch import seed_everything

from tofdenoise.cli.export_cli_config import PRESETS, export_preset
from tofdenoise.cli.export_cli_config import main as export_main
from tofdenoise.cli.lightning_cli import build_cli
from tofdenoise.cli.lightning_cli import main as cli_main
from tofdenoise.config import compose_config, config_dir
from tofdenoise.training.module import DepthRestorer

CLI_DIR = config_dir() / "cli"


def test_committed_cli_configs_are_generated_from_hydra(tmp_path):
    for name, overrides in PRESETS.items():
        committed = (CLI_DIR / f"{name}.yaml").read_text()
        assert committed == export_preset(name, overrides), (
            f"configs/cli/{name}.yaml is stale: run python -m tofdenoise.cli.export_cli_config"
        )
    assert export_main(["--check"]) == 0
    (tmp_path / "default.yaml").write_text("seed_everything: 1\n")
    assert export_main(["--check", "--out", str(tmp_path)]) == 1


def test_hydra_and_lightning_cli_build_the_same_model(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["tofdenoise"])
    monkeypatch.chdir(tmp_path)  # the YAML's relative run folder (outputs/cli/default) lands in tmp_path
    cfg = compose_config(["paths.run_dir=outputs/cli/default"])
    seed_everything(int(cfg.seed))
    hydra_model = instantiate(cfg.model, _convert_="all")
    hydra_data = instantiate(cfg.data, _convert_="all")
    cli = build_cli(["--config", str(CLI_DIR / "default.yaml")], run=False)
    # LightningCLI also records how it built the model (_class_path, _instantiator)
    # (a tuple read from YAML is a list: compare the JSON forms)
    cli_hparams = {k: v for k, v in cli.model.hparams.items() if not k.startswith("_")}
    assert json.dumps(cli_hparams, sort_keys=True) == json.dumps(dict(hydra_model.hparams), sort_keys=True)
    assert cli.model.hparams["_class_path"] == "tofdenoise.training.module.DepthRestorer"
    assert {k: v for k, v in cli.datamodule.hparams.items() if not k.startswith("_")} == dict(hydra_data.hparams)
    a, b = hydra_model.state_dict(), cli.model.state_dict()
    assert list(a) == list(b)
    for k in a:  # same seed -> same initial weights
        assert a[k].shape == b[k].shape and torch.equal(a[k], b[k]), k
    assert cli.trainer.max_epochs == cfg.trainer.max_epochs
    assert (
        Path(cli.trainer.checkpoint_callback.dirpath).resolve()
        == (tmp_path / "outputs/cli/default/checkpoints").resolve()
    )
    assert sorted(type(lg).__name__ for lg in cli.trainer.loggers) == ["ResumableCSVLogger", "WandbLogger"]
    assert any(type(cb).__name__ == "CSVLogResume" for cb in cli.trainer.callbacks)


def _smoke_args(tmp_path, data_cache) -> list[str]:
    """The smoke config at the test suite's tiny size, outputs under tmp_path."""
    return [
        "--config",
        str(CLI_DIR / "smoke.yaml"),
        f"--trainer.default_root_dir={tmp_path}/run",
        "--trainer.logger=false",
        "--trainer.enable_progress_bar=false",
        f"--data.init_args.cache_dir={data_cache}",
        "--data.init_args.source_kwargs={num_samples: 10, height: 32, width: 48}",
        "--data.init_args.crop_size=32",
        "--model.init_args.backbone_kwargs={in_channels: 1, width: 8, stages: 2}",
        "--model.init_args.backbone=unet",
    ]


def test_fit_test_predict_from_the_smoke_config(tmp_path, data_cache, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["tofdenoise"])  # the arguments come from `args`, not pytest's argv
    monkeypatch.chdir(tmp_path)  # relative paths of the YAML (outputs/cli/...) land in tmp_path
    common = _smoke_args(tmp_path, data_cache)
    cli_main(["fit", *common, "--trainer.max_epochs=1"])
    best = tmp_path / "outputs" / "cli" / "smoke" / "checkpoints" / "best.ckpt"
    assert best.is_file() and (best.parent / "last.ckpt").is_file()
    cli_main(["test", *common, f"--ckpt_path={best}"])
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert set(metrics["synthetic"]) >= {"psnr_db", "mae_mm", "mse_mm2", "ssim", "raw"}
    assert (tmp_path / "run" / "per_image" / "synthetic.csv").is_file()
    # the same RunOutputs callback as the Hydra run: run_info.json with the tested checkpoint
    info = json.loads((tmp_path / "run" / "run_info.json").read_text())
    assert {
        "backbone": "unet",
        "noise": "hetero",
        "loss": "full",
        "run_name": "unet-hetero-full",
        "data": "procedural",
        "seed": 0,
        "best_ckpt": str(best),
    }.items() <= info.items()
    assert "finished" in info and "started" in info
    # the test of the fit's own best checkpoint kept the fit's record (its steps, its start) and added the test's time
    assert info["global_step"] == 3 and "tested" in info
    # another checkpoint tested there, or none, would be recorded as the fit's: refused, nothing rewritten
    before = {name: (tmp_path / "run" / name).read_bytes() for name in ("run_info.json", "metrics.json")}
    for other in ([f"--ckpt_path={best.parent / 'last.ckpt'}"], []):
        with pytest.raises(SystemExit) as exit_info:
            cli_main(["test", *common, *other])
        assert exit_info.value.code == 2
    assert {name: (tmp_path / "run" / name).read_bytes() for name in before} == before
    # the learned guard's fields come from the tested checkpoint (6 training scenes, batch 2: 3 steps)
    from tofdenoise.records import learned_status, learned_verdict

    ckpt = torch.load(best, weights_only=True)
    assert metrics["trained_steps"] == ckpt["global_step"] == 3
    assert metrics["best_val_mae_mm"] > 0 and metrics["raw_val_mae_mm"] > 0
    assert metrics["best_val_mae_mm"] == pytest.approx(
        float(
            ckpt["callbacks"][next(k for k in ckpt["callbacks"] if k.startswith("BestAndLastCheckpoint"))][
                "best_model_score"
            ]
        ),
        rel=1e-6,
    )
    assert {k: metrics[k] for k in ("learned", "learned_reason")} == {
        k: v
        for k, v in learned_verdict(3, metrics["best_val_mae_mm"], metrics["raw_val_mae_mm"]).items()
        if k in ("learned", "learned_reason")
    }
    # `test` without a checkpoint evaluates an untrained network: never reported as trained
    untrained = [a.replace(f"{tmp_path}/run", f"{tmp_path}/untrained") for a in common]
    cli_main(["test", *untrained])
    fresh = json.loads((tmp_path / "untrained" / "metrics.json").read_text())
    assert fresh["learned"] is False and fresh["trained_steps"] == 0 and learned_status(fresh) == "not trained"
    cli_main(["predict", *common, f"--ckpt_path={best}"])
    pngs = sorted((tmp_path / "outputs" / "cli" / "smoke" / "predictions" / "synthetic" / "png").glob("*.png"))
    npys = sorted((tmp_path / "outputs" / "cli" / "smoke" / "predictions" / "synthetic" / "npy").glob("*.npy"))
    assert len(pngs) == len(npys) == 2
    import cv2

    png = cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED)
    npy = np.load(npys[0])
    assert png.dtype == np.uint16 and png.shape == npy.shape == (32, 48)
    valid = np.isfinite(npy) & (npy > 0)
    assert np.abs(png[valid].astype(np.float64) - npy[valid]).max() <= 0.5 + 1e-6


def test_truncated_checkpoint_stops_before_config_yaml_is_rewritten(tmp_path, data_cache, monkeypatch, capsys):
    import os

    import pytest

    monkeypatch.setattr(sys, "argv", ["tofdenoise"])
    monkeypatch.chdir(tmp_path)
    common = _smoke_args(tmp_path, data_cache)
    cli_main(["fit", *common, "--trainer.max_epochs=1"])
    config = tmp_path / "run" / "config.yaml"
    last = tmp_path / "outputs" / "cli" / "smoke" / "checkpoints" / "last.ckpt"
    before = config.read_bytes()
    os.truncate(last, last.stat().st_size - 100)
    for ckpt in ("last", str(last)):
        with pytest.raises(SystemExit) as exit_info:
            cli_main(["fit", *common, "--trainer.max_epochs=3", "--ckpt_path", ckpt])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith(f"tofdenoise: error: checkpoint {last} is ") and "best.ckpt" in err[-1]
        assert config.read_bytes() == before  # max_epochs: 3 never reached the run's config.yaml


def test_a_run_folder_written_by_another_process_is_refused_before_anything_is_written(
    tmp_path, data_cache, monkeypatch, capsys, lock_holder
):
    """issue 23 case 3, LightningCLI front end: `tofdenoise fit` on a run folder another process writes is refused
    (exit 2, one line naming the lock file and its holder) before a class is built or a file written."""
    monkeypatch.setattr(sys, "argv", ["tofdenoise"])
    monkeypatch.chdir(tmp_path)
    run_dir = tmp_path / "run"
    with lock_holder(run_dir, "other fit") as pid:
        with pytest.raises(SystemExit) as exit_info:
            cli_main(["fit", *_smoke_args(tmp_path, data_cache), "--trainer.max_epochs=1"])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith(f"tofdenoise: error: run folder {run_dir} is locked by pid {pid} ")
        assert "other fit" in err[-1] and str(run_dir / "run.lock") in err[-1]
        assert [p.name for p in run_dir.iterdir()] == ["run.lock"] and not (tmp_path / "outputs").exists()
    cli_main(["fit", *_smoke_args(tmp_path, data_cache), "--trainer.max_epochs=1"])  # free again once released
    assert (run_dir / "config.yaml").is_file() and not (run_dir / "run.lock").exists()


def test_fit_from_init_weights(tmp_path, data_cache, monkeypatch, capsys):
    """--model.init_args.init_weights: the LightningCLI face of ++model.init_weights (same module hook)."""
    from tofdenoise.training.init_weights import file_sha256

    monkeypatch.setattr(sys, "argv", ["tofdenoise"])
    monkeypatch.chdir(tmp_path)
    src = DepthRestorer(backbone="unet", backbone_kwargs={"width": 8, "stages": 2})
    gen = torch.Generator().manual_seed(1)
    src.backbone.load_state_dict(
        {k: v + torch.randn(v.shape, generator=gen) for k, v in src.backbone.state_dict().items()}
    )
    weights = tmp_path / "start.pt"
    torch.save(src.backbone.state_dict(), weights)
    common = _smoke_args(tmp_path, data_cache)
    cli_main(["fit", *common, "--trainer.max_epochs=1", f"--model.init_args.init_weights={weights}"])
    info = json.loads((tmp_path / "run" / "run_info.json").read_text())
    assert info["init_weights"] == {"path": str(weights.resolve()), "sha256": file_sha256(weights)}
    saved = (tmp_path / "run" / "config.yaml").read_text()
    assert f"init_weights: {weights}" in saved
    # a file of another size: one line naming it, exit status 2
    big = DepthRestorer(backbone="unet", backbone_kwargs={"width": 16, "stages": 2})
    torch.save(big.state_dict(), tmp_path / "big.pt")
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["fit", *common, "--trainer.max_epochs=1", f"--model.init_args.init_weights={tmp_path / 'big.pt'}"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"tofdenoise: error: model.init_weights: {tmp_path / 'big.pt'} does not fit backbone 'unet'")
