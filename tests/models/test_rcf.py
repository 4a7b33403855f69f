"""RCF (our reading): depth + amplitude in, K step predictions in training and one in eval, any input size,
identity at initialisation, gradient to every parameter, the amplitude matters, neighbour differences by hand."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from tofdenoise.models import build_backbone, count_parameters
from tofdenoise.models.rcf import RCF, neighbour_differences

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "backbone" / "rcf.yaml"
TINY = dict(width=8, hidden=8, steps=3, global_levels=2)


def tiny(**kw) -> RCF:
    torch.manual_seed(0)
    return build_backbone("rcf", **{**TINY, **kw})


def _randomise_head(model: RCF) -> None:
    """The zero-initialised head blocks gradients to the trunk and makes every output the input: give it
    random weights for the flow and amplitude tests."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        last = model.head[-1]
        last.weight.copy_(0.1 * torch.randn(last.weight.shape, generator=g))
        last.bias.copy_(0.01 * torch.randn(last.bias.shape, generator=g))


def _input(b: int, h: int, w: int, seed: int = 2) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.cat([torch.randn(b, 1, h, w, generator=g), torch.rand(b, 1, h, w, generator=g)], dim=1)


@pytest.mark.parametrize("size", [(37, 53), (4, 4), (1, 9), (64, 48)])
def test_steps_in_training_one_prediction_in_eval_any_size(size):
    model = tiny()
    _randomise_head(model)
    x = _input(2, *size)
    model.train()
    steps = model(x)
    assert isinstance(steps, list) and len(steps) == 3
    assert all(s.shape == (2, 1, *size) for s in steps)
    assert not torch.allclose(steps[0], steps[-1])  # the steps refine: they differ
    model.eval()
    with torch.no_grad():
        final = model(x)
    assert isinstance(final, torch.Tensor) and final.shape == (2, 1, *size)
    torch.testing.assert_close(final, steps[-1].detach())


def test_identity_at_initialisation_on_every_step():
    model = tiny().train()
    x = _input(2, 21, 30)
    with torch.no_grad():
        for step in model(x):
            torch.testing.assert_close(step, x[:, :1], rtol=0, atol=0)


def test_gradient_reaches_every_parameter_through_every_step():
    model = tiny().train()
    _randomise_head(model)
    x = _input(1, 37, 53).requires_grad_(True)
    sum(s.square().mean() for s in model(x)).backward()
    assert torch.isfinite(x.grad).all() and x.grad[:, 1].abs().sum() > 0  # the amplitude channel too
    missing = [n for n, p in model.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not missing, missing
    zero = [n for n, p in model.named_parameters() if p.grad.abs().sum() == 0]
    assert not zero, zero


def test_the_first_step_alone_trains_the_encoders():
    """A loss on step 1 only reaches the whole trunk (the step losses supervise the shared update)."""
    model = tiny().train()
    _randomise_head(model)
    model(_input(1, 16, 16))[0].square().mean().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


def test_the_amplitude_channel_changes_the_output():
    model = tiny().eval()
    _randomise_head(model)
    x = _input(1, 24, 24)
    y = x.clone()
    y[:, 1] = torch.rand(24, 24, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        diff = (model(x) - model(y)).abs()
    assert diff.max() > 1e-3
    # and only the amplitude changed: the same input gives the same output
    with torch.no_grad():
        torch.testing.assert_close(model(x), model(x.clone()))


def test_step_loss_weights_are_normalised_powers_of_gamma():
    model = tiny(steps=4, step_gamma=0.5)
    raw = [0.125, 0.25, 0.5, 1.0]
    assert model.step_loss_weights == pytest.approx([w / sum(raw) for w in raw])
    assert tiny(steps=3, step_gamma=1.0).step_loss_weights == pytest.approx([1 / 3] * 3)
    assert RCF.deep_supervision


def test_neighbour_differences_by_hand():
    depth = torch.arange(20, dtype=torch.float32).view(1, 1, 4, 5)  # value = 5 row + col
    d1 = neighbour_differences(depth, 1)
    # interior pixel (1, 1): neighbours in row-major order, offsets (-1,-1) ... (1,1)
    assert d1[0, :, 1, 1].tolist() == [-6, -5, -4, -1, 1, 4, 5, 6]
    # corner (0, 0) with replicate padding: out-of-image neighbours repeat the border
    assert d1[0, :, 0, 0].tolist() == [0, 0, 1, 0, 1, 5, 5, 6]
    d2 = neighbour_differences(depth, 2)
    assert d2[0, 6, 3, 0].item() == 0.0  # two rows below the last row: replicate -> the pixel itself
    assert d2[0, 6, 1, 0].item() == 10.0  # two rows below row 1: row 3
    square = torch.arange(25, dtype=torch.float32).view(1, 1, 5, 5)
    assert neighbour_differences(square, 2)[0, :, 2, 2].tolist() == [-12, -10, -8, -2, 2, 8, 10, 12]
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        neighbour_differences(torch.zeros(1, 2, 4, 4))


def test_needs_depth_and_amplitude_and_checks_its_arguments():
    with pytest.raises(ValueError, match="in_channels must be 2.*conditioning.use_signal_channel=true"):
        build_backbone("rcf", in_channels=1)
    with pytest.raises(ValueError, match="steps must be >= 1"):
        build_backbone("rcf", steps=0)
    with pytest.raises(ValueError, match="step_gamma"):
        build_backbone("rcf", step_gamma=0.0)
    with pytest.raises(ValueError, match=r"expected input of shape \(B, 2, H, W\)"):
        tiny()(torch.zeros(1, 1, 8, 8))


def test_config_builds_a_small_network_that_wants_the_amplitude():
    cfg = yaml.safe_load(CONFIG.read_text())
    assert cfg["name"] == "rcf" and cfg["use_signal_channel"] is True
    model = build_backbone(cfg["name"], **cfg["kwargs"])
    assert 100_000 < count_parameters(model) < 1_000_000
    assert cfg["recipe"]["lr"] > 0 and cfg["recipe"]["warmup_steps"] >= 0


def test_depth_restorer_trains_rcf_on_every_step_and_evaluates_the_last():
    """Through DepthRestorer: the training loss is the gamma-weighted mean of the K step losses (checked against
    the step losses computed by hand), and restore_mm returns the final step."""
    from tofdenoise.training.module import DepthRestorer

    model = DepthRestorer(backbone="rcf", backbone_kwargs=TINY, loss="l1", conditioning={"use_signal_channel": True})
    _randomise_head(model.backbone)
    g = torch.Generator().manual_seed(3)
    clean = 800.0 + 50.0 * torch.rand(2, 1, 20, 20, generator=g)
    batch = {
        "noisy": clean + 5.0 * torch.randn(2, 1, 20, 20, generator=g),
        "clean": clean,
        "sigma": torch.full_like(clean, 5.0),
        "mask": torch.ones_like(clean),
        "amplitude": torch.rand(2, 1, 20, 20, generator=g),
    }
    model.train()
    x, offset = model.condition(batch)
    steps = model.backbone(x)
    per_step = [(s * 100.0 + offset - clean).abs().mean() for s in steps]
    expected = sum(w * loss for w, loss in zip(model.backbone.step_loss_weights, per_step))
    torch.testing.assert_close(model.training_loss(batch), expected, rtol=1e-5, atol=1e-5)
    model.eval()
    with torch.no_grad():
        torch.testing.assert_close(model.restore_mm(batch), steps[-1].detach() * 100.0 + offset, rtol=1e-5, atol=1e-4)
