"""The optimiser and its schedule: AdamW, a linear warm-up, then a per-step cosine (the paper, Sec. V-A).

One group of settings (``model.optim`` in the configs): :class:`OptimSettings`. :func:`parameter_groups` splits a
network's parameters into decayed and not decayed ones; :meth:`OptimSettings.build` returns what Lightning's
``configure_optimizers`` returns. docs/training.md ("Optimiser and schedule") gives the reasons.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import nn

__all__ = ["OptimSettings", "parameter_groups"]


@dataclass(frozen=True)
class OptimSettings:
    """AdamW and its learning-rate schedule.

    Args:
        lr: initial learning rate (paper: 2e-4).
        weight_decay: decay of >= 2-D weights not flagged ``_no_weight_decay`` (AdamW's default 1e-2; the paper
            does not state it).
        betas: AdamW betas.
        lr_min: learning rate at the end of the cosine (paper: 1e-6).
        warmup_steps: linear warm-up from lr / warmup_steps to lr over this many optimiser steps before the
            cosine (0 = none, the paper's schedule); protects a zero-initialised residual head from Adam's large
            first steps at high rates.
    """

    lr: float = 2e-4
    weight_decay: float = 1e-2
    betas: tuple[float, float] = (0.9, 0.999)
    lr_min: float = 1e-6
    warmup_steps: int = 0

    def __post_init__(self) -> None:
        lr, lr_min = float(self.lr), float(self.lr_min)
        if not (lr > 0 and 0 <= lr_min <= lr):
            raise ValueError(f"optim: need lr > 0 and 0 <= lr_min <= lr, got lr={self.lr}, lr_min={self.lr_min}")
        if int(self.warmup_steps) < 0:
            raise ValueError(f"optim.warmup_steps must be >= 0, got {self.warmup_steps}")
        if float(self.weight_decay) < 0:
            raise ValueError(f"optim.weight_decay must be >= 0, got {self.weight_decay}")
        betas = tuple(self.betas)
        if len(betas) != 2:
            raise ValueError(f"optim.betas needs two values, got {self.betas}")
        object.__setattr__(self, "lr", lr)
        object.__setattr__(self, "lr_min", lr_min)
        object.__setattr__(self, "weight_decay", float(self.weight_decay))
        object.__setattr__(self, "warmup_steps", int(self.warmup_steps))
        object.__setattr__(self, "betas", (float(betas[0]), float(betas[1])))  # whichever front end passed a list

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["betas"] = list(self.betas)  # YAML and checkpoints hold lists
        return out

    def build(self, network: nn.Module, total_steps: float) -> dict[str, Any]:
        """AdamW over :func:`parameter_groups` of ``network`` and the schedule over ``total_steps`` optimiser
        steps (Lightning's ``estimated_stepping_batches``): what ``configure_optimizers`` returns."""
        if not math.isfinite(total_steps) or total_steps < 1:
            raise ValueError(
                "the cosine schedule runs over the whole run; set trainer.max_epochs or trainer.max_steps "
                f"(estimated optimiser steps: {total_steps})"
            )
        total = int(total_steps)
        opt = torch.optim.AdamW(parameter_groups(network, self.weight_decay), lr=self.lr, betas=self.betas)
        warm = min(self.warmup_steps, total - 1)
        sched: torch.optim.lr_scheduler.LRScheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
            opt, T_max=total - warm, eta_min=self.lr_min
        )
        if warm > 0:
            ramp = torch.optim.lr_scheduler.LinearLR(opt, start_factor=1.0 / warm, end_factor=1.0, total_iters=warm)
            sched = torch.optim.lr_scheduler.SequentialLR(opt, [ramp, sched], milestones=[warm])
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}


def parameter_groups(network: nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    """AdamW groups: decay on >= 2-D weights; biases, norms and parameters flagged ``_no_weight_decay`` (SS2D's
    A_log and D, as in VMamba/MambaIR) are not decayed. Frozen parameters are left out."""
    decay, no_decay = [], []
    for p in network.parameters():
        if p.requires_grad:
            wants_decay = p.ndim >= 2 and not getattr(p, "_no_weight_decay", False)
            (decay if wants_decay else no_decay).append(p)
    groups = [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return [g for g in groups if g["params"]]
