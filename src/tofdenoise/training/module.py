"""``DepthRestorer``: one LightningModule for every registered restoration backbone.

The paper's recipe (Sec. V-A: AdamW 2e-4, per-step cosine to 1e-6, checkpoint at the lowest validation MAE) and
every design decision of training (input conditioning, weight decay, EMA, compile, deep supervision, exact DDP
metrics, the learned guard, classical filters) are described in docs/training.md. Where the pieces live:
what the network sees, ``models/conditioning.py``; tiles, ``models/tiling.py``; the optimiser and schedule,
``optim.py``; losses, ``losses.py``; per-image metrics, ``metrics.py``; the learned guard's inputs,
``learned_guard.py``; the records a run writes, ``tofdenoise.records`` and ``callbacks/run_outputs.py``. Every
hyper-parameter is a plain value (backbone and loss by registered name, the groups as mappings), so a checkpoint
loads with ``torch.load(weights_only=True)`` and ``DepthRestorer.load_from_checkpoint(path)``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from contextlib import nullcontext
from typing import Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn

from tofdenoise.config import settings_group
from tofdenoise.models import build_backbone, tiled_forward
from tofdenoise.models.conditioning import CENTERING_MODES, InputConditioning
from tofdenoise.models.registry import accepts_kwarg, backbone_factory, is_trainable
from tofdenoise.models.tiling import TilingSettings, min_tile_px, model_multiple
from tofdenoise.records import set_entry
from tofdenoise.training.depth_range import TrainingDepthRange
from tofdenoise.training.init_weights import INIT_RECORD_KEY, load_init_weights
from tofdenoise.training.learned_guard import LearnedGuard
from tofdenoise.training.legacy_hparams import is_legacy, upgrade_hparams
from tofdenoise.training.losses import DepthLoss, build_loss
from tofdenoise.training.metrics import DepthMetrics, FixedBatchCache, depth_metrics_per_image
from tofdenoise.training.optim import OptimSettings
from tofdenoise.training.tile_memory import TilePlan, activation_bytes_per_px, memory_budget_bytes, tile_plan

__all__ = [
    "DepthRestorer",
    "CheckpointMismatchError",
    "checkpoint_backbone",
    "step_predictions",
    "final_prediction",
    "step_loss_weights",
]

log = logging.getLogger(__name__)


class CheckpointMismatchError(ValueError):
    """A checkpoint was written by a DepthRestorer with another backbone / architecture."""


def _architecture(hparams: dict[str, Any]) -> dict[str, Any]:
    """What defines the network and what it was trained to see, from a hyper-parameter dict: a checkpoint must
    agree on all of it."""
    conditioning = dict(hparams.get("conditioning") or {})
    return {
        "backbone": hparams.get("backbone"),
        "backbone_kwargs": dict(hparams.get("backbone_kwargs") or {}),
        "use_signal_channel": conditioning.get("use_signal_channel"),
        "ema": hparams.get("ema_decay") is not None,
        "input_centering": conditioning.get("centering"),
    }


class DepthRestorer(pl.LightningModule):
    """Depth restoration with any backbone of ``tofdenoise.models.build_backbone``: the one LightningModule.

    It conditions the input (hole fill, centring, optional signal channel), computes the loss in millimetres,
    and scores validation and test with the project's metrics. Every argument is a plain value, so a checkpoint
    loads with ``weights_only=True``; ``configs/model/`` and ``configs/backbone/`` set them.

    Args:
        backbone: a registered backbone name (``tofdenoise.models.available_backbones()``).
        backbone_kwargs: its constructor arguments (``in_channels`` comes from ``conditioning``).
        loss: a registered loss name (``l1``, ``nar``, ``full``).
        loss_kwargs: its arguments.
        conditioning: what the network sees, the ``model.conditioning`` group (``InputConditioning``:
            ``depth_scale_mm``, ``centering``, ``block_px``, ``use_signal_channel``); None: the defaults.
        optim: AdamW and its schedule, the ``model.optim`` group (``OptimSettings``); None: the defaults.
        tiling: tile-by-tile inference, the ``model.tiling`` group (``TilingSettings``); None: the defaults.
        ema_decay: decay of the EMA of the weights (e.g. 0.999); ``None`` = no EMA.
        compile: ``torch.compile`` the backbone for the training steps (``configs/model/default.yaml``:
            ``model.compile``): set up in ``configure_model``, compiled at the first training forward (forward
            and backward graphs); kept out of the module tree, so the state dict keys are those of an eager run.
            Validation, test and prediction run the eager network (``eval_net``).
        d_max_mm: fixed PSNR/SSIM peak (paper: 1000 mm).
        learned_margin: a run counts as learned only when its best validation MAE is at most
            ``(1 - learned_margin)`` x the raw validation MAE (``training/learned_guard.py``).
        init_weights: weights file the network starts from when a fit begins without ``ckpt_path`` (fine-tuning;
            ``training/init_weights.py``).
    """

    def __init__(
        self,
        backbone: str = "dvss",
        backbone_kwargs: dict[str, Any] | None = None,
        loss: str = "full",
        loss_kwargs: dict[str, Any] | None = None,
        conditioning: dict[str, Any] | None = None,
        optim: dict[str, Any] | None = None,
        tiling: dict[str, Any] | None = None,
        ema_decay: float | None = None,
        compile: bool = False,
        d_max_mm: float = 1000.0,
        learned_margin: float = 0.05,
        init_weights: str | None = None,
    ) -> None:
        super().__init__()
        backbone_kwargs = dict(backbone_kwargs or {})
        loss_kwargs = dict(loss_kwargs or {})
        self.conditioning = settings_group(InputConditioning, conditioning, "model.conditioning")
        self.optim = settings_group(OptimSettings, optim, "model.optim")
        self.tiling = settings_group(TilingSettings, tiling, "model.tiling")
        if ema_decay is not None and not 0.0 < ema_decay < 1.0:
            raise ValueError(f"DepthRestorer.ema_decay must be in (0, 1) or null, got {ema_decay}")
        if not 0.0 <= learned_margin < 1.0:
            raise ValueError(f"DepthRestorer.learned_margin must be in [0, 1), got {learned_margin}")
        in_channels = self.conditioning.in_channels
        if backbone_kwargs.get("in_channels", in_channels) != in_channels:
            raise ValueError(
                f"DepthRestorer: backbone_kwargs.in_channels={backbone_kwargs['in_channels']} contradicts "
                f"conditioning.use_signal_channel={self.conditioning.use_signal_channel} (needs {in_channels}); "
                "leave in_channels out"
            )
        _check_backbone_input(backbone, backbone_kwargs, self.conditioning)
        # plain values only (a checkpoint loads with weights_only=True); each group complete, with its defaults
        self.save_hyperparameters()
        self.hparams.update(
            conditioning=self.conditioning.to_dict(), optim=self.optim.to_dict(), tiling=self.tiling.to_dict()
        )

        net_kwargs = {k: v for k, v in backbone_kwargs.items() if k != "in_channels"}
        if accepts_kwarg(backbone, "depth_scale_mm"):  # a filter comparing depth differences in mm
            net_kwargs["depth_scale_mm"] = self.conditioning.depth_scale_mm
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

        self.val_metrics = DepthMetrics(d_max_mm=float(d_max_mm))
        self.val_raw_metrics = DepthMetrics(d_max_mm=float(d_max_mm))
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
        #: the valid target depths of the training batches (``training/depth_range.py``), kept in the checkpoint
        self.training_depths = TrainingDepthRange()

    @property
    def training_depth_range_mm(self) -> tuple[float, float] | None:
        """(nearest, farthest) depth [mm] of the training targets this network saw (0.5 % and 99.5 % of them;
        ``training/depth_range.py``); None for a checkpoint written before the record existed, or no training."""
        return self.training_depths.range_mm

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
        """The network input and the offset the output is measured from (``InputConditioning``).

        Computed in float32 whatever the autocast setting.

        Args:
            batch: ``"noisy"`` depth [mm] (B, 1, H, W) with 0 at invalid pixels, and ``"amplitude"`` (B, 1, H, W)
                when the model uses the signal channel.

        Returns:
            The network input (B, C, H, W), and the offset [mm] to add back to ``depth_scale_mm`` x its output.

        Raises:
            KeyError: the model uses the signal channel and the batch has no ``"amplitude"``.
        """
        noisy = batch["noisy"]
        if self.conditioning.use_signal_channel and "amplitude" not in batch:
            raise KeyError("DepthRestorer(conditioning.use_signal_channel=True) needs batch['amplitude']")
        with torch.autocast(device_type=noisy.device.type, enabled=False):
            return self.conditioning(noisy, batch.get("amplitude"))

    def network_input(self, batch: dict[str, Any]) -> Tensor:
        """The conditioned network input of ``condition`` (without the offset)."""
        return self.condition(batch)[0]

    def restore_mm(self, batch: dict[str, Any], tile: int | None = None, net: nn.Module | None = None) -> Tensor:
        """Restored depth [mm] at every pixel: the restore path of ``predict``, ``tofdenoise denoise`` and
        ``tofdenoise.denoise``.

        Args:
            batch: as ``condition`` takes it (``"noisy"`` [mm] with 0 at invalid pixels, ``"amplitude"`` when
                the model uses the signal channel).
            tile: run tile by tile (``tiled_forward``, overlap ``tiling.overlap_px``, tiles on the network's
                padding multiple) when a side exceeds this; None: the whole frame.
            net: the network to run (default: ``eval_net``).

        Returns:
            Depth [mm], (B, 1, H, W); input holes get the network's estimate too (callers mask them).
        """
        net = self.eval_net if net is None else net
        x, offset = self.condition(batch)
        if tile is not None and max(x.shape[-2:]) > tile:
            y = tiled_forward(
                lambda t: final_prediction(net(t)),
                x,
                tile=tile,
                overlap=self.tiling.overlap_px,
                multiple=model_multiple(net),
            )
        else:
            y = final_prediction(net(x))
        return y.float() * self.conditioning.depth_scale_mm + offset

    # ------------------------------------------------------------------ optimisation
    def configure_optimizers(self) -> dict[str, Any]:
        if not self.trainable:
            raise ValueError(
                f"DepthRestorer: backbone {self.hparams.backbone!r} is a classical filter without "
                "trainable parameters: there is nothing to fit; tune and test it with "
                "`tofdenoise classic` (docs/models.md#classical-row-joint-bilateral-filter)"
            )
        return self.optim.build(self.backbone, self.trainer.estimated_stepping_batches)

    def training_terms(self, batch: dict[str, Any], net: nn.Module | None = None) -> dict[str, Tensor]:
        """The loss of one training batch through ``net`` (default: the training network) with its parts:
        ``DepthLoss.terms`` (``"loss"``: the total, with gradient; the parts, e.g. ``"nar"``, ``"grad"``, detached).

        Deep supervision: when the network returns a list of step predictions (``step_predictions``), every
        term is ``sum_k w_k term(pred_k)`` with the backbone's ``step_loss_weights`` (normalised to sum 1;
        uniform when it has none).

        Args:
            batch: a training batch: ``"noisy"``, ``"clean"`` and ``"sigma"`` [mm] and ``"mask"``, (B, 1, H, W)
                each, and ``"amplitude"`` when the model uses the signal channel.
            net: the network (default: the compiled training network when ``compile``, else the backbone).
        """
        if net is None:
            net = self._compiled if self._compiled is not None else self.backbone
        x, offset = self.condition(batch)
        preds = step_predictions(net(x))
        weights = step_loss_weights(net, len(preds))
        # the loss in millimetres relative to the offset (differences are those of the restored depth in mm)
        target_mm = batch["clean"].float() - offset
        terms = [
            self.criterion.terms(p.float() * self.conditioning.depth_scale_mm, target_mm, batch["sigma"], batch["mask"])
            for p in preds
        ]
        if len(terms) == 1:
            return terms[0]
        return {key: sum(w * t[key] for w, t in zip(weights, terms)) for key in terms[0]}

    def training_loss(self, batch: dict[str, Any], net: nn.Module | None = None) -> Tensor:
        """The loss of one training batch (``training_terms``' total, with gradient).

        Args:
            batch: a training batch, as ``training_terms`` takes it.
            net: the network (default: the training network).
        """
        return self.training_terms(batch, net)["loss"]

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor:
        self.training_depths.update(batch["clean"], batch["mask"])
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
        pred_mm = self.restore_mm(batch, tile=self.tiling.eval_tile_px)
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
        pred_mm = self.restore_mm(batch, tile=self.tiling.eval_tile_px)
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
    def predict_tile_plan(
        self, shape: Sequence[int], tile: int | None = None, precision: str | None = None, autocast: Any = None
    ) -> TilePlan:
        """Whole frames or tiles for a (B, C, H, W) or (H, W) input to predict (``training/tile_memory.py``): ``tile``
        forces tiles of that side; else whole when the network's activations, measured once on a small probe under
        ``autocast`` (default: the autocast state of the caller; ``precision`` names it, e.g. "bf16"), fit the memory
        budget of this model's device, and tiles of ``tiling.predict_tile_px`` when they do not."""
        device = self.device
        if precision is None:
            on = torch.is_autocast_enabled(device.type)
            precision = str(torch.get_autocast_dtype(device.type)) if on else "fp32"

        def per_px() -> float:
            context = nullcontext() if autocast is None else autocast
            return activation_bytes_per_px(self.eval_net, self.conditioning.in_channels, device, precision, context)

        frames = int(shape[0]) if len(shape) == 4 else 1
        budget = lambda: memory_budget_bytes(device)  # noqa: E731
        floor = min_tile_px(self.tiling.overlap_px, model_multiple(self.eval_net))
        return tile_plan(
            tuple(shape[-2:]), tile, self.tiling.predict_tile_px, per_px, budget, frames=frames, min_tile=floor
        )

    def predict_step(self, batch: dict[str, Any], batch_idx: int, dataloader_idx: int = 0) -> Tensor:
        """Restored depth in mm (B, 1, H, W); pixels invalid in the input (``mask == 0``) are set to 0. The batch runs
        whole unless it does not fit the memory budget (:meth:`predict_tile_plan`)."""
        pred_mm = self.restore_mm(batch, tile=self.predict_tile_plan(tuple(batch["noisy"].shape)).tile)
        if "mask" in batch:
            pred_mm = torch.where(batch["mask"] > 0, pred_mm, torch.zeros_like(pred_mm))
        return pred_mm

    # ------------------------------------------------------------------ learned guard
    def learned_record(self) -> dict[str, Any]:
        """The learned guard's verdict (``training.results.learned_verdict``, or ``classical_verdict`` for a
        classical filter): ``trained_steps``, ``best_val_mae_mm``, ``raw_val_mae_mm``, ``learned_margin``,
        ``learned``, ``learned_reason`` (inputs: ``training/learned_guard.py``)."""
        margin = float(self.hparams.learned_margin)
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
        if self.hparams.init_weights and not resuming:
            # after the modules are set up, before the sanity check: the optimiser holds these same tensors
            self.init_record = load_init_weights(self, str(self.hparams.init_weights))
            log.info("network initialised from %s (sha256 %s)", self.init_record["path"], self.init_record["sha256"])

    def on_fit_end(self) -> None:
        self.guard.end_fit(self.trainer)

    # ------------------------------------------------------------------ checkpoints
    @classmethod
    def load_from_checkpoint(cls, checkpoint_path: Any, *args: Any, **kwargs: Any) -> DepthRestorer:  # type: ignore[override]
        """Lightning's ``load_from_checkpoint``; a checkpoint of the old flat layout is rebuilt with its own
        settings, moved into today's groups (``training/legacy_hparams.py``).

        ``tofdenoise.inference.load_restorer`` adds checks and clear errors for files that are no checkpoint.

        Args:
            checkpoint_path: the ``.ckpt`` file.
            *args: passed to Lightning's ``load_from_checkpoint``.
            **kwargs: passed to it too (``map_location``, ``strict`` ...); hyper-parameters given here override
                the saved ones.
        """
        saved = _saved_hparams(checkpoint_path)
        # a checkpoint written before a setting's default changed keeps the value it was trained with
        # (legacy_hparams.FORMER_DEFAULTS), and a settings group given in kwargs overrides field by field:
        # conditioning={"fill": "harmonic"} keeps the checkpoint's other conditioning settings
        if saved is not None:
            upgraded = upgrade_hparams(saved) if is_legacy(saved) else saved
            for group in ("conditioning", "optim", "tiling"):
                mine = kwargs.get(group)
                if isinstance(upgraded.get(group), dict) and (is_legacy(saved) or isinstance(mine, dict)):
                    kwargs[group] = {**upgraded[group], **dict(mine or {})}
        return super().load_from_checkpoint(checkpoint_path, *args, **kwargs)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Keep the learned guard's inputs in the checkpoint (plain values: loads with weights_only=True)."""
        if self._trainer is not None:
            self.guard.save(checkpoint, self.trainer)
        if self.init_record is not None:
            checkpoint[INIT_RECORD_KEY] = dict(self.init_record)
        self.training_depths.save(checkpoint)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Refuse a checkpoint written for another backbone/architecture with a readable message; restore the
        learned guard's record (validation MAEs continue across a resume)."""
        self._check_architecture(checkpoint)
        init = checkpoint.get(INIT_RECORD_KEY)
        self.init_record = dict(init) if isinstance(init, dict) else None
        self.guard.load(checkpoint)
        self.training_depths.load(checkpoint)

    def _check_architecture(self, checkpoint: dict[str, Any]) -> None:
        saved = checkpoint.get("hyper_parameters")
        if not saved:
            return
        mine, theirs = _architecture(dict(self.hparams)), _architecture(upgrade_hparams(saved))
        diff = {k: (theirs[k], mine[k]) for k in mine if mine[k] != theirs[k]}
        if diff:
            lines = "; ".join(f"{k}: checkpoint {a!r} vs this model {b!r}" for k, (a, b) in diff.items())
            raise CheckpointMismatchError(
                f"checkpoint was written by a DepthRestorer with another architecture ({lines}). "
                f"Load it with DepthRestorer.load_from_checkpoint(path) (it rebuilds the saved backbone), "
                f"or select backbone={theirs['backbone']!r} with the same backbone_kwargs"
            )


def _saved_hparams(checkpoint_path: Any) -> dict[str, Any] | None:
    """The hyper-parameters stored in a checkpoint file (memory-mapped read), or None for anything else (a stream,
    a URL, a file without them: Lightning then reports what it finds)."""
    if not isinstance(checkpoint_path, (str, os.PathLike)) or not os.path.isfile(checkpoint_path):
        return None
    try:
        content = torch.load(checkpoint_path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # noqa: BLE001 - Lightning's own load gives the error for a file it cannot read
        return None
    saved = content.get("hyper_parameters") if isinstance(content, dict) else None
    return dict(saved) if isinstance(saved, dict) else None


def checkpoint_backbone(checkpoint_path: Any) -> str | None:
    """The backbone name a checkpoint file was written for (its hyper-parameters), or None when the file has none
    (or cannot be read: the loader reports that)."""
    saved = _saved_hparams(checkpoint_path)
    backbone = upgrade_hparams(saved).get("backbone") if saved else None
    return None if backbone is None else str(backbone)


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


def _check_backbone_input(backbone: str, backbone_kwargs: dict[str, Any], conditioning: InputConditioning) -> None:
    """A backbone's stated input needs (class attributes ``input_centering_modes``, ``needs_signal_channel``;
    a ``depth_scale_mm`` argument is DepthRestorer's own) against the conditioning settings."""
    factory = backbone_factory(backbone)
    modes = tuple(getattr(factory, "input_centering_modes", CENTERING_MODES))
    if conditioning.centering not in modes:
        raise ValueError(
            f"DepthRestorer: backbone {backbone!r} needs conditioning.centering in {list(modes)}, got "
            f"{conditioning.centering!r} (a local offset changes the depth differences it compares)"
        )
    if getattr(factory, "needs_signal_channel", False) and not conditioning.use_signal_channel:
        raise ValueError(
            f"DepthRestorer: backbone {backbone!r} needs the amplitude channel: set "
            "conditioning.use_signal_channel=true"
        )
    given = backbone_kwargs.get("depth_scale_mm", conditioning.depth_scale_mm)
    if given != conditioning.depth_scale_mm:
        raise ValueError(
            f"DepthRestorer: backbone_kwargs.depth_scale_mm={given} contradicts conditioning.depth_scale_mm="
            f"{conditioning.depth_scale_mm}; leave it out of backbone_kwargs (DepthRestorer passes its own)"
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
