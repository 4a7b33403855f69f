"""Fine-tuning from weights (model.init_weights): a run starts from another run's network, weights only."""

from __future__ import annotations

import csv
import json
import sys

import pytest
import torch
from hydra.utils import instantiate
from lightning.pytorch import Trainer, seed_everything
from omegaconf import OmegaConf

from tofdenoise.cli.train import run
from tofdenoise.config import compose_config, instantiate_node
from tofdenoise.training.init_weights import InitWeightsError, file_sha256
from tofdenoise.training.module import DepthRestorer


def _first_val_mae(run_dir) -> float:
    with open(run_dir / "csv" / "metrics.csv") as fh:
        return next(float(r["val/mae_mm"]) for r in csv.DictReader(fh) if r.get("val/mae_mm"))


def _val_mae(model, datamodule) -> float:
    trainer = Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False)
    return float(trainer.validate(model, datamodule=datamodule, verbose=False)[0]["val/mae_mm"])


def test_a_run_starts_from_the_weights_of_another_on_a_new_camera(tmp_path, data_cache, tiny, own_camera_file):
    base = tmp_path / "base"
    run(compose_config(tiny(base, data_cache) + ["trainer.max_epochs=6", "model.optim.lr=3e-3", "logger=csv"]))
    best = base / "checkpoints" / "best.ckpt"
    _, calib_file = own_camera_file(tmp_path)
    # a near-zero rate: the first validation (after one epoch) shows the network the run started from
    fine = tmp_path / "fine"
    overrides = tiny(fine, data_cache) + [
        "trainer.max_epochs=1",
        "logger=csv",
        f"++data.sensor={calib_file}",
        f"++model.init_weights={best}",
        "model.optim.lr=1e-12",
        "++model.optim.lr_min=0",
    ]
    cfg = compose_config(overrides)
    run(cfg)
    first = _first_val_mae(fine)

    datamodule = instantiate_node(cfg.data, "data")  # the new camera's validation split
    loaded = _val_mae(DepthRestorer.load_from_checkpoint(best, weights_only=True), datamodule)
    seed_everything(0)
    fresh_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    fresh_cfg.pop("init_weights")
    fresh = _val_mae(instantiate(fresh_cfg, _convert_="all"), datamodule)
    # the tiny base run moves the network by ~0.01 mm of validation MAE: the loaded weights, not a fresh init
    assert abs(first - loaded) < 1e-4 < 2e-3 < abs(first - fresh), (first, loaded, fresh)

    info = json.loads((fine / "run_info.json").read_text())
    assert info["init_weights"] == {"path": str(best.resolve()), "sha256": file_sha256(best)}
    assert info["global_step"] == 3  # fresh optimiser, schedule and epoch: one epoch of 3 steps
    saved = OmegaConf.load(fine / "config.yaml")
    assert saved.model.init_weights == str(best)
    # the record travels with the checkpoints, and the fine-tuned checkpoint loads without the init file
    ckpt = torch.load(fine / "checkpoints" / "last.ckpt", weights_only=True)
    assert ckpt["tofdenoise_init_weights"]["sha256"] == file_sha256(best)
    assert ckpt["epoch"] == 0


def test_a_mismatched_backbone_is_one_line_naming_the_layers(tmp_path, data_cache, tiny, capsys):
    other = DepthRestorer(backbone="unet", backbone_kwargs={"width": 16, "stages": 2})
    weights = tmp_path / "other.pt"
    torch.save(other.state_dict(), weights)
    cfg = compose_config(tiny(tmp_path / "r", data_cache) + [f"++model.init_weights={weights}", "logger=csv"])
    with pytest.raises(InitWeightsError) as info:
        run(cfg)
    msg = str(info.value)
    assert str(weights) in msg and "shape mismatch(es) (" in msg and "vs model (8," in msg and "\n" not in msg
    assert not (tmp_path / "r" / "run_info.json").exists()  # nothing of the run was recorded


def test_a_corrupt_init_file_through_the_command_line_is_one_line(tmp_path, data_cache, tiny):
    import os
    import subprocess

    broken = tmp_path / "broken.ckpt"
    broken.write_bytes(b"PK\x03\x04 half a file")
    args = tiny(tmp_path / "r", data_cache) + [f"++model.init_weights={broken}", "logger=csv"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "WANDB_MODE": "offline"}
    proc = subprocess.run(
        [sys.executable, "-m", "tofdenoise.cli.train", *args], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 2, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"tofdenoise train: error: model.init_weights: {broken} is not loadable by torch.load")
    assert "Traceback" not in proc.stderr
