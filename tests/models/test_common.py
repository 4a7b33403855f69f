"""models.common.eager_inference: where a backbone's inference-only shortcuts may run."""

from __future__ import annotations

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
