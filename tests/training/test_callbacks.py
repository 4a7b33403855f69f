"""Run summary lines and the prediction writer's file formats."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tofdenoise.callbacks.predict_writer import DepthPredictionWriter
from tofdenoise.callbacks.summary import format_fit_summary, format_test_summary


def test_summary_lines():
    line = format_fit_summary(
        "unet-hetero-full",
        20,
        900,
        370.4,
        torch.tensor(3.1234),
        "/r/checkpoints/best.ckpt",
        "val/mae_mm",
        torch.tensor(6.05),
    )
    assert line == (
        "[unet-hetero-full] fit: 20 epochs, 900 steps in 6m10s | best val/mae_mm 3.123 (raw 6.050)"
        " -> /r/checkpoints/best.ckpt"
    )
    assert "(no checkpoint written)" in format_fit_summary("x", 1, 1, 1.0, None, "", "val/mae_mm")
    res = {
        "synthetic": {
            "mae_mm": 3.1,
            "psnr_db": 44.12,
            "ssim": 0.99512,
            "raw": {"mae_mm": 6.0, "psnr_db": 39.9, "ssim": 0.93},
        },
        "real": {"mae_mm": None, "psnr_db": 30.0, "ssim": 0.9, "raw": {}},
    }
    line = format_test_summary("r", res, 3725.0)
    assert line.startswith(
        "[r] test in 1h02m05s | synthetic [paper protocol (hetero-noised)]: MAE 3.10 mm (raw 6.00), PSNR 44.12 dB"
    )
    assert "| real [capture set]: MAE n/a mm (raw n/a)" in line and "\n" not in line


def test_prediction_writer_layout(tmp_path):
    class T:  # the trainer attributes the writer reads
        default_root_dir = str(tmp_path)
        datamodule = type("DM", (), {"test_set_names": ["synthetic", "real"]})()

    w = DepthPredictionWriter(write_sigma=True, write_reference=True, write_previews=True)
    pred = torch.full((2, 1, 8, 10), 1000.25)
    batch = {
        "name": ["a_1", "b_2"],
        "index": torch.tensor([3, 4]),
        "sigma": torch.full((2, 1, 8, 10), 2.5),
        "clean": torch.full((2, 1, 8, 10), 999.0),
        "noisy": torch.full((2, 1, 8, 10), 1003.0),
        "mask": torch.ones(2, 1, 8, 10),
    }
    w.write_on_batch_end(T(), None, pred, None, batch, 0, dataloader_idx=1)
    root = tmp_path / "predictions" / "real"
    assert sorted(p.name for p in (root / "png").iterdir()) == ["a_1.png", "b_2.png"]
    assert np.load(root / "npy" / "a_1.npy").dtype == np.float32
    assert np.allclose(np.load(root / "npy" / "b_2.npy"), 1000.25)
    assert np.allclose(np.load(root / "sigma_npy" / "a_1.npy"), 2.5)
    assert cv2.imread(str(root / "reference_png" / "a_1.png"), cv2.IMREAD_UNCHANGED)[0, 0] == 999
    assert cv2.imread(str(root / "noisy_png" / "b_2.png"), cv2.IMREAD_UNCHANGED)[0, 0] == 1003
    assert cv2.imread(str(root / "preview" / "a_1.png")).ndim == 3
    assert np.load(root / "reference_npy" / "a_1.npy").dtype == np.float32
    assert np.allclose(np.load(root / "reference_npy" / "a_1.npy"), 999.0)
    assert np.allclose(np.load(root / "noisy_npy" / "b_2.npy"), 1003.0)
    assert cv2.imread(str(root / "mask" / "a_1.png"), cv2.IMREAD_UNCHANGED).min() == 255


def test_written_float_maps_score_as_the_test_step_and_pngs_do_not(tmp_path, tiny_data):
    """``evaluate --pred <set>/npy --ref <set>/reference_npy --mask <set>/mask`` gives the test step's numbers (to
    1e-9); the PNG maps, both rounded to whole millimetres, do not (here MSE +0.26 mm^2), which is why
    docs/evaluation.md gives the PNG route's offsets."""
    from tofdenoise.evaluation import evaluate_dirs
    from tofdenoise.training.module import DepthRestorer

    from .conftest import quiet_trainer

    torch.manual_seed(0)
    model = DepthRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 2}, loss="l1")
    quiet_trainer(tmp_path).test(model, datamodule=tiny_data)
    recorded = model.test_results["synthetic"]
    writer = DepthPredictionWriter(tmp_path / "pred", write_reference=True)
    quiet_trainer(tmp_path, callbacks=[writer]).predict(model, datamodule=tiny_data, return_predictions=False)
    root = tmp_path / "pred" / "synthetic"
    floats = evaluate_dirs(root / "npy", root / "reference_npy", root / "mask")
    raw = evaluate_dirs(root / "noisy_npy", root / "reference_npy", root / "mask")
    pngs = evaluate_dirs(root / "png", root / "reference_png", root / "mask")
    assert floats["num_images"] == 4 and floats["nan_px"] == 0
    for key in ("psnr_db", "mae_mm", "mse_mm2", "ssim"):
        assert floats["mean"][key] == pytest.approx(recorded[key], rel=1e-9, abs=1e-12)
        assert raw["mean"][key] == pytest.approx(recorded["raw"][key], rel=1e-9, abs=1e-12)
    assert 0.1 < pngs["mean"]["mse_mm2"] - recorded["mse_mm2"] < 0.4  # measured +0.26 mm^2


def test_csv_log_survives_a_resume_without_duplicates(tmp_path, tiny_data):
    """A run that went on past its checkpoint (as if killed later) and is resumed from it: the CSV log ends
    with exactly the rows of an uninterrupted run (epoch-0 rows kept, later rows replaced, none twice)."""
    import csv

    import lightning.pytorch as pl
    from lightning.pytorch.callbacks import ModelCheckpoint

    from tofdenoise.callbacks.csv_log import CSVLogResume, ResumableCSVLogger
    from tofdenoise.training.module import DepthRestorer

    def fit(ckpt_path=None):
        model = DepthRestorer(backbone="unet", backbone_kwargs={"width": 4, "stages": 2}, loss="l1")
        ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", filename="{epoch}", save_top_k=-1, every_n_epochs=1)
        resume = CSVLogResume()
        trainer = pl.Trainer(
            default_root_dir=tmp_path,
            accelerator="cpu",
            max_epochs=3,
            log_every_n_steps=1,
            logger=ResumableCSVLogger(tmp_path, name="csv", version=""),
            callbacks=[ckpt, resume],
            enable_progress_bar=False,
            enable_model_summary=False,
            num_sanity_val_steps=0,
        )
        trainer.fit(model, datamodule=tiny_data, ckpt_path=ckpt_path)
        with open(tmp_path / "csv" / "metrics.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        return [
            (r["epoch"], r["step"], tuple(sorted(k for k, v in r.items() if v and k not in ("epoch", "step"))))
            for r in rows
        ], resume.dropped_rows

    uninterrupted, dropped = fit()
    assert dropped == 0 and len(uninterrupted) > 6
    resumed, dropped = fit(ckpt_path=str(tmp_path / "ckpt" / "epoch=0.ckpt"))
    steps_epoch0 = sum(1 for e, _, keys in uninterrupted if e == "0" and "train/loss_step" in keys)
    assert dropped == sum(1 for _, s, _ in uninterrupted if int(s) >= steps_epoch0)
    assert resumed == uninterrupted
