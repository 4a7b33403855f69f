"""models.common: where a backbone's inference-only shortcuts may run (eager_inference), and the drawn zero parameters
that let a comparison of two executions reach every layer (draw_zero_parameters)."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models.common import eager_inference


def test_eager_inference_only_in_an_eager_forward_without_gradient():
    seen = []

    def probe(x: torch.Tensor) -> torch.Tensor:
        seen.append(eager_inference())
        return x + 1

    x = torch.zeros(2)
    probe(x)
    with torch.no_grad():
        probe(x)
        torch.jit.trace(probe, (x,), check_trace=False)
        torch.compile(probe, backend="eager", fullgraph=True)(x)
    assert seen == [False, True, False, False]


@pytest.mark.parametrize("onednn", [True, False])
def test_pointwise_is_the_per_pixel_product_on_either_layout(onednn, monkeypatch):
    """models.common.pointwise: x (B, C, H, W), weight (out, C), bias -> x[b, :, i, j] @ weight.T + bias at every
    pixel; channels-last in, channels-last out; equal to the (B H W, C) rows' product, on oneDNN and on MKL."""
    from tofdenoise.models import common
    from tofdenoise.models.common import pointwise

    monkeypatch.setattr(common, "POINTWISE_ONEDNN", onednn)

    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 7, 9, generator=gen)
    weight, bias = torch.randn(3, 5, generator=gen), torch.randn(3, generator=gen)
    rows = x.permute(0, 2, 3, 1).reshape(-1, 5)
    want = (rows @ weight.t() + bias).view(2, 7, 9, 3).permute(0, 3, 1, 2)
    for layout in (torch.contiguous_format, torch.channels_last):
        got = pointwise(x.contiguous(memory_format=layout), weight, bias)
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
        assert got.is_contiguous(memory_format=layout if onednn else torch.channels_last)
    torch.testing.assert_close(pointwise(x, weight), want - bias.view(1, 3, 1, 1), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backbone", ["unet", "dvss", "restormer"])
def test_drawn_zero_parameters_give_every_layer_a_gradient(backbone):
    """At initialisation every backbone's residual head is zero, so only the head gets a gradient; with the zero
    parameters drawn (and nothing else changed) every parameter does, and the draw is the same for the same seed."""
    from tofdenoise.models.common import draw_zero_parameters
    from tofdenoise.models.registry import build_backbone

    small = {
        "unet": {"width": 4, "stages": 2},
        "dvss": {"width": 8, "enc_blocks": [1], "bottleneck_blocks": 1},
        "restormer": {"width": 8, "blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "refinement_blocks": 1},
    }[backbone]

    def grads(net):
        net.zero_grad(set_to_none=True)
        net(torch.randn(1, 1, 16, 16, generator=torch.Generator().manual_seed(1))).square().mean().backward()
        return {n: p.grad for n, p in net.named_parameters()}

    torch.manual_seed(0)
    net = build_backbone(backbone, in_channels=1, **small)
    before = {n: p.detach().clone() for n, p in net.named_parameters()}
    assert sum(int(g is not None and bool(g.any())) for g in grads(net).values()) <= 2  # the head only
    zero = [n for n, p in before.items() if not p.any()]
    assert zero and draw_zero_parameters(net, seed=3) is net
    after = dict(net.named_parameters())
    for n, p in before.items():
        assert torch.equal(after[n], p) == (n not in zero), n  # the zero ones drawn, the rest untouched
    assert all(g is not None and g.any() for g in grads(net).values())
    torch.manual_seed(0)
    again = draw_zero_parameters(build_backbone(backbone, in_channels=1, **small), seed=3)
    assert all(torch.equal(p, after[n]) for n, p in again.named_parameters())


def test_execution_distances_by_hand():
    """Output: largest difference over the reference's largest magnitude; a gradient: over the larger of its own
    largest magnitude and 1e-3 of the network's largest gradient (a near-zero gradient is judged at the network's
    scale)."""
    from tofdenoise.models.common import execution_distances

    y0 = torch.tensor([2.0, -4.0])
    g0 = {"w": torch.tensor([10.0, -20.0]), "b": torch.tensor([1e-6, 0.0])}
    y1 = torch.tensor([2.0, -3.0])
    g1 = {"w": torch.tensor([10.0, -19.0]), "b": torch.tensor([0.0, 0.0])}
    d = execution_distances((y0, g0), (y1, g1))
    assert d["output"] == pytest.approx(1.0 / 4.0)
    assert d["w"] == pytest.approx(1.0 / 20.0)
    assert d["b"] == pytest.approx(1e-6 / (1e-3 * 20.0))  # the floor, not b's own 1e-6
    assert execution_distances((y0, g0), (y0, g0)) == {"output": 0.0, "w": 0.0, "b": 0.0}
    with pytest.raises(ValueError, match="different parameters"):
        execution_distances((y0, g0), (y1, {"w": g1["w"]}))
