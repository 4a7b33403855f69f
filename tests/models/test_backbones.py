"""Backbones: registry, shapes on odd sizes, gradient flow, identity at initialisation."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import nn

from tofdenoise.models import available_backbones, build_backbone, count_parameters, trainable_backbones
from tofdenoise.models.common import crop_to, pad_to_multiple
from tofdenoise.models.scr import SCR, SqueezeExcitation
from tofdenoise.models.ss2d import cross_merge, cross_scan
from tofdenoise.models.tofkpn import apply_kernels

NAMES = ["dvss", "dvss_no_local", "dvss_no_dwconv", "dvss_se", "unet", "restormer", "deeptof", "tofkpn"]
CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs" / "backbone"

TINY = {
    "dvss": dict(width=8, enc_blocks=[1, 1], bottleneck_blocks=1, d_state=4),
    "unet": dict(width=4, stages=3),
    "restormer": dict(width=8, blocks=[1, 1, 1, 1], heads=[1, 2, 2, 4], refinement_blocks=1),
    "deeptof": dict(channels=[4, 4, 8, 8, 8, 8]),
    "tofkpn": dict(channels=[4, 4, 8, 8, 8, 8]),
}
RESIDUAL = {"dvss", "dvss_no_local", "dvss_no_dwconv", "dvss_se", "unet", "restormer"}


def tiny(name: str, **kw):
    base = TINY["dvss"] if name.startswith("dvss") else TINY[name]
    return build_backbone(name, **{**base, **kw})


def _randomise_heads(model: torch.nn.Module) -> None:
    """Zero-initialised heads block gradients to the trunk: give them random weights for flow tests."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for mod in model.modules():
            if isinstance(mod, torch.nn.Conv2d) and mod.weight.abs().sum() == 0:
                mod.weight.copy_(0.1 * torch.randn(mod.weight.shape, generator=g))


def test_registry_lists_all_names():
    assert trainable_backbones() == sorted(NAMES + ["rcf"])
    # the classical row (tests/models/test_bilateral.py): registered, not trainable; rcf needs two input channels
    # and returns its steps in training: tested in test_rcf.py
    assert available_backbones() == sorted(NAMES + ["bilateral", "rcf"])


def test_unknown_name_and_bad_kwargs_raise():
    with pytest.raises(ValueError, match="valid names: .*dvss.*unet"):
        build_backbone("resnet")
    with pytest.raises(ValueError, match="unexpected keyword.*'widht'.*accepted: in_channels"):
        build_backbone("unet", widht=8)
    with pytest.raises(ValueError, match="local"):
        build_backbone("dvss", local="scr")  # fixed by the variant name
    with pytest.raises(ValueError, match="plain value"):
        build_backbone("unet", width=torch.nn.Identity())


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("in_channels", [1, 2])
def test_shape_and_gradient_flow_on_odd_size(name, in_channels):
    model = tiny(name, in_channels=in_channels)
    _randomise_heads(model)
    x = torch.randn(1, in_channels, 37, 53, requires_grad=True)
    y = model(x)
    assert y.shape == (1, 1, 37, 53)
    y.square().mean().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    missing = [n for n, p in model.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not missing, f"{name}: parameters without finite gradient: {missing[:5]}"
    zero = [n for n, p in model.named_parameters() if p.grad.abs().sum() == 0]
    assert len(zero) <= 0.05 * len(list(model.parameters())), f"{name}: zero gradients for {zero[:5]}"


@pytest.mark.parametrize("name", sorted(RESIDUAL))
def test_residual_networks_are_identity_at_init(name):
    model = tiny(name, in_channels=2)
    x = torch.randn(2, 2, 21, 30)
    with torch.no_grad():
        y = model(x)
    torch.testing.assert_close(y, x[:, :1], rtol=0, atol=0)


def test_tofkpn_starts_as_identity_and_deeptof_predicts_directly():
    x = torch.randn(1, 1, 20, 24)
    with torch.no_grad():
        torch.testing.assert_close(tiny("tofkpn")(x), x / (1 + 1e-6), rtol=1e-6, atol=1e-6)
        assert (tiny("deeptof")(x) - x).abs().mean() > 0.1


def test_apply_kernels_hand_computed():
    depth = torch.arange(16, dtype=torch.float32).view(1, 1, 4, 4)
    # Uniform positive weights -> 3x3 mean of the replicate-padded depth (+ bias).
    w = torch.full((1, 9, 4, 4), 2.0)
    out = apply_kernels(depth, w, torch.full((1, 1, 4, 4), 0.5))
    assert out[0, 0, 1, 1].item() == pytest.approx(
        (0 + 1 + 2 + 4 + 5 + 6 + 8 + 9 + 10) / 9 * 18 / (18 + 1e-6) + 0.5, rel=1e-6
    )
    # Corner (0, 0) with replicate padding: window rows [0,0,1], cols [0,0,1].
    corner = (0 + 0 + 1 + 0 + 0 + 1 + 4 + 4 + 5) / 9
    assert out[0, 0, 0, 0].item() == pytest.approx(corner + 0.5, rel=1e-5)
    # Signed weights are L1-normalised: one +1 on the right neighbour and -1 on the centre.
    w = torch.zeros(1, 9, 4, 4)
    w[:, 5] = 1.0
    w[:, 4] = -1.0
    out = apply_kernels(depth, w, torch.zeros(1, 1, 4, 4))
    assert out[0, 0, 2, 1].item() == pytest.approx((10 - 9) / 2, rel=1e-5)


def test_large_frame_480x640_and_padding_helpers():
    model = tiny("unet", width=2, stages=4)
    with torch.no_grad():
        y = model(torch.randn(1, 1, 480, 640))
    assert y.shape == (1, 1, 480, 640)
    x = torch.randn(1, 1, 5, 3)
    xp, size = pad_to_multiple(x, 8)  # too small to reflect -> replicate
    assert xp.shape == (1, 1, 8, 8) and torch.equal(crop_to(xp, size), x)
    assert torch.equal(xp[..., 7, :3], x[..., 4, :])
    xp, _ = pad_to_multiple(torch.arange(6.0).view(1, 1, 1, 6).expand(1, 1, 6, 6), 4)
    assert xp[0, 0, 0, 6:].tolist() == [4.0, 3.0]  # reflect


def test_cross_scan_merge_and_refinement_modules():
    x = torch.randn(2, 3, 5, 7)
    xs = cross_scan(x)
    assert xs.shape == (2, 4, 3, 35)
    torch.testing.assert_close(xs[:, 1, :, 1], x[:, :, 1, 0])  # column-major second element
    torch.testing.assert_close(cross_merge(xs, 5, 7), 4 * x)
    feats = torch.randn(2, 8, 6, 9)
    assert SCR(8)(feats).shape == feats.shape
    se = SqueezeExcitation(8)
    out = se(feats)
    ratio = out / feats
    # SE is channel-only: one scale per (image, channel), in (0, 1).
    assert torch.allclose(ratio, ratio[..., :1, :1].expand_as(ratio), atol=1e-5)
    assert SCR(8)(torch.zeros(1, 8, 4, 4)).abs().max() == 0


def backbone_config(name: str) -> dict:
    """configs/backbone/<name>.yaml as Hydra composes it (the dvss ablations inherit dvss.yaml)."""
    from omegaconf import OmegaConf

    from tofdenoise.config import compose_config

    return OmegaConf.to_container(compose_config([f"backbone={name}"]).backbone, resolve=True)


@pytest.mark.parametrize("name", NAMES)
def test_config_files_build(name):
    assert (CONFIG_DIR / f"{name}.yaml").is_file()
    cfg = backbone_config(name)
    assert cfg["name"] == name
    model = build_backbone(cfg["name"], **cfg["kwargs"])
    assert count_parameters(model) > 100_000


def test_dvss_activation_checkpointing_gives_same_gradients():
    grads = []
    for checkpoint in (False, True):
        torch.manual_seed(0)
        model = tiny("dvss", checkpoint=checkpoint)
        _randomise_heads(model)
        model(torch.randn(1, 1, 19, 23, generator=torch.Generator().manual_seed(2))).square().mean().backward()
        grads.append(torch.cat([p.grad.flatten() for p in model.parameters()]))
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-7)


def test_dvss_native_cpu_scan_route_matches_pytorch_route():
    """DVSS with the native CPU scan (direction reading, no cross_scan copies) equals the pure-PyTorch route
    (cross_scan + chunked scan), forward and every parameter gradient."""
    from tofdenoise.models.scan.cpu import cpu_kernel_available

    if not cpu_kernel_available():
        pytest.skip("native CPU scan not built on this machine")
    outs = []
    for backend in ("torch", "cpu"):
        torch.manual_seed(0)
        model = tiny("dvss", scan_backend=backend)
        _randomise_heads(model)
        y = model(torch.randn(2, 1, 19, 23, generator=torch.Generator().manual_seed(2)))
        y.square().mean().backward()
        outs.append((y.detach(), torch.cat([p.grad.flatten() for p in model.parameters()])))
    torch.testing.assert_close(outs[1][0], outs[0][0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(outs[1][1], outs[0][1], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_dvss_inference_runs_channels_last_and_equals_the_training_layout(backend, monkeypatch):
    """Without a gradient DVSS runs its blocks on channels-last memory (and the native kernel projects the steps
    itself); with a gradient it keeps the default layout. The two forwards agree to rounding, at an odd size and
    batch 2, on both scan routes."""
    from tofdenoise.models import dvss as dvss_module
    from tofdenoise.models.scan.cpu import cpu_kernel_available

    if backend == "cpu" and not cpu_kernel_available():
        pytest.skip("native CPU scan not built on this machine")
    seen = []
    real_forward = dvss_module.DVSSBlock.forward
    monkeypatch.setattr(
        dvss_module.DVSSBlock,
        "forward",
        lambda self, x: seen.append(x.is_contiguous(memory_format=torch.channels_last)) or real_forward(self, x),
    )
    torch.manual_seed(0)
    model = tiny("dvss", scan_backend=backend).eval()
    _randomise_heads(model)
    x = torch.randn(2, 1, 19, 23, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        y_inference = model(x)
    assert seen and all(seen)
    seen.clear()
    y_training = model(x)
    assert seen and not any(seen)
    torch.testing.assert_close(y_inference, y_training.detach(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("variant", ["dvss", "dvss_se", "dvss_no_local", "dvss_no_dwconv"])
def test_dvss_block_folded_inference_equals_the_block(variant, monkeypatch):
    """Inference on channels-last memory folds SS2D's out_proj into the 1x1 fusion and drops the concatenations
    (block and skip fusions): the same numbers to rounding as the block with folding switched off, for every
    ablation variant, and the folded path is really taken."""
    from tofdenoise.models import dvss as dvss_module

    torch.manual_seed(1)
    model = tiny(variant).eval()
    _randomise_heads(model)
    for p in model.parameters():  # weights away from their initialisation (zero heads, unit norms)
        p.data.add_(0.05 * torch.randn_like(p))
    x = torch.randn(1, 1, 21, 26, generator=torch.Generator().manual_seed(3))
    folded = []
    real = dvss_module.DVSSBlock._forward_folded
    monkeypatch.setattr(dvss_module.DVSSBlock, "_forward_folded", lambda *a: folded.append(1) or real(*a))
    with torch.no_grad():
        y_folded = model(x)
        assert folded
        monkeypatch.setattr(dvss_module, "folds_for_inference", lambda x: False)
        folded.clear()
        y_plain = model(x)
        assert not folded
    torch.testing.assert_close(y_folded, y_plain, rtol=1e-5, atol=1e-5)
    assert (y_folded - x).abs().max() > 1e-3  # the blocks did something


def test_conv1x1_of_cat_equals_the_convolution_of_the_concatenation():
    from tofdenoise.models.dvss import conv1x1_of_cat

    torch.manual_seed(0)
    for bias in (True, False):
        conv = nn.Conv2d(5 + 3, 4, 1, bias=bias)
        a = torch.randn(2, 5, 6, 7).contiguous(memory_format=torch.channels_last)
        b = torch.randn(2, 3, 6, 7)  # default layout: copied, still right
        got = conv1x1_of_cat(conv, a, b)
        torch.testing.assert_close(got, conv(torch.cat([a, b], dim=1)), rtol=1e-5, atol=1e-6)
        assert got.is_contiguous(memory_format=torch.channels_last)


def test_scr_one_image_without_gradient_equals_its_batch_path():
    """SCR on one image under no_grad scales the depthwise kernels by the channel gate instead of forming X * g: the
    same output to rounding as the path taken with a gradient or a batch."""
    torch.manual_seed(0)
    scr = SCR(8)
    for p in scr.parameters():
        p.data.normal_(0, 0.5)
    x = torch.randn(1, 8, 9, 11)
    with torch.no_grad():
        fast = scr(x)
        batch = scr(torch.cat([x, x]))[:1]
    slow = scr(x.clone().requires_grad_())
    torch.testing.assert_close(fast, slow.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fast, batch, rtol=1e-5, atol=1e-6)
    # under autocast (bf16 on a GPU) the shortcut is not taken: its in-place gates would mix dtypes
    calls = []
    scr._refine_one_image = lambda *a: calls.append(1)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = scr(x)
    assert not calls and out.shape == x.shape


@pytest.mark.parametrize("module", ["scr", "se"])
def test_channel_gate_factored_out_equals_the_module(module):
    """SCR and SE hand over one image's output as (T, g) with T * g their output (DVSS folds g into its fusion's
    weights); both are the module's own output to rounding."""
    torch.manual_seed(5)
    m = SCR(8) if module == "scr" else SqueezeExcitation(8)
    for p in m.parameters():
        p.data.normal_(0, 0.5)
    x = torch.randn(1, 8, 9, 11)
    with torch.no_grad():
        t, g = m.factored(x)
        assert g.shape == (1, 8, 1, 1)
        want = m(x.clone().requires_grad_()).detach()  # the batch path, no shortcut
        torch.testing.assert_close(t * g, want, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(m(x), want, rtol=1e-5, atol=1e-6)
