"""Issue item 7: a network trained in float32 gives the same metrics under CPU bf16 autocast (within 2 %),
because its input is centred and scaled (``tofdenoise.models.conditioning``). With the raw depth / 1000 input
the same network stays at the identity (dead ReLUs, tests/training/test_recipes.py), and its input would be rounded
to 4-8 mm in bf16 (tests/models/test_conditioning.py)."""

from __future__ import annotations

import torch

from tofdenoise.training.metrics import depth_metrics_per_image
from tofdenoise.training.module import DepthRestorer
from tofdenoise.training.optim import parameter_groups

from .conftest import TinyDepthData


def _train(centering: str, steps: int = 150) -> tuple[DepthRestorer, TinyDepthData]:
    torch.manual_seed(0)
    data = TinyDepthData(n_train=16, n_val=8)
    model = DepthRestorer(
        backbone="unet", backbone_kwargs={"width": 8, "stages": 2}, loss="l1", conditioning={"centering": centering}
    )
    opt = torch.optim.AdamW(parameter_groups(model.backbone, model.optim.weight_decay), lr=2e-3)
    model.train()
    step = 0
    while step < steps:
        for batch in data.train_dataloader():
            loss = model.training_loss(batch)
            opt.zero_grad()
            loss.backward()
            opt.step()
            step += 1
    model.eval()
    return model, data


def _mae(model: DepthRestorer, data: TinyDepthData, bf16: bool) -> tuple[float, float]:
    maes, raws = [], []
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        for batch in data.val_dataloader():
            pred = model.restore_mm(batch)
            maes.append(depth_metrics_per_image(pred, batch["clean"], batch["mask"])["mae_mm"])
            raws.append(depth_metrics_per_image(batch["noisy"], batch["clean"], batch["mask"])["mae_mm"])
    return torch.cat(maes).mean().item(), torch.cat(raws).mean().item()


def test_bf16_autocast_matches_float32_with_centred_input():
    model, data = _train("gaussian")
    fp32, raw = _mae(model, data, bf16=False)
    bf16, _ = _mae(model, data, bf16=True)
    assert fp32 < 0.7 * raw  # the network learned something
    assert abs(bf16 - fp32) <= 0.02 * fp32, (fp32, bf16, raw)
