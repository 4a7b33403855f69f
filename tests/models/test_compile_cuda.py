"""``torch.compile`` of the U-Net and the Restormer on CUDA equals eager (DVSS's is in scan/test_ops.py): forward and
every parameter gradient, float32 and bf16 autocast (run on a GPU machine: ``-m gpu``)."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models.registry import build_backbone

from .scan.test_ops import _assert_equal_runs, _forward_backward

SMALL = {
    "unet": {"width": 8, "stages": 3},
    "restormer": {"width": 8, "blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "refinement_blocks": 1},
}


@pytest.mark.gpu
@pytest.mark.parametrize("autocast", [False, True])
@pytest.mark.parametrize("backbone", sorted(SMALL))
def test_compiled_backbone_equals_eager_on_cuda(backbone, autocast):
    torch.manual_seed(0)
    net = build_backbone(backbone, in_channels=1, **SMALL[backbone]).cuda()
    x = torch.randn(2, 1, 32, 48, device="cuda")
    tf32 = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False  # eager and compiled may pick other TF32 convolutions
    try:
        with torch.autocast("cuda", dtype=torch.bfloat16, enabled=autocast):
            eager = _forward_backward(net, x)
            torch._dynamo.reset()
            compiled = _forward_backward(net, x, torch.compile(net, fullgraph=True))
    finally:
        torch.backends.cudnn.allow_tf32 = tf32
    _assert_equal_runs(eager, compiled, 2e-2 if autocast else 1e-4)
