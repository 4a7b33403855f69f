"""ImagePanelLogger: fixed samples every validation epoch, PNG files, wandb offline and TensorBoard logging."""

from __future__ import annotations

import glob
from types import SimpleNamespace

import cv2
import lightning.pytorch as pl
import numpy as np
import pytest
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from torch import nn
from torch.utils.data import DataLoader, Dataset

from tofdenoise.callbacks.image_panels import ImagePanelLogger

H, W = 24, 32


class _Scenes(Dataset):
    def __init__(self, n: int = 10) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        g = torch.Generator().manual_seed(i)
        yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
        clean = (600.0 + 10.0 * i + 4.0 * xx + yy).float()[None]
        sigma = (1.0 + 0.1 * xx).float()[None]
        noisy = clean + sigma * torch.randn(clean.shape, generator=g)
        mask = torch.ones_like(clean)
        mask[:, :3, :4] = 0
        return {
            "noisy": noisy * mask,
            "clean": clean * mask,
            "sigma": sigma,
            "mask": mask,
            "amplitude": torch.ones_like(clean),
            "index": i,
            "name": f"scene_{i:02d}",
        }


class _Tiny(pl.LightningModule):
    def __init__(self) -> None:
        super().__init__()
        self.offset = nn.Parameter(torch.tensor(3.0))
        self.val_calls = 0

    def training_step(self, batch, batch_idx):
        return ((batch["noisy"] + self.offset - batch["clean"]) ** 2 * batch["mask"]).mean()

    def validation_step(self, batch, batch_idx):
        self.val_calls += 1
        return {"pred_mm": (batch["clean"] + self.offset).detach()}

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=1e-3)


def _fit(tmp_path, callback, loggers, epochs: int = 2):
    trainer = pl.Trainer(
        max_epochs=epochs,
        accelerator="cpu",
        devices=1,
        default_root_dir=tmp_path,
        logger=loggers,
        callbacks=[callback],
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_train_batches=1,
        num_sanity_val_steps=2,
        log_every_n_steps=1,
    )
    loader = DataLoader(_Scenes(), batch_size=4)
    trainer.fit(_Tiny(), train_dataloaders=DataLoader(_Scenes(4), batch_size=2), val_dataloaders=loader)
    return trainer


def _panel_height(n: int, tile_h: int = 5 * H) -> int:
    # default min_tile=160 enlarges 24x32 maps 5x; title + depth row + gap + error row (two-line titles)
    one = 20 + (20 + tile_h) + 4 + (36 + tile_h)
    return n * one + (n - 1) * 6


def test_fixed_panels_every_epoch_as_png_and_in_offline_wandb(tmp_path):
    import wandb
    from lightning.pytorch.loggers import WandbLogger

    cb = ImagePanelLogger(indices=3)
    logger = WandbLogger(offline=True, save_dir=str(tmp_path), project="tofdenoise-test")
    try:
        _fit(tmp_path, cb, [logger])
    finally:
        wandb.finish()
    assert cb.indices == [0, 4, 9]  # linspace(0, 9, 3) rounded
    files = sorted(p.name for p in (tmp_path / "panels").iterdir())
    assert files == ["epoch_000.png", "epoch_001.png"]  # none for the sanity check, no temp files
    img = cv2.imread(str(tmp_path / "panels" / "epoch_001.png"), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.shape[0] == _panel_height(3)
    media = glob.glob(str(tmp_path / "wandb" / "offline-run-*" / "files" / "media" / "images" / "val" / "panels_*.png"))
    assert len(media) == 2


def test_explicit_indices_dirpath_and_every_n_epochs(tmp_path):
    cb = ImagePanelLogger(indices=[7, 2], dirpath=tmp_path / "out", every_n_epochs=2, max_tile=16)
    _fit(tmp_path, cb, False, epochs=2)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["epoch_001.png"]
    img = cv2.imread(str(tmp_path / "out" / "epoch_001.png"))
    assert img.shape[0] < _panel_height(2)  # tiles downscaled to 16 px
    assert cb.last_panel_path == tmp_path / "out" / "epoch_001.png"


class _RecordingTB(TensorBoardLogger):
    @property
    def experiment(self):
        return self._recorder


def test_tensorboard_logger_receives_hwc_image(tmp_path):
    tb = object.__new__(_RecordingTB)
    calls = []
    tb._recorder = SimpleNamespace(add_image=lambda *a, **k: calls.append((a, k)))
    loader = DataLoader(_Scenes(), batch_size=4)
    trainer = SimpleNamespace(
        sanity_checking=False,
        current_epoch=4,
        global_step=40,
        global_rank=0,
        val_dataloaders=loader,
        default_root_dir=str(tmp_path),
        loggers=[tb],
    )
    cb = ImagePanelLogger(indices=[5])
    cb.on_validation_epoch_start(trainer, None)
    for batch_idx, batch in enumerate(loader):
        cb.on_validation_batch_end(trainer, None, {"pred_mm": batch["clean"]}, batch, batch_idx)
    cb.on_validation_epoch_end(trainer, None)
    assert len(calls) == 1
    (key, image, step), kwargs = calls[0]
    assert key == "val/panels" and step == 40 and kwargs == {"dataformats": "HWC"}
    assert image.dtype == np.uint8 and image.shape[0] == _panel_height(1)
    assert (tmp_path / "panels" / "epoch_004.png").is_file()


def test_missing_pred_mm_is_a_clear_error(tmp_path):
    loader = DataLoader(_Scenes(2), batch_size=2)
    trainer = SimpleNamespace(
        sanity_checking=False,
        current_epoch=0,
        global_step=0,
        global_rank=0,
        val_dataloaders=loader,
        default_root_dir=str(tmp_path),
        loggers=[],
    )
    cb = ImagePanelLogger(indices=1)
    cb.on_validation_epoch_start(trainer, None)
    batch = next(iter(loader))
    with pytest.raises(KeyError, match="pred_mm"):
        cb.on_validation_batch_end(trainer, None, torch.zeros(1), batch, 0)
    with pytest.raises(ValueError, match="indices"):
        ImagePanelLogger(indices=0)
