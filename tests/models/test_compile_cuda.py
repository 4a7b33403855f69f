"""``torch.compile`` of the U-Net and the Restormer equals eager (DVSS's is in scan/test_ops.py): forward and every
parameter gradient, with the zero-initialised heads drawn so that every layer gets a gradient; on the CPU in float32
(the Restormer's compile takes minutes: ``slow``) and the U-Net in bf16 autocast, on CUDA in float32 and bf16 autocast
(``-m gpu``); in bf16 within bf16's own rounding of a float32 run (``_assert_within_bf16_rounding``)."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models.common import draw_zero_parameters
from tofdenoise.models.registry import build_backbone

from .scan.test_ops import _compare_compiled

SMALL = {
    "unet": {"width": 8, "stages": 3},
    "restormer": {"width": 8, "blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "refinement_blocks": 1},
}


@pytest.mark.parametrize(
    "backbone, autocast",
    [("unet", False), ("unet", True), pytest.param("restormer", False, marks=pytest.mark.slow)],
)
def test_compiled_backbone_equals_eager_on_cpu(backbone, autocast):
    torch.manual_seed(0)
    net = draw_zero_parameters(build_backbone(backbone, in_channels=1, **SMALL[backbone]))
    _compare_compiled(net, torch.randn(2, 1, 32, 48), autocast)


@pytest.mark.gpu
@pytest.mark.parametrize("autocast", [False, True])
@pytest.mark.parametrize("backbone", sorted(SMALL))
def test_compiled_backbone_equals_eager_on_cuda(backbone, autocast):
    torch.manual_seed(0)
    net = draw_zero_parameters(build_backbone(backbone, in_channels=1, **SMALL[backbone])).cuda()
    tf32 = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False  # eager and compiled may pick other TF32 convolutions
    try:
        _compare_compiled(net, torch.randn(2, 1, 32, 48, device="cuda"), autocast)
    finally:
        torch.backends.cudnn.allow_tf32 = tf32
