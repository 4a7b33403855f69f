"""Checkpoints of the old flat hyper-parameter layout (before the settings groups) load with their own settings."""

from __future__ import annotations

import lightning
import pytest
import torch

from tofdenoise.inference.denoise import load_restorer
from tofdenoise.training.init_weights import load_init_weights
from tofdenoise.training.learned_guard import LEARNED_RECORD_KEY
from tofdenoise.training.legacy_hparams import LEGACY_KEYS, is_legacy, upgrade_hparams
from tofdenoise.training.module import DepthRestorer

TINY_UNET = {"width": 8, "stages": 2}


def _flat(model: DepthRestorer) -> dict:
    """``model``'s hyper-parameters as a checkpoint of the old layout stored them (hand-written, not through
    :data:`LEGACY_KEYS`, so that a wrong mapping fails here)."""
    c, o, t = model.conditioning, model.optim, model.tiling
    hp = {k: v for k, v in dict(model.hparams).items() if k not in ("conditioning", "optim", "tiling")}
    hp.update(
        depth_scale_mm=c.depth_scale_mm,
        input_centering=c.centering,
        centering_block_px=c.block_px,
        use_signal_channel=c.use_signal_channel,
        lr=o.lr,
        weight_decay=o.weight_decay,
        betas=tuple(o.betas),
        lr_min=o.lr_min,
        warmup_steps=o.warmup_steps,
        predict_tile_size=t.predict_tile_px,
        eval_tile_size=t.eval_tile_px,
        tile_overlap=t.overlap_px,
    )
    return hp


def _settings_off_default() -> DepthRestorer:
    torch.manual_seed(0)
    model = DepthRestorer(
        backbone="unet",
        backbone_kwargs=TINY_UNET,
        loss="l1",
        # the flat layout predates the fill setting: such files were trained with the pull-push fill
        conditioning={
            "use_signal_channel": True,
            "centering": "none",
            "depth_scale_mm": 250.0,
            "block_px": 8,
            "fill": "pullpush",
        },
        optim={"lr": 1e-3, "warmup_steps": 7, "betas": (0.8, 0.99)},
        tiling={"predict_tile_px": 128, "eval_tile_px": 96, "overlap_px": 8},
    ).eval()
    with torch.no_grad():
        for p in model.backbone.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


def _save_legacy(model: DepthRestorer, path) -> None:
    torch.save(
        {
            "state_dict": model.state_dict(),
            "hyper_parameters": _flat(model),
            LEARNED_RECORD_KEY: {"trained_steps": 0, "best_val_mae_mm": None, "raw_val_mae_mm": None},
            "pytorch-lightning_version": lightning.__version__,
        },
        path,
    )


def test_upgrade_moves_every_flat_setting_into_its_group():
    model = _settings_off_default()
    flat = _flat(model)
    assert is_legacy(flat) and not is_legacy(dict(model.hparams))
    up = upgrade_hparams(flat)
    assert not set(LEGACY_KEYS) & set(up)
    assert up["conditioning"] == model.conditioning.to_dict()
    assert up["optim"] == {**model.optim.to_dict(), "betas": tuple(model.optim.betas)}
    assert up["tiling"] == model.tiling.to_dict()
    assert upgrade_hparams(dict(model.hparams)) == dict(model.hparams)  # today's layout: unchanged


def test_a_legacy_checkpoint_loads_with_its_own_settings_and_restores_the_same(tmp_path):
    model = _settings_off_default()
    ckpt = tmp_path / "old.ckpt"
    _save_legacy(model, ckpt)
    loaded = load_restorer(ckpt)
    assert loaded.conditioning.to_dict() == model.conditioning.to_dict()  # not today's defaults
    assert loaded.tiling.to_dict() == model.tiling.to_dict() and loaded.optim.lr == 1e-3
    depth = 900.0 + 50.0 * torch.rand(1, 1, 24, 32)
    amp = 1000.0 * torch.rand(1, 1, 24, 32)
    with torch.no_grad():
        a = model.restore_mm({"noisy": depth, "amplitude": amp}, tile=None)
        b = loaded.restore_mm({"noisy": depth, "amplitude": amp}, tile=None)
    assert torch.equal(a, b)
    # a setting passed to load_from_checkpoint still wins over the file's
    over = DepthRestorer.load_from_checkpoint(ckpt, tiling={"predict_tile_px": 64})
    assert over.tiling.predict_tile_px == 64 and over.conditioning.depth_scale_mm == 250.0


def test_a_legacy_checkpoint_is_accepted_as_init_weights(tmp_path):
    model = _settings_off_default()
    ckpt = tmp_path / "old.ckpt"
    _save_legacy(model, ckpt)
    fresh = DepthRestorer(
        backbone="unet",
        backbone_kwargs=TINY_UNET,
        conditioning={"use_signal_channel": True, "centering": "none", "depth_scale_mm": 250.0, "block_px": 8},
    )
    load_init_weights(fresh, ckpt)
    for (k, v), w in zip(model.backbone.state_dict().items(), fresh.backbone.state_dict().values()):
        assert torch.equal(v, w), k
    other = DepthRestorer(backbone="unet", backbone_kwargs=TINY_UNET, conditioning={"use_signal_channel": True})
    with pytest.raises(ValueError, match=r"conditioning.centering: file 'none' vs this model 'gaussian'"):
        load_init_weights(other, ckpt)


def test_a_checkpoint_written_before_the_fill_setting_keeps_its_fill_and_block_offset(tmp_path):
    """Issue 42: the defaults became centering 'gaussian' and fill 'harmonic'; a checkpoint of 2026-11-26 stores
    centering 'local' and no fill: it loads with the pull-push fill and the block offset it was trained with."""
    torch.manual_seed(0)
    old = DepthRestorer(
        backbone="unet", backbone_kwargs=TINY_UNET, conditioning={"centering": "local", "fill": "pullpush"}
    ).eval()
    with torch.no_grad():
        for p in old.backbone.parameters():
            p.add_(0.05 * torch.randn_like(p))
    hparams = dict(old.hparams)
    hparams["conditioning"] = {k: v for k, v in hparams["conditioning"].items() if k != "fill"}
    ckpt = tmp_path / "before-fill.ckpt"
    torch.save(
        {
            "state_dict": old.state_dict(),
            "hyper_parameters": hparams,
            LEARNED_RECORD_KEY: {"trained_steps": 0, "best_val_mae_mm": None, "raw_val_mae_mm": None},
            "pytorch-lightning_version": lightning.__version__,
        },
        ckpt,
    )
    assert is_legacy(hparams) and upgrade_hparams(hparams)["conditioning"]["fill"] == "pullpush"
    loaded = load_restorer(ckpt)
    assert loaded.conditioning.fill == "pullpush" and loaded.conditioning.centering == "local"
    depth = 900.0 + 50.0 * torch.rand(1, 1, 40, 48)
    depth[..., 10:22, 12:30] = 0.0
    with torch.no_grad():
        assert torch.equal(old.restore_mm({"noisy": depth}), loaded.restore_mm({"noisy": depth}))
    # one setting given at loading overrides that setting only: the harmonic fill with the checkpoint's offset
    harmonic = DepthRestorer.load_from_checkpoint(ckpt, conditioning={"fill": "harmonic"})
    assert harmonic.conditioning.to_dict() == {**loaded.conditioning.to_dict(), "fill": "harmonic"}
    # a new model's settings are today's defaults, and its own hyper-parameters need no upgrade
    new = DepthRestorer(backbone="unet", backbone_kwargs=TINY_UNET)
    assert (new.conditioning.centering, new.conditioning.fill) == ("gaussian", "harmonic")
    assert not is_legacy(dict(new.hparams))
