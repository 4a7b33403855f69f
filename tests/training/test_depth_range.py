"""The depths a network was trained on: counted from the training batches, kept in the checkpoint, resumed, and
unknown for a checkpoint written before the record existed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tofdenoise.training.depth_range import DEPTH_RANGE_KEY, TrainingDepthRange, outside_fraction
from tofdenoise.training.module import DepthRestorer

from .conftest import quiet_trainer


def test_the_histogram_quantiles_and_extremes_match_numpy_on_the_valid_depths():
    rng = np.random.default_rng(0)
    record = TrainingDepthRange()
    seen = []
    for _ in range(3):
        depth = np.exp(rng.uniform(np.log(300), np.log(7500), (2, 1, 40, 50))).astype(np.float32)
        mask = (rng.uniform(size=depth.shape) > 0.2).astype(np.float32)
        depth[0, 0, :3] = np.nan  # never counted, wherever the mask says
        mask[0, 0, 3] = 1.0
        depth[0, 0, 3] = 0.0
        record.update(torch.from_numpy(depth), torch.from_numpy(mask))
        ok = (mask > 0) & np.isfinite(depth) & (depth > 0)
        seen.append(depth[ok])
    values = np.concatenate(seen)
    out = record.record()
    assert out["pixels"] == values.size
    assert out["min_mm"] == pytest.approx(values.min()) and out["max_mm"] == pytest.approx(values.max())
    low, high = np.quantile(values, [0.005, 0.995])
    assert out["low_mm"] == pytest.approx(low, rel=0.025) and out["high_mm"] == pytest.approx(high, rel=0.025)
    assert record.range_mm == (out["low_mm"], out["high_mm"])
    # a checkpoint's record goes on counting (a resumed fit)
    resumed = TrainingDepthRange()
    resumed.load({DEPTH_RANGE_KEY: out})
    assert resumed.range_mm == record.range_mm
    resumed.update(torch.full((1, 1, 4, 4), 9000.0), torch.ones(1, 1, 4, 4))
    assert resumed.record()["pixels"] == values.size + 16 and resumed.record()["max_mm"] == 9000.0
    # none recorded: unknown
    old = TrainingDepthRange()
    old.load({"state_dict": {}})
    assert old.range_mm is None and old.record() is None


def test_outside_fraction_counts_only_valid_pixels():
    depth = np.array([[100.0, 500.0], [3000.0, 0.0]])
    valid = depth > 0
    assert outside_fraction(depth, valid, (300.0, 2400.0)) == pytest.approx(2 / 3)
    assert outside_fraction(depth, np.zeros_like(valid), (300.0, 2400.0)) == 0.0


def test_a_fit_keeps_the_training_depths_in_its_checkpoint(tmp_path, tiny_data):
    model = DepthRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 2}, loss="l1")
    assert model.training_depth_range_mm is None
    trainer = quiet_trainer(tmp_path, max_epochs=1, limit_val_batches=0)
    trainer.fit(model, datamodule=tiny_data)
    tiny_data.setup("fit")
    values = np.concatenate(
        [b["clean"][b["mask"] > 0].numpy() for b in tiny_data.train_dataloader()]  # one epoch: every sample once
    )
    ckpt = tmp_path / "fit.ckpt"
    trainer.save_checkpoint(ckpt)
    content = torch.load(ckpt, map_location="cpu", weights_only=True)
    record = content[DEPTH_RANGE_KEY]
    assert record["pixels"] == values.size
    assert (record["min_mm"], record["max_mm"]) == pytest.approx((values.min(), values.max()))
    low, high = np.quantile(values, [0.005, 0.995])
    loaded = DepthRestorer.load_from_checkpoint(ckpt, map_location="cpu")
    assert loaded.training_depth_range_mm == pytest.approx((low, high), rel=0.025)
    # a checkpoint written before the record existed: the range is unknown
    del content[DEPTH_RANGE_KEY]
    torch.save(content, tmp_path / "old.ckpt")
    assert DepthRestorer.load_from_checkpoint(tmp_path / "old.ckpt", map_location="cpu").training_depth_range_mm is None
