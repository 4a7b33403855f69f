"""Training losses: hand-computed values, NAR weights, gradient term, masking, registry and configs."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
import yaml

from tofdenoise.training.losses import (
    FullLoss,
    L1DepthLoss,
    NoiseAwareLoss,
    available_losses,
    build_loss,
    charbonnier,
    normalized_sigma,
    uncertainty_weight,
)

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"

EPS = 1e-3


def rho(x: float) -> float:
    return math.sqrt(x * x + EPS * EPS)


def _t(rows):
    return torch.tensor(rows, dtype=torch.float64)[None, None]


def test_available_losses_and_unknown_names():
    assert available_losses() == ["full", "l1", "nar"]
    with pytest.raises(ValueError, match="full, l1, nar"):
        build_loss("l2")
    with pytest.raises(ValueError, match="accepted"):
        build_loss("nar", lambda_g=0.1)
    with pytest.raises(ValueError, match=r"loss 'l1' got unexpected keyword argument\(s\) 'beta'; accepted: none"):
        build_loss("l1", beta=0.5)
    assert isinstance(build_loss("L1"), L1DepthLoss)
    full = build_loss("full", beta=0.25, lambda_g=0.5)
    assert isinstance(full, FullLoss) and full.beta == 0.25 and full.lambda_g == 0.5
    with pytest.raises(ValueError, match="beta"):
        build_loss("nar", beta=-1.0)


def test_charbonnier_values():
    assert charbonnier(torch.tensor(0.0)).item() == pytest.approx(EPS)
    assert charbonnier(torch.tensor(3.0), eps=4.0).item() == pytest.approx(5.0)


def test_l1_hand_computed_with_mask():
    pred = _t([[1.0, 2.0], [3.0, 4.0]])
    gt = _t([[1.5, 2.0], [1.0, 100.0]])
    mask = _t([[1.0, 1.0], [1.0, 0.0]])
    loss = build_loss("l1")(pred, gt, None, mask)
    assert loss.item() == pytest.approx((0.5 + 0.0 + 2.0) / 3)


def test_normalized_sigma_and_weights_per_image_min_max():
    sigma = torch.tensor([[[[1.0, 2.0], [3.0, 5.0]]], [[[10.0, 30.0], [20.0, 99.0]]]])
    mask = torch.ones_like(sigma)
    mask[1, 0, 1, 1] = 0  # 99 is invalid: image 2 ranges over 10..30
    valid = mask > 0
    s = normalized_sigma(sigma, valid, eta=1e-6)
    exp0 = [(v - 1.0) / (4.0 + 1e-6) for v in (1.0, 2.0, 3.0, 5.0)]
    exp1 = [(v - 10.0) / (20.0 + 1e-6) for v in (10.0, 30.0, 20.0)]
    assert s[0].flatten().tolist() == pytest.approx(exp0)
    assert s[1].flatten().tolist()[:3] == pytest.approx(exp1)
    assert s[1, 0, 1, 1].item() == 0.0
    w = uncertainty_weight(sigma, valid, beta=0.5)
    assert w[0].flatten().tolist() == pytest.approx([1.0 + 0.5 * e for e in exp0])
    assert w[1, 0, 1, 1].item() == 0.0
    # a constant sigma map gives weight 1 (eta keeps the division finite)
    flat = uncertainty_weight(torch.full((1, 1, 3, 3), 7.0), torch.ones(1, 1, 3, 3, dtype=torch.bool))
    assert torch.allclose(flat, torch.ones_like(flat))


def test_nar_hand_computed():
    pred = _t([[0.0, 1.0], [2.0, 3.0]])
    gt = _t([[0.0, 0.5], [1.0, 1.0]])
    sigma = _t([[1.0, 2.0], [3.0, 5.0]])
    mask = torch.ones_like(pred)
    diffs = [0.0, 0.5, 1.0, 2.0]
    weights = [1.0 + 0.5 * (s - 1.0) / (4.0 + 1e-6) for s in (1.0, 2.0, 3.0, 5.0)]
    expected = sum(w * rho(d) for w, d in zip(weights, diffs)) / 4
    loss = NoiseAwareLoss()(pred, gt, sigma, mask)
    assert loss.item() == pytest.approx(expected, rel=1e-12)
    # beta = 0 and a tiny eps reduce NAR to L1
    l1 = build_loss("l1")(pred, gt, sigma, mask)
    assert build_loss("nar", beta=0.0, eps=1e-12)(pred, gt, sigma, mask).item() == pytest.approx(l1.item())


def test_nar_requires_sigma():
    x = torch.zeros(1, 1, 2, 2)
    with pytest.raises(ValueError, match="sigma"):
        build_loss("nar")(x, x, None, torch.ones_like(x))


def test_gradient_term_hand_computed_only_differences_with_both_pixels_valid():
    # error e = pred - gt on a 2x3 grid; pixel (1, 2) invalid
    pred = _t([[1.0, 3.0, 6.0], [0.0, 2.0, 50.0]])
    gt = _t([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    mask = _t([[1.0, 1.0, 1.0], [1.0, 1.0, 0.0]])
    sigma = torch.ones_like(pred)  # constant sigma -> NAR weights 1
    # horizontal differences of e: row0: 2, 3 ; row1: 2 (the 2->50 one has an invalid pixel)
    # vertical differences of e: col0: -1, col1: -1 (col2 has an invalid pixel)
    grad = rho(2) + rho(3) + rho(2) + rho(-1) + rho(-1)
    n_valid = 5
    nar = (rho(1) + rho(3) + rho(6) + rho(0) + rho(2)) / n_valid
    full = FullLoss(lambda_g=0.1)
    terms = full.terms(pred, gt, sigma, mask)
    assert terms["grad"].item() == pytest.approx(grad / n_valid, rel=1e-12)
    assert terms["nar"].item() == pytest.approx(nar, rel=1e-12)
    assert terms["loss"].item() == pytest.approx(nar + 0.1 * grad / n_valid, rel=1e-12)
    # an offset prediction has the same gradients as the target: the gradient term is eps per difference
    flat = full.terms(gt + 0.7, gt, sigma, torch.ones_like(gt))
    assert flat["grad"].item() == pytest.approx(EPS * 7 / 6)


@pytest.mark.parametrize("name", ["l1", "nar", "full"])
def test_garbage_in_masked_pixels_changes_neither_loss_nor_gradient(name):
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(2, 1, 6, 7, generator=g)
    sigma = torch.rand(2, 1, 6, 7, generator=g) + 0.1
    mask = (torch.rand(2, 1, 6, 7, generator=g) > 0.3).float()
    base = torch.rand(2, 1, 6, 7, generator=g)
    loss_fn = build_loss(name)
    results = []
    for garbage in (0.0, torch.nan, 1e6):
        pred = base.clone()
        pred[mask == 0] = garbage
        pred.requires_grad_(True)
        t, s = gt.clone(), sigma.clone()
        t[mask == 0] = garbage
        s[mask == 0] = garbage
        loss = loss_fn(pred, t, s, mask)
        loss.backward()
        assert torch.isfinite(pred.grad).all()
        assert (pred.grad[mask == 0] == 0).all()
        results.append((loss.item(), pred.grad.clone()))
    for value, grad in results[1:]:
        assert value == pytest.approx(results[0][0], rel=1e-6)
        assert torch.allclose(grad, results[0][1], atol=1e-7)


@pytest.mark.parametrize("name", ["l1", "nar", "full"])
def test_all_invalid_batch_gives_zero_with_gradient_path(name):
    pred = torch.full((2, 1, 4, 4), torch.nan, requires_grad=True)
    sigma = torch.full((2, 1, 4, 4), torch.nan)
    loss = build_loss(name)(pred, torch.zeros(2, 1, 4, 4), sigma, torch.zeros(2, 1, 4, 4))
    assert loss.item() == 0.0
    loss.backward()
    assert torch.equal(pred.grad, torch.zeros_like(pred))


def test_nonfinite_sigma_at_valid_pixel_gets_largest_weight():
    sigma = torch.tensor([[[[1.0, 3.0, torch.nan]]]])
    valid = torch.ones_like(sigma, dtype=torch.bool)
    w = uncertainty_weight(sigma, valid, beta=0.5)
    assert w.flatten().tolist() == pytest.approx([1.0, 1.0 + 0.5 * 2 / (2 + 1e-6), 1.5])


def test_shape_mismatch_is_a_clear_error():
    with pytest.raises(ValueError, match="differ in shape"):
        build_loss("l1")(torch.zeros(1, 1, 4, 4), torch.zeros(1, 1, 4, 5), None, torch.ones(1, 1, 4, 4))


@pytest.mark.parametrize("name", ["l1", "nar", "full"])
def test_loss_configs_build_the_paper_defaults(name):
    cfg = yaml.safe_load((CONFIG_DIR / "loss" / f"{name}.yaml").read_text())
    assert cfg["name"] == name
    loss = build_loss(cfg["name"], **cfg["kwargs"])
    if name != "l1":
        assert (loss.beta, loss.eps, loss.eta) == (0.5, 1e-3, 1e-6)
    if name == "full":
        assert loss.lambda_g == 0.1
