"""DepthRestorer: plain hyper-parameters, schedule, EMA, metrics of restored and raw input, test sets,
prediction, checkpoint compatibility."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from lightning.pytorch.callbacks import Callback

from tofdenoise.training.metrics import depth_metrics_per_image
from tofdenoise.training.module import CheckpointMismatchError, DepthRestorer
from tofdenoise.training.optim import parameter_groups

from .conftest import quiet_trainer as trainer

TINY = {"width": 4, "stages": 2}


def tiny_model(**kw) -> DepthRestorer:
    args = {
        "backbone": "unet",
        "backbone_kwargs": dict(TINY),
        "loss": "full",
        "loss_kwargs": {"beta": 0.5, "lambda_g": 0.1},
    }
    args.update(kw)
    return DepthRestorer(**args)


def test_bad_names_list_valid_ones():
    with pytest.raises(ValueError, match=r"unknown backbone 'nope'.*valid names:.*unet"):
        tiny_model(backbone="nope")
    with pytest.raises(ValueError, match=r"unknown loss 'huber'.*valid names:.*full.*l1.*nar"):
        tiny_model(loss="huber")
    with pytest.raises(ValueError, match="in_channels"):
        tiny_model(backbone_kwargs={**TINY, "in_channels": 3})


def test_hparams_are_plain_values():
    model = tiny_model(ema_decay=0.9)
    allowed = (str, int, float, bool, type(None))

    def plain(v):
        if isinstance(v, dict):
            return all(isinstance(k, str) and plain(x) for k, x in v.items())
        if isinstance(v, (list, tuple)):
            return all(plain(x) for x in v)
        return isinstance(v, allowed)

    assert plain(dict(model.hparams)), dict(model.hparams)
    assert model.hparams.backbone == "unet" and model.hparams.optim["lr"] == 2e-4
    # every group complete, with the defaults of its settings class (one source of truth per setting)
    assert model.hparams.optim == {
        "lr": 2e-4,
        "weight_decay": 1e-2,
        "betas": [0.9, 0.999],
        "lr_min": 1e-6,
        "warmup_steps": 0,
    }
    assert model.hparams.conditioning == {
        "depth_scale_mm": 100.0,
        "centering": "gaussian",
        "block_px": 16,
        "use_signal_channel": False,
        "fill": "harmonic",
    }
    assert model.hparams.tiling == {"predict_tile_px": 512, "eval_tile_px": None, "overlap_px": 32}


def test_settings_groups_name_a_bad_key_and_value():
    with pytest.raises(ValueError, match=r"model\.optim\.learning_rate: unknown setting; valid: lr, weight_decay"):
        tiny_model(optim={"learning_rate": 1e-3})
    with pytest.raises(
        ValueError, match=r"model\.conditioning\.input_centering: unknown setting; valid: depth_scale_mm"
    ):
        tiny_model(conditioning={"input_centering": "none"})
    with pytest.raises(ValueError, match=r"model\.tiling: expected a mapping of TilingSettings settings, got int"):
        tiny_model(tiling=512)
    with pytest.raises(ValueError, match=r"optim: need lr > 0 and 0 <= lr_min <= lr, got lr=1e-05, lr_min=0.001"):
        tiny_model(optim={"lr": 1e-5, "lr_min": 1e-3})
    with pytest.raises(
        ValueError, match=r"conditioning.centering: unknown mode 'median'; valid: gaussian, local, image, none"
    ):
        tiny_model(conditioning={"centering": "median"})
    with pytest.raises(ValueError, match=r"tiling.predict_tile_px must exceed tiling.overlap_px \(32\), got 16"):
        tiny_model(tiling={"predict_tile_px": 16})


def test_a_checkpoint_rebuilds_the_same_groups(tmp_path, make_restorer_ckpt):
    path = make_restorer_ckpt(
        tmp_path / "m.ckpt",
        optim={"lr": 5e-4, "betas": (0.8, 0.99)},
        conditioning={"block_px": 8},
        tiling={"eval_tile_px": 64, "overlap_px": 8},
    )
    torch.load(path, weights_only=True)  # plain values only
    again = DepthRestorer.load_from_checkpoint(path)
    assert again.optim.lr == 5e-4 and again.optim.betas == (0.8, 0.99)
    assert again.conditioning.block_px == 8 and again.tiling.eval_tile_px == 64 and again.tiling.overlap_px == 8


def test_signal_channel_input(tiny_data):
    model = tiny_model(conditioning={"use_signal_channel": True})
    batch = next(iter(tiny_data.val_dataloader()))
    x, offset = model.condition(batch)
    assert x.shape[1] == 2
    # channel 0: the depth centred on the local offset (no input holes here: noisy > 0 wherever mask is 1)
    valid = batch["noisy"] > 0
    torch.testing.assert_close((x[:, :1] * model.conditioning.depth_scale_mm + offset)[valid], batch["noisy"][valid])
    amp = batch["amplitude"] * batch["mask"]
    assert torch.allclose(x[:, 1:].amax(dim=(1, 2, 3)), torch.ones(x.shape[0]))
    torch.testing.assert_close(x[0, 1], amp[0, 0] / amp[0].max())
    assert model.restore_mm(batch).shape == batch["noisy"].shape


def test_cosine_schedule_per_step_reaches_lr_min(tmp_path, tiny_data):
    lrs: list[float] = []

    class Rec(Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            lrs.append(trainer.optimizers[0].param_groups[0]["lr"])

    model = tiny_model(optim={"lr": 1e-3, "lr_min": 1e-5})
    t = trainer(tmp_path, max_epochs=3, limit_val_batches=0, callbacks=[Rec()])
    t.fit(model, datamodule=tiny_data)
    total = 3 * 2  # 8 samples / batch 4 = 2 steps per epoch
    assert t.global_step == total and len(lrs) == total
    expected = [1e-5 + (1e-3 - 1e-5) * (1 + math.cos(math.pi * s / total)) / 2 for s in range(total)]
    assert lrs == pytest.approx(expected, rel=1e-6)
    assert t.optimizers[0].param_groups[0]["lr"] == pytest.approx(1e-5, rel=1e-6)
    # weight decay only on >= 2-D weights
    groups = t.optimizers[0].param_groups
    assert {g["weight_decay"] for g in groups} == {1e-2, 0.0}
    assert all(p.ndim >= 2 for p in groups[0]["params"]) and all(p.ndim < 2 for p in groups[1]["params"])


def test_linear_warmup_then_cosine(tmp_path, tiny_data):
    lrs: list[float] = []

    class Rec(Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            lrs.append(trainer.optimizers[0].param_groups[0]["lr"])

    model = tiny_model(optim={"lr": 1e-3, "lr_min": 1e-5, "warmup_steps": 2})
    trainer(tmp_path, max_epochs=4, limit_val_batches=0, callbacks=[Rec()]).fit(model, datamodule=tiny_data)
    total, warm = 8, 2
    expected = [1e-3 * (1 / warm + (1 - 1 / warm) * s / warm) for s in range(warm)]  # 5e-4, 7.5e-4
    expected += [
        1e-5 + (1e-3 - 1e-5) * (1 + math.cos(math.pi * (s - warm) / (total - warm))) / 2 for s in range(warm, total)
    ]
    assert lrs == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("loss, parts", [("full", ("nar", "grad")), ("l1", ("l1",))])
def test_training_logs_the_loss_terms(tmp_path, tiny_data, loss, parts):
    """DepthLoss.terms reach the logs: train/loss_<part> every step and per epoch, and they add up to train/loss."""
    steps: list[dict[str, float]] = []

    class Rec(Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            steps.append({k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("train/loss")})

    kwargs = {} if loss == "full" else {"loss": "l1", "loss_kwargs": {}}
    model = tiny_model(**kwargs)
    t = trainer(tmp_path, max_epochs=2, limit_val_batches=0, callbacks=[Rec()])
    t.fit(model, datamodule=tiny_data)
    assert len(steps) == 4
    for logged in steps:
        assert {f"train/loss_{p}_step" for p in parts} <= set(logged)
        total = logged["train/loss_step"]
        if loss == "full":  # L_full = L_nar + lambda_g L_grad, lambda_g = 0.1
            assert logged["train/loss_grad_step"] > 0
            assert logged["train/loss_nar_step"] + 0.1 * logged["train/loss_grad_step"] == pytest.approx(
                total, rel=1e-5
            )
        else:
            assert logged["train/loss_l1_step"] == pytest.approx(total, rel=1e-6)
    assert {f"train/loss_{p}_epoch" for p in parts} <= set(t.callback_metrics)


def test_ema_update_rule_and_use_in_eval():
    model = tiny_model(ema_decay=0.75)
    p0 = [p.detach().clone() for p in model.backbone.parameters()]
    model.on_train_batch_end(None, None, 0)  # first update copies the weights
    for e, p in zip(model.ema.module.parameters(), p0):
        torch.testing.assert_close(e, p)
    with torch.no_grad():
        for p in model.backbone.parameters():
            p.add_(1.0)
    model.on_train_batch_end(None, None, 1)
    for e, p in zip(model.ema.module.parameters(), p0):
        torch.testing.assert_close(e, p + 0.25)  # 0.75 * p + 0.25 * (p + 1)
    assert model.eval_net is model.ema.module
    assert any(k.startswith("ema.") for k in model.state_dict())
    assert not any(p.requires_grad for p in model.ema.parameters())


def test_validation_logs_restored_and_raw_metrics(tmp_path, tiny_data):
    model = tiny_model()
    t = trainer(tmp_path)
    t.validate(model, datamodule=tiny_data, verbose=False)
    m = t.callback_metrics
    for key in (
        "val/mae_mm",
        "val/psnr_db",
        "val/ssim",
        "val/mse_mm2",
        "val/mae_mm_pooled",
        "val/raw/mae_mm",
        "val/raw/psnr_db",
        "val/loss",
    ):
        assert key in m, key
    # raw = the noisy input against the reference, per-image means over the validation set
    batch = next(iter(tiny_data.val_dataloader()))
    per = depth_metrics_per_image(batch["noisy"], batch["clean"], batch["mask"])
    assert float(m["val/raw/mae_mm"]) == pytest.approx(per["mae_mm"].mean().item(), rel=1e-5)
    assert float(m["val/raw/psnr_db"]) == pytest.approx(per["psnr_db"].mean().item(), rel=1e-5)


def test_raw_val_metrics_are_computed_once_and_recomputed_when_the_batch_changes(tmp_path, tiny_data, monkeypatch):
    import tofdenoise.training.module as lm

    calls = []

    def spy(*args, **kw):
        calls.append(args[0].shape[0])
        return depth_metrics_per_image(*args, **kw)

    monkeypatch.setattr(lm, "depth_metrics_per_image", spy)
    model = tiny_model()
    t = trainer(tmp_path)
    first = float(t.validate(model, datamodule=tiny_data, verbose=False)[0]["val/raw/mae_mm"])
    n_batches = len(calls)
    assert n_batches >= 1
    second = float(t.validate(model, datamodule=tiny_data, verbose=False)[0]["val/raw/mae_mm"])
    assert len(calls) == n_batches and second == first  # the fixed validation noise: served from the cache
    batch = next(iter(tiny_data.val_dataloader()))
    changed = dict(batch, noisy=batch["noisy"] + 1.0)
    per = model._raw_val_per_image(changed, 0, 0)
    assert len(calls) == n_batches + 1  # a different batch at the same position is measured again
    assert torch.equal(
        per["mae_mm"], depth_metrics_per_image(changed["noisy"], batch["clean"], batch["mask"])["mae_mm"]
    )


def test_test_sets_are_namespaced_with_per_image_rows(tmp_path, tiny_data_cls):
    data = tiny_data_cls(n_test=3, test_set_names=("synthetic", "real"))
    model = tiny_model()
    t = trainer(tmp_path)
    t.test(model, datamodule=data, verbose=False)
    m = t.callback_metrics
    for s in ("synthetic", "real"):
        for k in ("psnr_db", "mae_mm", "mse_mm2", "ssim"):
            assert f"test/{s}/{k}" in m and f"test/{s}/raw/{k}" in m
    assert set(model.test_results) == {"synthetic", "real"}
    for s, loader in zip(("synthetic", "real"), data.test_dataloader()):
        res = model.test_results[s]
        batch = next(iter(loader))
        raw = depth_metrics_per_image(batch["noisy"], batch["clean"], batch["mask"])
        assert res["raw"]["mae_mm"] == pytest.approx(raw["mae_mm"].mean().item(), rel=1e-6)
        assert res["images"] == 3 and res["skipped_images"] == 0
        assert float(m[f"test/{s}/mae_mm"]) == pytest.approx(res["mae_mm"], rel=1e-5)
        per = model.test_per_image[s]
        assert [r["index"] for r in per["rows"]] == batch["index"].tolist()
        assert per["names"] == dict(zip(batch["index"].tolist(), batch["name"]))
        assert [r["mae_mm"] for r in per["raw_rows"]] == pytest.approx(raw["mae_mm"].tolist())


def test_predict_zeroes_invalid_and_tiles_large_frames(tmp_path, tiny_data, monkeypatch):
    import tofdenoise.training.module as module

    calls = []
    real = module.tiled_forward

    def spy(net, x, tile, overlap, multiple):
        calls.append((tuple(x.shape), tile, overlap, multiple))
        return real(net, x, tile=tile, overlap=overlap, multiple=multiple)

    monkeypatch.setattr(module, "tiled_forward", spy)
    model = tiny_model(tiling={"predict_tile_px": 16, "overlap_px": 4})
    trainer(tmp_path).predict(model, datamodule=tiny_data)
    assert not calls  # 32 x 32 frames fit the memory budget: whole frames, whatever the tile size
    monkeypatch.setattr(module, "memory_budget_bytes", lambda device: 1.0)  # nothing fits: the checkpoint's tiles
    preds = trainer(tmp_path).predict(model, datamodule=tiny_data)
    assert calls and calls[0][1:] == (16, 4, model.backbone.multiple)  # tiles on the backbone's padding multiple
    pred = preds[0]  # one loader: a list of batch outputs
    batch = next(iter(tiny_data.test_dataloader()[0]))
    assert pred.shape == batch["noisy"].shape
    assert torch.all(pred[batch["mask"] == 0] == 0)
    assert torch.all(torch.isfinite(pred))
    calls.clear()
    model.tiling = dataclasses.replace(model.tiling, predict_tile_px=None)
    trainer(tmp_path).predict(model, datamodule=tiny_data)
    assert not calls


def test_checkpoint_of_another_backbone_fails_clearly(tmp_path, tiny_data):
    model = tiny_model()
    t = trainer(tmp_path, max_steps=1, limit_val_batches=0)
    t.fit(model, datamodule=tiny_data)
    path = tmp_path / "unet.ckpt"
    t.save_checkpoint(path)
    ckpt = torch.load(path, weights_only=True)  # plain hyper-parameters: safe loading works
    assert ckpt["hyper_parameters"]["backbone"] == "unet"
    reloaded = DepthRestorer.load_from_checkpoint(path)
    for (k, a), (k2, b) in zip(model.state_dict().items(), reloaded.state_dict().items()):
        assert k == k2 and torch.equal(a, b)
    other = tiny_model(backbone_kwargs={"width": 8, "stages": 2})
    with pytest.raises(CheckpointMismatchError, match=r"backbone_kwargs: checkpoint .*'width': 4.*'width': 8"):
        trainer(tmp_path).test(other, datamodule=tiny_data, ckpt_path=path, weights_only=True)
    with pytest.raises(CheckpointMismatchError, match="ema"):
        tiny_model(ema_decay=0.9).on_load_checkpoint(ckpt)


def test_compile_switch_keeps_the_state_dict_keys():
    plain, compiled = tiny_model(), tiny_model(compile=True)
    compiled.configure_model()  # torch.compile is lazy: nothing is compiled until the first training forward
    assert compiled._compiled is not None and plain._compiled is None
    assert list(compiled.state_dict()) == list(plain.state_dict())
    assert compiled.eval_net is compiled.backbone  # evaluation runs the eager module


def test_ss2d_state_parameters_are_not_weight_decayed():
    """A_log and D of the selective scan are excluded from weight decay (VMamba/MambaIR practice)."""
    from tofdenoise.training.module import DepthRestorer

    module = DepthRestorer(
        backbone="dvss", backbone_kwargs={"width": 8, "enc_blocks": [1], "bottleneck_blocks": 1, "d_state": 4}
    )
    flagged = {id(p) for p in module.backbone.parameters() if getattr(p, "_no_weight_decay", False)}
    assert flagged, "the DVSS backbone should flag its A_log / D parameters"
    groups = parameter_groups(module.backbone, module.optim.weight_decay)
    for group in groups:
        ids = {id(p) for p in group["params"]}
        if group["weight_decay"] > 0:
            assert not ids & flagged
    no_decay = {id(p) for g in groups if g["weight_decay"] == 0 for p in g["params"]}
    assert flagged <= no_decay


# ------------------------------------------------------------------ a classical filter as the backbone
BILATERAL = {"sigma_spatial_px": 1.5, "sigma_depth_mm": 15.0, "amplitude_power": 1.0}


def bilateral_model(**kw) -> DepthRestorer:
    args = {
        "backbone": "bilateral",
        "backbone_kwargs": dict(BILATERAL),
        "conditioning": {"use_signal_channel": True, "centering": "none"},
    }
    args.update(kw)
    return DepthRestorer(**args)


def test_classical_backbone_input_requirements_are_checked():
    with pytest.raises(ValueError, match=r"backbone 'bilateral' needs conditioning.centering in \['none', 'image'\]"):
        bilateral_model(conditioning={"use_signal_channel": True, "centering": "local"})
    with pytest.raises(ValueError, match="needs the amplitude channel: set conditioning.use_signal_channel=true"):
        bilateral_model(conditioning={"use_signal_channel": False, "centering": "none"})
    with pytest.raises(ValueError, match="depth_scale_mm=50.0 contradicts conditioning.depth_scale_mm=100.0"):
        bilateral_model(backbone_kwargs={**BILATERAL, "depth_scale_mm": 50.0})
    model = bilateral_model(conditioning={"use_signal_channel": True, "centering": "image", "depth_scale_mm": 250.0})
    assert model.backbone.depth_scale_mm == 250.0 and not model.trainable and tiny_model().trainable


@pytest.mark.parametrize("centering", ["none", "image"])
def test_classical_restore_mm_is_the_filter_of_the_input_in_mm(tiny_data, centering):
    """Through condition() (holes filled, amplitude x mask / peak, depth / depth_scale_mm) the backbone computes
    the joint bilateral filter of the noisy depth in mm with the invalid input pixels given no weight."""
    from tofdenoise.models.bilateral import joint_bilateral_filter

    batch = next(iter(tiny_data.val_dataloader()))
    model = bilateral_model(conditioning={"use_signal_channel": True, "centering": centering})
    got = model.restore_mm(batch)
    valid = batch["mask"] > 0
    want = joint_bilateral_filter(batch["noisy"], batch["amplitude"], valid, radius_px=3, **BILATERAL)
    assert (got - want)[valid].abs().max() < 2e-3
    mae = depth_metrics_per_image(got, batch["clean"], batch["mask"])["mae_mm"]
    raw = depth_metrics_per_image(batch["noisy"], batch["clean"], batch["mask"])["mae_mm"]
    assert (mae < 0.8 * raw).all()


def test_classical_backbone_cannot_be_fitted_and_reports_its_tuning(tmp_path, tiny_data):
    model = bilateral_model()
    with pytest.raises(ValueError, match="classical filter without trainable parameters.*tofdenoise classic"):
        trainer(tmp_path, max_epochs=1).fit(model, datamodule=tiny_data)
    rec = model.learned_record()
    assert rec["method_kind"] == "classical" and rec["trained_steps"] == 0 and rec["best_val_mae_mm"] is None
    model.record_tuning(3.25, 7.5)
    rec = model.learned_record()
    assert (rec["best_val_mae_mm"], rec["raw_val_mae_mm"], rec["learned"]) == (3.25, 7.5, False)
    with pytest.raises(RuntimeError, match="is a network"):
        tiny_model().record_tuning(1.0, 2.0)
    assert tiny_model().learned_record()["method_kind"] == "network"


class _ThreeSteps(torch.nn.Module):
    """Toy deep-supervised backbone: step k shifts the depth channel by shift_k (network units); training mode
    returns the three step predictions, eval mode the last."""

    deep_supervision = True

    def __init__(self, weights=None) -> None:
        super().__init__()
        self.shift = torch.nn.Parameter(torch.tensor([0.01, 0.03, -0.02]))
        if weights is not None:
            self.step_loss_weights = weights

    def forward(self, x):
        steps = [x[:, :1] + s for s in self.shift]
        return steps if self.training else steps[-1]


@pytest.mark.parametrize("weights", [None, (1.0, 2.0, 5.0)])
def test_deep_supervision_loss_is_the_weighted_mean_of_the_step_losses(tiny_data, weights):
    """Per-step losses by hand: L1 over valid pixels of (noisy + 100 mm x shift_k - clean); the training loss is
    their mean (no weights) or sum_k w_k L_k / sum_k w_k."""
    model = tiny_model(loss="l1", loss_kwargs={})
    batch = next(iter(tiny_data.train_dataloader()))
    net = _ThreeSteps(weights).train()
    valid = batch["mask"] > 0
    per_step = [((batch["noisy"] + 100.0 * s - batch["clean"])[valid]).abs().mean().item() for s in (0.01, 0.03, -0.02)]
    w = (1.0, 1.0, 1.0) if weights is None else weights
    expected = sum(wk * lk for wk, lk in zip(w, per_step)) / sum(w)
    loss = model.training_loss(batch, net=net)
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    assert loss.item() != pytest.approx(per_step[-1], rel=1e-3)  # not only the final step
    loss.backward()
    assert torch.all(net.shift.grad != 0)  # every step receives a gradient
    # the final prediction only, whatever the mode: restore_mm and forward
    final = (batch["noisy"] + 100.0 * -0.02)[valid]
    for mode in (True, False):
        net.train(mode)
        with torch.no_grad():
            torch.testing.assert_close(model.restore_mm(batch, net=net)[valid], final, rtol=0, atol=1e-3)


def test_deep_supervision_rejects_step_weights_that_do_not_match(tiny_data):
    from tofdenoise.training.module import final_prediction, step_predictions

    model = tiny_model(loss="l1", loss_kwargs={})
    batch = next(iter(tiny_data.train_dataloader()))
    with pytest.raises(ValueError, match=r"_ThreeSteps.step_loss_weights: expected 3 non-negative weights"):
        model.training_loss(batch, net=_ThreeSteps((1.0, 1.0)).train())
    with pytest.raises(ValueError, match="not all 0"):
        model.training_loss(batch, net=_ThreeSteps((0.0, 0.0, 0.0)).train())
    with pytest.raises(TypeError, match="one per refinement step"):
        step_predictions([])
    x = torch.zeros(1, 1, 2, 2)
    assert final_prediction(x) is x and final_prediction((x + 1, x)) is x


#: the paper backbones at tiny sizes; ``model.compile=true`` trains each through torch.compile. A first compile
#: (empty inductor cache) on 2 CPU cores: unet about 40 s, dvss about 110 s, restormer about 260 s -- the last two
#: are ``slow`` (tests/models/scan/test_ops.py compiles a DVSS forward and backward in the default run)
COMPILE_TINY = {
    "unet": {"width": 4, "stages": 2},
    "restormer": {"width": 8, "blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "refinement_blocks": 1},
    "dvss": {"width": 8, "enc_blocks": [1], "bottleneck_blocks": 1},
    "rcf": {"width": 8, "hidden": 8, "steps": 2, "global_levels": 2},
    "tofkpn": {},
    "deeptof": {},
}


def _autograd_node_names(t: torch.Tensor) -> set[str]:
    names, stack, seen = set(), [t.grad_fn], set()
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        names.add(type(node).__name__)
        stack.extend(n for n, _ in node.next_functions)
    return names


SLOW = pytest.mark.slow


@pytest.mark.parametrize(
    "backbone", ["unet", *[pytest.param(b, marks=SLOW) for b in ("restormer", "dvss", "rcf", "tofkpn", "deeptof")]]
)
def test_model_compile_trains_the_compiled_forward_and_backward(tmp_path, tiny_data, backbone):
    """``model.compile=true`` (configs/model/default.yaml) on a paper backbone: a fast_dev_run step whose loss comes
    from the compiled network in one graph (no graph break; its backward is the compiled one: the loss's autograd
    graph holds a CompiledFunctionBackward), and a checkpoint whose keys have no ``_orig_mod.`` and that loads into an
    uncompiled module with the same weights."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf
    from torch._dynamo.utils import counters

    from tofdenoise.config import compose_config

    cfg = compose_config([f"backbone={backbone}", f"paths.run_dir={tmp_path}", "model.compile=true"])
    cfg.model.backbone_kwargs = OmegaConf.merge(cfg.model.backbone_kwargs, COMPILE_TINY[backbone])
    model = instantiate(cfg.model, _convert_="all")
    assert model.hparams.compile is True
    nodes: list[set[str]] = []

    class Record(Callback):
        def on_before_backward(self, trainer, pl_module, loss):
            nodes.append(_autograd_node_names(loss))

    torch._dynamo.reset()
    counters.clear()
    t = trainer(tmp_path, fast_dev_run=1, callbacks=[Record()])
    t.fit(model, datamodule=tiny_data)
    assert len(nodes) == 1 and "CompiledFunctionBackward" in nodes[0]
    assert counters["stats"]["unique_graphs"] == 1 and not counters["graph_break"]
    path = tmp_path / "compiled.ckpt"
    t.save_checkpoint(path)
    state = torch.load(path, map_location="cpu", weights_only=False)["state_dict"]
    assert not [k for k in state if "_orig_mod" in k]
    plain = DepthRestorer.load_from_checkpoint(path, compile=False, weights_only=False)
    assert plain._compiled is None and not plain.hparams.compile
    for (name, p), q in zip(model.backbone.state_dict().items(), plain.backbone.state_dict().values()):
        assert torch.equal(p, q), name
