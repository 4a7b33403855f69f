"""Fixtures for the LightningModule tests: a tiny in-memory depth dataset in the batch layout of the contract
(``noisy``, ``clean``, ``sigma``, ``mask``, ``amplitude`` (B,1,H,W) float32 mm, ``index``, ``name``)."""

from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from torch.utils.data import DataLoader, Dataset


def quiet_trainer(tmp_path, **kw) -> pl.Trainer:
    """A CPU ``pl.Trainer`` for the tests: one device, no logger, progress bar, model summary, checkpointing or sanity
    validation; ``kw`` overrides or adds any argument."""
    args = dict(
        default_root_dir=tmp_path,
        accelerator="cpu",
        devices=1,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
        num_sanity_val_steps=0,
    )
    args.update(kw)
    return pl.Trainer(**args)


def make_sample(index: int, size: int = 32, noise_seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(1000 + index)
    yy, xx = torch.meshgrid(
        torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32), indexing="ij"
    )
    base = 600.0 + 400.0 * torch.rand((), generator=g)
    clean = base + 3.0 * xx + 2.0 * yy
    x0, y0 = (torch.randint(0, size // 2, (2,), generator=g)).tolist()
    clean[y0 : y0 + size // 3, x0 : x0 + size // 3] -= 150.0
    amplitude = 1e6 / clean**2
    sigma = 2.0 + 0.004 * clean
    gn = torch.Generator().manual_seed(noise_seed * 100003 + index)
    noisy = clean + sigma * torch.randn(clean.shape, generator=gn)
    mask = torch.ones_like(clean)
    mask[:2, :5] = 0.0
    clean = clean * mask
    noisy = noisy * mask
    return {
        "noisy": noisy[None],
        "clean": clean[None],
        "sigma": sigma[None],
        "mask": mask[None],
        "amplitude": amplitude[None],
        "index": torch.tensor(index),
        "name": f"scene_{index:03d}",
    }


class TinyDepthSet(Dataset):
    def __init__(self, n: int, size: int = 32, offset: int = 0) -> None:
        self.items = [make_sample(offset + i, size) for i in range(n)]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        return self.items[i]


class TinyDepthData(pl.LightningDataModule):
    """Train / val / test loaders over a few 32x32 synthetic planes; ``test_set_names`` configurable."""

    def __init__(
        self,
        n_train: int = 8,
        n_val: int = 4,
        n_test: int = 4,
        size: int = 32,
        batch_size: int = 4,
        test_set_names: tuple[str, ...] = ("synthetic",),
    ) -> None:
        super().__init__()
        self.train_set = TinyDepthSet(n_train, size, 0)
        self.val_set = TinyDepthSet(n_val, size, 100)
        self.test_sets = [TinyDepthSet(n_test, size, 200 + 50 * k) for k in range(len(test_set_names))]
        self.test_set_names = list(test_set_names)
        self.batch_size = batch_size

    def train_dataloader(self):
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True)

    def val_dataloader(self):
        return DataLoader(self.val_set, batch_size=self.batch_size)

    def test_dataloader(self):
        return [DataLoader(s, batch_size=self.batch_size) for s in self.test_sets]

    def predict_dataloader(self):
        return self.test_dataloader()


@pytest.fixture
def tiny_data() -> TinyDepthData:
    return TinyDepthData()


@pytest.fixture
def tiny_data_cls() -> type[TinyDepthData]:
    return TinyDepthData
