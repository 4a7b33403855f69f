"""``DepthRestorer``: one LightningModule for every registered restoration backbone.

The paper's recipe (Sec. V-A: AdamW 2e-4, per-step cosine to 1e-6, checkpoint at the lowest validation MAE) and
every design decision of training (input conditioning, weight decay, EMA, compile, deep supervision, exact DDP
metrics, the learned guard, classical filters) are described in docs/training.md. Where the pieces live:
what the network sees, ``models/conditioning.py``; losses, ``losses.py``; per-image metrics, ``metrics.py``;
the learned guard's inputs, ``learned_guard.py``; the records a run writes, ``results.py`` and
``callbacks/run_outputs.py``. Every hyper-parameter is a plain value (backbone and loss by registered name), so a
checkpoint loads with ``torch.load(weights_only=True)`` and ``DepthRestorer.load_from_checkpoint(path)``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn

from tofdenoise.models import build_backbone, tiled_forward
from tofdenoise.models.conditioning import CENTERING_MODES, condition_input
from tofdenoise.models.registry import accepts_kwarg, backbone_factory, is_trainable
from tofdenoise.records import set_entry
from tofdenoise.training.init_weights import INIT_RECORD_KEY, load_init_weights
from tofdenoise.training.learned_guard import LearnedGuard
from tofdenoise.training.losses import DepthLoss, build_loss
from tofdenoise.training.metrics import DepthMetrics, FixedBatchCache, depth_metrics_per_image

__all__ = ["DepthRestorer", "CheckpointMismatchError", "step_predictions", "final_prediction", "step_loss_weights"]

log = logging.getLogger(__name__)


class CheckpointMismatchError(ValueError):
    """A checkpoint was written by a DepthRestorer with another backbone / architecture."""


def _architecture(hparams: dict[str, Any]) -> dict[str, Any]:
    """What defines the network's parameters, from a hyper-parameter dict: a checkpoint must agree on all of it."""
    return {
        "backbone": hparams.get("backbone"),
        "backbone_kwargs": dict(hparams.get("backbone_kwargs") or {}),
        "use_signal_channel": bool(hparams.get("use_signal_channel", False)),
        "ema": hparams.get("ema_decay") is not None,
        "input_centering": hparams.get("input_centering"),
    }


class DepthRestorer(pl.LightningModule):
    """Depth restoration with any backbone of :func:`tofdenoise.models.build_backbone`.

    Args:
        backbone: registered backbone name (``tofdenoise.models.available_backbones()``).
        backbone_kwargs: constructor keyword arguments of the backbone (plain values; ``in_channels`` is set
            from ``use_signal_channel``).
        loss: registered loss name (``tofdenoise.training.losses.available_losses()``: ``l1``, ``nar``, ``full``).
        loss_kwargs: keyword arguments of the loss (e.g. ``beta``, ``lambda_g``).
        depth_scale_mm: fixed divisor turning (centred) millimetres into network units. 100 mm puts the noise
            (3-12 mm) at 0.03-0.12 and surface detail near 1: inputs of unit order, which Adam's first steps
            cannot swamp (docs/training.md#what-the-network-sees-input-conditioning).
        input_centering: ``local`` (default: depth minus a smooth local offset, see
            ``tofdenoise.models.conditioning``), ``image`` (minus the per-image valid median) or ``none``
            (raw depth / depth_scale_mm, checkpoints written before centring).
        centering_block_px: block size of the ``local`` offset in pixels.
        use_signal_channel: feed the normalised amplitude as a second input channel.
        lr: AdamW initial learning rate (paper: 2e-4).
        weight_decay: AdamW weight decay on >= 2-D weights not flagged `_no_weight_decay` (AdamW's default 1e-2;
            the paper does not state it).
        betas: AdamW betas.
        lr_min: learning rate at the end of the cosine schedule (paper: 1e-6).
        warmup_steps: linear warm-up from lr / warmup_steps to lr over this many optimiser steps before the
            cosine (0 = none, the paper's schedule). Protects a zero-initialised residual head from Adam's
            large first steps at high learning rates.
        ema_decay: decay of the EMA of the weights (e.g. 0.999); ``None`` = no EMA.
        compile: ``torch.compile`` the backbone for training.
        d_max_mm: fixed PSNR/SSIM peak (paper: 1000 mm).
        predict_tile_size: ``predict`` runs frames larger than this (either side) tile by tile
            (``tofdenoise.models.tiled_forward``); ``None`` = never tile.
        eval_tile_size: the same for validation and test (``None`` = whole frames, the paper's protocol).
        tile_overlap: overlap of neighbouring tiles in pixels.
        learned_margin: the learned guard: a run counts as learned only when its best validation MAE is at
            most ``(1 - learned_margin)`` x the raw validation MAE (default 0.05: 5 % below raw).
        init_weights: a checkpoint or state-dict file whose weights the network starts from when a fit begins
            without ``ckpt_path`` (fine-tuning: optimiser, schedule and epoch start fresh;
            ``tofdenoise.training.init_weights``). Any missing, unexpected or mis-shaped layer is an error;
            the path and its sha256 go to ``run_info.json`` and the checkpoints.
    """

    def __init__(
        self,
        backbone: str = "dvss",
        backbone_kwargs: dict[str, Any] | None = None,
        loss: str = "full",
        loss_kwargs: dict[str, Any] | None = None,
        depth_scale_mm: float = 100.0,
        input_centering: str = "local",
        centering_block_px: int = 16,
        use_signal_channel: bool = False,
        lr: float = 2e-4,
        weight_decay: float = 1e-2,
        betas: tuple[float, float] = (0.9, 0.999),
        lr_min: float = 1e-6,
        warmup_steps: int = 0,
        ema_decay: float | None = None,
        compile: bool = False,
        d_max_mm: float = 1000.0,
        predict_tile_size: int | None = 512,
        eval_tile_size: int | None = None,
        tile_overlap: int = 32,
        learned_margin: float = 0.05,
        init_weights: str | None = None,
    ) -> None:
        super().__init__()
        backbone_kwargs = dict(backbone_kwargs or {})
        loss_kwargs = dict(loss_kwargs or {})
        if not depth_scale_mm > 0:
            raise ValueError(f"DepthRestorer.depth_scale_mm must be > 0, got {depth_scale_mm}")
        if input_centering not in CENTERING_MODES:
            raise ValueError(
                f"DepthRestorer.input_centering: unknown mode {input_centering!r}; valid: {', '.join(CENTERING_MODES)}"
            )
        if int(centering_block_px) < 1:
            raise ValueError(f"DepthRestorer.centering_block_px must be >= 1, got {centering_block_px}")
        if not (lr > 0 and 0 <= lr_min <= lr):
            raise ValueError(f"DepthRestorer: need lr > 0 and 0 <= lr_min <= lr, got lr={lr}, lr_min={lr_min}")
        if warmup_steps < 0:
            raise ValueError(f"DepthRestorer.warmup_steps must be >= 0, got {warmup_steps}")
        if ema_decay is not None and not 0.0 < ema_decay < 1.0:
            raise ValueError(f"DepthRestorer.ema_decay must be in (0, 1) or null, got {ema_decay}")
        if not 0.0 <= learned_margin < 1.0:
            raise ValueError(f"DepthRestorer.learned_margin must be in [0, 1), got {learned_margin}")
        if len(betas) != 2:
            raise ValueError(f"DepthRestorer.betas needs two values, got {betas}")
        betas = (float(betas[0]), float(betas[1]))  # a tuple whichever front end passed a list
        in_channels = 2 if use_signal_channel else 1
        if backbone_kwargs.get("in_channels", in_channels) != in_channels:
            raise ValueError(
                f"DepthRestorer: backbone_kwargs.in_channels={backbone_kwargs['in_channels']} contradicts "
                f"use_signal_channel={use_signal_channel} (needs {in_channels}); leave in_channels out"
            )
        _check_backbone_input(backbone, backbone_kwargs, input_centering, use_signal_channel, depth_scale_mm)
        # plain values only: checkpoints load with weights_only=True
        self.save_hyperparameters()

        net_kwargs = {k: v for k, v in backbone_kwargs.items() if k != "in_channels"}
        if accepts_kwarg(backbone, "depth_scale_mm"):  # a filter comparing depth differences in mm
            net_kwargs["depth_scale_mm"] = float(depth_scale_mm)
        #: False for a classical filter without trainable parameters (``tofdenoise classic``): never fitted
        self.trainable = is_trainable(backbone)
        self.backbone: nn.Module = build_backbone(backbone, in_channels=in_channels, **net_kwargs)
        self.criterion: DepthLoss = build_loss(loss, **loss_kwargs)
        self.ema: torch.optim.swa_utils.AveragedModel | None = None
        if ema_decay is not None:
            self.ema = torch.optim.swa_utils.AveragedModel(
                self.backbone, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(ema_decay), use_buffers=True
            )
            self.ema.requires_grad_(False)
        self._compiled: Any = None

        self.val_metrics = DepthMetrics(d_max_mm=d_max_mm)
        self.val_raw_metrics = DepthMetrics(d_max_mm=d_max_mm)
        #: per-image Raw-row values of each validation batch: the validation noise is fixed, so they are computed
        #: once and reused every epoch (recomputed if the batch ever differs)
        self._raw_val_cache = FixedBatchCache()
        self.test_metrics = nn.ModuleDict()
        self.test_raw_metrics = nn.ModuleDict()
        self._test_names: dict[str, dict[int, str]] = {}
        #: final test results per set (filled at the end of ``trainer.test``), the ``metrics.json`` entries:
        #: {set: {"psnr_db", "mae_mm", "mse_mm2", "ssim", "mae_mm_pooled", "images", ..., "raw": {...}}}
        self.test_results: dict[str, dict[str, Any]] = {}
        #: per-image rows per set: {set: {"rows", "raw_rows", "names"}} (``DepthMetrics.per_image_rows``)
        self.test_per_image: dict[str, dict[str, Any]] = {}
        #: the learned guard's inputs (``training/learned_guard.py``)
        self.guard = LearnedGuard()
        #: {"path", "sha256"} of the weights this run started from (``init_weights``), None for a fresh init
        self.init_record: dict[str, str] | None = None

    # ------------------------------------------------------------------ networks
    @property
    def eval_net(self) -> nn.Module:
        """The network used for validation/test/predict: the EMA copy when EMA is on."""
        return self.ema.module if self.ema is not None else self.backbone

    def configure_model(self) -> None:
        if self.hparams.compile and self._compiled is None:
            # kept out of the module tree so the state dict keys stay the same
            object.__setattr__(self, "_compiled", torch.compile(self.backbone))

    def forward(self, x: Tensor) -> Tensor:
        """Backbone forward in network units, (B, C, H, W) -> (B, 1, H, W) (the final prediction of a
        deep-supervised backbone)."""
        return final_prediction(self.backbone(x))

    def condition(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor]:
        """Network input (B, C, H, W) and the offset (mm) to add back to ``depth_scale_mm`` x its output
        (:func:`tofdenoise.models.conditioning.condition_input`, in float32 whatever the autocast setting)."""
        noisy = batch["noisy"]
        hp = self.hparams
        if hp.use_signal_channel and "amplitude" not in batch:
            raise KeyError("DepthRestorer(use_signal_channel=True) needs batch['amplitude']")
        with torch.autocast(device_type=noisy.device.type, enabled=False):
            return condition_input(
                noisy,
                batch.get("amplitude"),
                centering=hp.input_centering,
                block_px=int(hp.centering_block_px),
                depth_scale_mm=hp.depth_scale_mm,
                use_signal_channel=hp.use_signal_channel,
            )

    def network_input(self, batch: dict[str, Any]) -> Tensor:
        """The conditioned network input of :meth:`condition` (without the offset)."""
        return self.condition(batch)[0]

    def restore_mm(self, batch: dict[str, Any], tile: int | None = None, net: nn.Module | None = None) -> Tensor:
        """Restored depth in millimetres (B, 1, H, W) at every pixel (input holes get the network's estimate;
        callers mask them), tiled when a side exceeds ``tile``."""
        net = self.eval_net if net is None else net
        x, offset = self.condition(batch)
        if tile is not None and max(x.shape[-2:]) > tile:
            y = tiled_forward(lambda t: final_prediction(net(t)), x, tile=tile, overlap=self.hparams.tile_overlap)
        else:
            y = final_prediction(net(x))
        return y.float() * self.hparams.depth_scale_mm + offset

    # ------------------------------------------------------------------ optimisation
    def parameter_groups(self) -> list[dict[str, Any]]:
        """AdamW groups: decay on >= 2-D weights; biases, norms and parameters flagged ``_no_weight_decay``
        (SS2D's A_log and D, as in VMamba/MambaIR) are not decayed."""
        decay, no_decay = [], []
        for p in self.backbone.parameters():
            if p.requires_grad:
                wants_decay = p.ndim >= 2 and not getattr(p, "_no_weight_decay", False)
                (decay if wants_decay else no_decay).append(p)
        groups = [
            {"params": decay, "weight_decay": self.hparams.weight_decay},
            {"params": no_decay, "weight_decay": 0.0},
        ]
        return [g for g in groups if g["params"]]

    def configure_optimizers(self) -> dict[str, Any]:
        if not self.trainable:
            raise ValueError(
                f"DepthRestorer: backbone {self.hparams.backbone!r} is a classical filter without "
                "trainable parameters: there is nothing to fit; tune and test it with "
                "`tofdenoise classic` (docs/models.md#classical-row-joint-bilateral-filter)"
            )
        opt = torch.optim.AdamW(self.parameter_groups(), lr=self.hparams.lr, betas=tuple(self.hparams.betas))
        total = self.trainer.estimated_stepping_batches
        if not math.isfinite(total) or total < 1:
            raise ValueError(
                "DepthRestorer: the cosine schedule runs over the whole run; set trainer.max_epochs "
                f"or trainer.max_steps (estimated optimiser steps: {total})"
            )
        total = int(total)
        warm = min(int(self.hparams.warmup_steps), total - 1)
        sched: torch.optim.lr_scheduler.LRScheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
            opt, T_max=total - warm, eta_min=self.hparams.lr_min
        )
        if warm > 0:
            ramp = torch.optim.lr_scheduler.LinearLR(opt, start_factor=1.0 / warm, end_factor=1.0, total_iters=warm)
            sched = torch.optim.lr_scheduler.SequentialLR(opt, [ramp, sched], milestones=[warm])
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step", "frequency": 1}}

    def training_terms(self, batch: dict[str, Any], net: nn.Module | None = None) -> dict[str, Tensor]:
        """The loss of one training batch through ``net`` (default: the training network) with its parts:
        ``DepthLoss.terms`` (``"loss"``: the total, with gradient; the parts, e.g. ``"nar"``, ``"grad"``, detached).

        Deep supervision: when the network returns a list of step predictions (:func:`step_predictions`), every
        term is ``sum_k w_k term(pred_k)`` with the backbone's ``step_loss_weights`` (normalised to sum 1;
        uniform when it has none)."""
        if net is None:
            net = self._compiled if self._compiled is not None else self.backbone
        x, offset = self.condition(batch)
        preds = step_predictions(net(x))
        weights = step_loss_weights(net, len(preds))
        # the loss in millimetres relative to the offset (differences are those of the restored depth in mm)
        target_mm = batch["clean"].float() - offset
        terms = [
            self.criterion.terms(p.float() * self.hparams.depth_scale_mm, target_mm, batch["sigma"], batch["mask"])
            for p in preds
        ]
        if len(terms) == 1:
            return terms[0]
        return {key: sum(w * t[key] for w, t in zip(weights, terms)) for key in terms[0]}

    def training_loss(self, batch: dict[str, Any], net: nn.Module | None = None) -> Tensor:
        """The loss of one training batch through ``net`` (default: the training network)."""
        return self.training_terms(batch, net)["loss"]

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor:
        terms = self.training_terms(batch)
        loss = terms["loss"]
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"DepthRestorer: non-finite training loss {loss.item()} at step "
                f"{self.global_step} (lower lr, enable gradient clipping, check the data)"
            )
        batch_size = batch["noisy"].shape[0]
        self.log("train/loss", loss, on_step=True, on_epoch=True, prog_bar=True, batch_size=batch_size)
        for name, value in terms.items():  # the parts: train/loss_l1; train/loss_nar; train/loss_nar + _grad
            if name != "loss":
                self.log(f"train/loss_{name}", value, on_step=True, on_epoch=True, batch_size=batch_size)
        self.log("train/lr", self.trainer.optimizers[0].param_groups[0]["lr"], on_step=True, on_epoch=False)
        return loss

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.ema is not None:
            self.ema.update_parameters(self.backbone)

    # ------------------------------------------------------------------ validation
    def validation_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> dict[str, Tensor]:
        pred_mm = self.restore_mm(batch, tile=self.hparams.eval_tile_size)
        loss = self.criterion(pred_mm, batch["clean"], batch["sigma"], batch["mask"])
        self.log("val/loss", loss, on_step=False, on_epoch=True, batch_size=pred_mm.shape[0], sync_dist=True)
        index = _loader_index(batch.get("index"), dataloader_idx)
        self.val_metrics.update(pred_mm, batch["clean"], batch["mask"], index=index)
        self.val_raw_metrics.update(
            batch["noisy"],
            batch["clean"],
            batch["mask"],
            index=index,
            per_image=self._raw_val_per_image(batch, batch_idx, dataloader_idx),
        )
        return {"pred_mm": pred_mm}

    def _raw_val_per_image(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int) -> dict[str, Tensor]:
        """Raw-row per-image metrics of a validation batch (noisy input vs reference), from the cache when the
        batch is the one seen before at this position."""
        return self._raw_val_cache.get(
            (dataloader_idx, batch_idx),
            batch,
            lambda: depth_metrics_per_image(batch["noisy"], batch["clean"], batch["mask"], self.hparams.d_max_mm),
        )

    def on_validation_epoch_end(self) -> None:
        restored = self.val_metrics.compute()
        raw = self.val_raw_metrics.compute()
        values = {f"val/{k}": float(v) for k, v in restored.items()}
        values.update({f"val/raw/{k}": float(v) for k, v in raw.items()})
        if self._trainer is not None and self.trainer.state.fn == "fit" and not self.trainer.sanity_checking:
            self.guard.observe_validation(values["val/mae_mm"], values["val/raw/mae_mm"])
        # compute() gathered the rows of every process: each rank logs the same exact value (no sync_dist
        # reduction needed; the checkpoint callback of every rank sees the single-process value)
        self.log("val/mae_mm", values.pop("val/mae_mm"), prog_bar=True)
        self.log("val/psnr_db", values.pop("val/psnr_db"), prog_bar=True)
        self.log_dict(values)
        self.val_metrics.reset()
        self.val_raw_metrics.reset()

    # ------------------------------------------------------------------ test
    def test_set_names(self) -> list[str]:
        """Names of the test loaders in order (``datamodule.test_set_names``; ``["synthetic"]`` without one)."""
        dm = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        names = getattr(dm, "test_set_names", None)
        if names:
            return [str(n) for n in names]
        loaders = self.trainer.test_dataloaders if self._trainer is not None else None
        n = len(loaders) if isinstance(loaders, (list, tuple)) else 1
        return ["synthetic"] if n == 1 else [f"set{i}" for i in range(n)]

    def on_test_start(self) -> None:
        self.test_results = {}
        self.test_per_image = {}
        self._test_names = {}
        for name in self.test_set_names():
            self.test_metrics[name] = DepthMetrics(d_max_mm=self.hparams.d_max_mm).to(self.device)
            self.test_raw_metrics[name] = DepthMetrics(d_max_mm=self.hparams.d_max_mm).to(self.device)
            self._test_names[name] = {}

    def test_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> dict[str, Tensor]:
        names = self.test_set_names()
        if dataloader_idx >= len(names):
            raise IndexError(f"test loader {dataloader_idx} has no name in datamodule.test_set_names={names}")
        set_name = names[dataloader_idx]
        pred_mm = self.restore_mm(batch, tile=self.hparams.eval_tile_size)
        index = batch.get("index")
        if index is None and self.trainer.world_size == 1:
            # one process: the position in the loader identifies the image (under DDP DepthMetrics refuses
            # a batch without index: the sampler's padded repeats could not be told apart)
            start = batch_idx * pred_mm.shape[0]
            index = torch.arange(start, start + pred_mm.shape[0], device=pred_mm.device)
        self.test_metrics[set_name].update(pred_mm, batch["clean"], batch["mask"], index=index)
        self.test_raw_metrics[set_name].update(batch["noisy"], batch["clean"], batch["mask"], index=index)
        if "name" in batch and index is not None:
            for i, n in zip(torch.as_tensor(index).tolist(), batch["name"]):
                self._test_names[set_name][int(i)] = str(n)
        return {"pred_mm": pred_mm}

    def on_test_epoch_end(self) -> None:
        for set_name in self.test_set_names():
            metric, raw_metric = self.test_metrics[set_name], self.test_raw_metrics[set_name]
            restored = {k: float(v) for k, v in metric.compute().items()}
            raw = {k: float(v) for k, v in raw_metric.compute().items()}
            # gathered from every process, each image once (DistributedSampler padding dropped)
            rows, raw_rows = metric.per_image_rows(), raw_metric.per_image_rows()
            counts = metric.counts()
            self.test_results[set_name] = set_entry(restored, raw, counts)
            self.test_per_image[set_name] = {
                "rows": rows,
                "raw_rows": raw_rows,
                "names": _gather_names(self._test_names[set_name]),
            }
            logged = {f"test/{set_name}/{k}": v for k, v in restored.items()}
            logged.update({f"test/{set_name}/raw/{k}": v for k, v in raw.items()})
            self.log_dict(logged)
            metric.reset()
            raw_metric.reset()

    # ------------------------------------------------------------------ predict
    def predict_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> Tensor:
        """Restored depth in mm (B, 1, H, W); pixels invalid in the input (``mask == 0``) are set to 0."""
        pred_mm = self.restore_mm(batch, tile=self.hparams.predict_tile_size)
        if "mask" in batch:
            pred_mm = torch.where(batch["mask"] > 0, pred_mm, torch.zeros_like(pred_mm))
        return pred_mm

    # ------------------------------------------------------------------ learned guard
    def learned_record(self) -> dict[str, Any]:
        """The learned guard's verdict (``training.results.learned_verdict``, or ``classical_verdict`` for a
        classical filter): ``trained_steps``, ``best_val_mae_mm``, ``raw_val_mae_mm``, ``learned_margin``,
        ``learned``, ``learned_reason`` (inputs: ``training/learned_guard.py``)."""
        margin = float(self.hparams.get("learned_margin", 0.05))
        return self.guard.verdict(self.trainable, margin, self._trainer)

    def record_tuning(self, best_val_mae_mm: float, raw_val_mae_mm: float) -> None:
        """The validation result of a classical filter's parameter search (its "fit"): the validation MAE of
        the chosen parameters and the raw validation MAE on the same images, for :meth:`learned_record`."""
        if self.trainable:
            raise RuntimeError(
                f"DepthRestorer.record_tuning: backbone {self.hparams.backbone!r} is a network; "
                "its validation MAEs come from trainer.fit"
            )
        self.guard.record_tuning(best_val_mae_mm, raw_val_mae_mm)

    def on_fit_start(self) -> None:
        self.guard.start_fit()
        resuming = self._trainer is not None and self.trainer.ckpt_path is not None
        if self.hparams.get("init_weights") and not resuming:
            # after the modules are set up, before the sanity check: the optimiser holds these same tensors
            self.init_record = load_init_weights(self, str(self.hparams.init_weights))
            log.info("network initialised from %s (sha256 %s)", self.init_record["path"], self.init_record["sha256"])

    def on_fit_end(self) -> None:
        self.guard.end_fit(self.trainer)

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Keep the learned guard's inputs in the checkpoint (plain values: loads with weights_only=True)."""
        if self._trainer is not None:
            self.guard.save(checkpoint, self.trainer)
        if self.init_record is not None:
            checkpoint[INIT_RECORD_KEY] = dict(self.init_record)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Refuse a checkpoint written for another backbone/architecture with a readable message; restore the
        learned guard's record (validation MAEs continue across a resume)."""
        self._check_architecture(checkpoint)
        init = checkpoint.get(INIT_RECORD_KEY)
        self.init_record = dict(init) if isinstance(init, dict) else None
        self.guard.load(checkpoint)

    def _check_architecture(self, checkpoint: dict[str, Any]) -> None:
        saved = checkpoint.get("hyper_parameters")
        if not saved:
            return
        mine, theirs = _architecture(dict(self.hparams)), _architecture(dict(saved))
        diff = {k: (theirs[k], mine[k]) for k in mine if mine[k] != theirs[k]}
        if diff:
            lines = "; ".join(f"{k}: checkpoint {a!r} vs this model {b!r}" for k, (a, b) in diff.items())
            raise CheckpointMismatchError(
                f"checkpoint was written by a DepthRestorer with another architecture ({lines}). "
                f"Load it with DepthRestorer.load_from_checkpoint(path) (it rebuilds the saved backbone), "
                f"or select backbone={theirs['backbone']!r} with the same backbone_kwargs"
            )


def step_predictions(out: Tensor | Sequence[Tensor]) -> list[Tensor]:
    """The deep-supervision protocol: a backbone's forward returns one prediction (B, 1, H, W), or -- a
    backbone with ``deep_supervision = True`` in training mode -- a list/tuple of its K step predictions, the
    final one last. Returns the predictions as a list (one element for an ordinary backbone)."""
    if isinstance(out, Tensor):
        return [out]
    if isinstance(out, (list, tuple)) and out and all(isinstance(p, Tensor) for p in out):
        return list(out)
    raise TypeError(
        f"backbone output: expected a tensor or a non-empty list/tuple of tensors (one per refinement "
        f"step), got {type(out).__name__}"
    )


def final_prediction(out: Tensor | Sequence[Tensor]) -> Tensor:
    """The prediction a backbone output stands for: the tensor itself, or the last of a list of step predictions."""
    return step_predictions(out)[-1]


def step_loss_weights(backbone: nn.Module, steps: int) -> list[float]:
    """Loss weights of ``steps`` step predictions, normalised to sum 1: the backbone's ``step_loss_weights``
    (a sequence of ``steps`` non-negative numbers, not all 0) when it has one, else uniform (the mean)."""
    raw = getattr(backbone, "step_loss_weights", None)
    if raw is None:
        return [1.0 / steps] * steps
    raw = [float(w) for w in raw]
    if len(raw) != steps or min(raw) < 0 or not sum(raw) > 0:
        raise ValueError(
            f"{type(backbone).__name__}.step_loss_weights: expected {steps} non-negative weights (one per "
            f"returned step prediction, not all 0), got {raw}"
        )
    total = sum(raw)
    return [w / total for w in raw]


#: image indices of validation loader k are offset by k x this, so that several loaders never share an index
_LOADER_INDEX_STRIDE = 1 << 32


def _check_backbone_input(
    backbone: str,
    backbone_kwargs: dict[str, Any],
    input_centering: str,
    use_signal_channel: bool,
    depth_scale_mm: float,
) -> None:
    """A backbone's stated input needs (class attributes ``input_centering_modes``, ``needs_signal_channel``;
    a ``depth_scale_mm`` argument is DepthRestorer's own) against the DepthRestorer settings."""
    factory = backbone_factory(backbone)
    modes = tuple(getattr(factory, "input_centering_modes", CENTERING_MODES))
    if input_centering not in modes:
        raise ValueError(
            f"DepthRestorer: backbone {backbone!r} needs input_centering in {list(modes)}, got "
            f"{input_centering!r} (a local offset changes the depth differences it compares)"
        )
    if getattr(factory, "needs_signal_channel", False) and not use_signal_channel:
        raise ValueError(
            f"DepthRestorer: backbone {backbone!r} needs the amplitude channel: set use_signal_channel=true"
        )
    given = backbone_kwargs.get("depth_scale_mm", depth_scale_mm)
    if given != depth_scale_mm:
        raise ValueError(
            f"DepthRestorer: backbone_kwargs.depth_scale_mm={given} contradicts depth_scale_mm="
            f"{depth_scale_mm}; leave it out of backbone_kwargs (DepthRestorer passes its own)"
        )


def _loader_index(index: Any, dataloader_idx: int) -> Tensor | None:
    if index is None:
        return None
    index = torch.as_tensor(index)
    return index + dataloader_idx * _LOADER_INDEX_STRIDE if dataloader_idx else index


def _gather_names(names: dict[int, str]) -> dict[int, str]:
    """{image index: name} of every process (under DDP each saw only its share of the images)."""
    dist = torch.distributed
    if not (dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
        return dict(names)
    parts: list[dict[int, str] | None] = [None] * dist.get_world_size()
    dist.all_gather_object(parts, dict(names))
    out: dict[int, str] = {}
    for part in parts:
        for index, name in (part or {}).items():
            out.setdefault(int(index), name)
    return out
