"""models.common.eager_inference: where a backbone's inference-only shortcuts may run."""

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
