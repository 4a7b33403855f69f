"""The export scan (plain tensor steps) equals the sequential selective scan."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models.scan import selective_scan, selective_scan_ref
from tofdenoise.models.scan.export import selective_scan_export


def _inputs(length: int, groups: int = 2, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    b, d, n = 2, 6, 4
    return (
        torch.randn(b, d, length, generator=g),
        torch.randn(b, d, length, generator=g),
        -3.0 * torch.rand(d, n, generator=g),
        torch.randn(b, groups, n, length, generator=g),
        torch.randn(b, groups, n, length, generator=g),
        torch.randn(d, generator=g),
        torch.randn(d, generator=g),
    )


@pytest.mark.parametrize("length", [1, 7, 64, 301])
def test_export_scan_equals_the_reference(length):
    u, delta, A, B, C, D, bias = _inputs(length)
    ref = selective_scan_ref(u, delta, A, B, C, D, bias, True)
    out = selective_scan_export(u, delta, A, B, C, D, bias, True)
    assert torch.allclose(out, ref, atol=1e-4, rtol=1e-4)
    assert torch.allclose(selective_scan(u, delta, A, B, C, D, bias, True, backend="export"), ref, atol=1e-4)


def test_too_few_doubling_steps_are_wrong_beyond_their_length():
    u, delta, A, B, C, D, bias = _inputs(40, groups=1)
    ref = selective_scan_ref(u, delta, A, B[:, 0], C[:, 0], D, bias, True)
    assert torch.allclose(selective_scan_export(u, delta, A, B[:, 0], C[:, 0], D, bias, True, steps=6), ref, atol=1e-4)
    short = selective_scan_export(u, delta, A, B[:, 0], C[:, 0], D, bias, True, steps=5)
    assert torch.allclose(short[..., :32], ref[..., :32], atol=1e-4)
    assert not torch.allclose(short[..., 32:], ref[..., 32:])
