"""Run summary lines and the prediction writer's file formats."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from tofdenoise.callbacks.predict_writer import DepthPredictionWriter
from tofdenoise.callbacks.summary import format_fit_summary, format_test_summary


def test_summary_lines():
    line = format_fit_summary("unet-hetero-full", 20, 900, 370.4, torch.tensor(3.1234), "/r/checkpoints/best.ckpt",
                              "val/mae_mm", torch.tensor(6.05))
    assert line == ("[unet-hetero-full] fit: 20 epochs, 900 steps in 6m10s | best val/mae_mm 3.123 (raw 6.050)"
                    " -> /r/checkpoints/best.ckpt")
    assert "(no checkpoint written)" in format_fit_summary("x", 1, 1, 1.0, None, "", "val/mae_mm")
    res = {"synthetic": {"mae_mm": 3.1, "psnr_db": 44.12, "ssim": 0.99512,
                         "raw": {"mae_mm": 6.0, "psnr_db": 39.9, "ssim": 0.93}},
           "real": {"mae_mm": None, "psnr_db": 30.0, "ssim": 0.9, "raw": {}}}
    line = format_test_summary("r", res, 3725.0)
    assert line.startswith("[r] test in 1h02m05s | synthetic: MAE 3.10 mm (raw 6.00), PSNR 44.12 dB (raw 39.90)")
    assert "| real: MAE n/a mm (raw n/a)" in line and "\n" not in line


def test_prediction_writer_layout(tmp_path):
    class T:  # the trainer attributes the writer reads
        default_root_dir = str(tmp_path)
        datamodule = type("DM", (), {"test_set_names": ["synthetic", "real"]})()

    w = DepthPredictionWriter(write_sigma=True, write_reference=True, write_previews=True)
    pred = torch.full((2, 1, 8, 10), 1000.25)
    batch = {"name": ["a_1", "b_2"], "index": torch.tensor([3, 4]), "sigma": torch.full((2, 1, 8, 10), 2.5),
             "clean": torch.full((2, 1, 8, 10), 999.0), "noisy": torch.full((2, 1, 8, 10), 1003.0),
             "mask": torch.ones(2, 1, 8, 10)}
    w.write_on_batch_end(T(), None, pred, None, batch, 0, dataloader_idx=1)
    root = tmp_path / "predictions" / "real"
    assert sorted(p.name for p in (root / "png").iterdir()) == ["a_1.png", "b_2.png"]
    assert np.load(root / "npy" / "a_1.npy").dtype == np.float32
    assert np.allclose(np.load(root / "npy" / "b_2.npy"), 1000.25)
    assert np.allclose(np.load(root / "sigma_npy" / "a_1.npy"), 2.5)
    assert cv2.imread(str(root / "reference_png" / "a_1.png"), cv2.IMREAD_UNCHANGED)[0, 0] == 999
    assert cv2.imread(str(root / "noisy_png" / "b_2.png"), cv2.IMREAD_UNCHANGED)[0, 0] == 1003
    assert cv2.imread(str(root / "preview" / "a_1.png")).ndim == 3
