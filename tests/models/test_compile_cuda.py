"""``torch.compile`` of every learned backbone but DVSS (whose is in scan/test_ops.py) equals eager: forward and every
parameter gradient, with the zero-initialised heads drawn so that every layer gets a gradient; on the CPU in float32
(the Restormer's, ToF-KPN's and RCF's compiles take 0.5 to several minutes on 2 cores: ``slow``) and the U-Net in bf16
autocast, on CUDA in float32 and bf16 autocast (``-m gpu``); in bf16 within bf16's own rounding of a float32 run
(``_assert_within_bf16_rounding``). RCF runs in eval mode (its training forward returns every refinement step)."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models.common import draw_zero_parameters
from tofdenoise.models.registry import build_backbone

from .scan.test_ops import _compare_compiled

SMALL = {
    "unet": {"in_channels": 1, "width": 8, "stages": 3},
    "restormer": {"in_channels": 1, "width": 8, "blocks": [1, 1, 1, 1], "heads": [1, 1, 2, 2], "refinement_blocks": 1},
    "deeptof": {"in_channels": 1},
    "tofkpn": {"in_channels": 1},
    "rcf": {"in_channels": 2, "width": 8, "hidden": 8, "steps": 2, "global_levels": 2},
}
SLOW = pytest.mark.slow


def _small(backbone: str) -> tuple[torch.nn.Module, torch.Tensor]:
    """``backbone`` at SMALL's size, zero-initialised parameters drawn (eval mode where the training forward returns
    every refinement step: RCF), and a (2, C, 32, 48) input."""
    torch.manual_seed(0)
    net = draw_zero_parameters(build_backbone(backbone, **SMALL[backbone]))
    if getattr(net, "deep_supervision", False):
        net.eval()
    return net, torch.randn(2, SMALL[backbone]["in_channels"], 32, 48)


@pytest.mark.parametrize(
    "backbone, autocast",
    [
        ("unet", False),
        ("unet", True),
        ("deeptof", False),
        pytest.param("restormer", False, marks=SLOW),
        pytest.param("tofkpn", False, marks=SLOW),
        pytest.param("rcf", False, marks=SLOW),
    ],
)
def test_compiled_backbone_equals_eager_on_cpu(backbone, autocast):
    net, x = _small(backbone)
    _compare_compiled(net, x, autocast)


@pytest.mark.gpu
@pytest.mark.parametrize("autocast", [False, True])
@pytest.mark.parametrize("backbone", sorted(SMALL))
def test_compiled_backbone_equals_eager_on_cuda(backbone, autocast):
    net, x = _small(backbone)
    net = net.cuda()
    tf32 = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False  # eager and compiled may pick other TF32 convolutions
    try:
        _compare_compiled(net, x.cuda(), autocast)
    finally:
        torch.backends.cudnn.allow_tf32 = tf32
