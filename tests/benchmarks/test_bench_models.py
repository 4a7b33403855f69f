"""The CPU benchmark's baseline adapter (an extension built from an older kernel source): a source without the
fused dt projection is given the product it ran before, with the output of today's fused kernel."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from tofdenoise.models.scan import cpu as scan_cpu

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmark code, not the package
import bench_models  # noqa: E402


class _OlderSource:
    """An extension as an older kernel source built it: scan_fwd only (needs chunk >= 1), no ss2d_fwd_lowrank."""

    def __init__(self, ext) -> None:
        self.calls: list[int] = []
        self._ext = ext

    def scan_fwd(self, *args):
        assert args[-1] >= 1, "an older source needs chunk >= 1"
        self.calls.append(args[-1])
        return self._ext.scan_fwd(*args)


def test_an_older_source_runs_the_fused_call_through_the_product():
    ext = scan_cpu.load_extension()
    if ext is None:
        pytest.skip("native CPU scan not built on this machine")
    g = torch.Generator().manual_seed(3)
    b, h, w, d, n, r = 2, 5, 7, 20, 4, 3
    x = torch.randn(b, h * w, d, generator=g)
    x_dbl = torch.randn(b, h * w, 4, r + 2 * n, generator=g)
    weight = torch.randn(4, d, r, generator=g)
    A = -torch.exp(0.3 * torch.randn(4 * d, n, generator=g))
    D, bias = torch.randn(4 * d, generator=g), torch.randn(4 * d, generator=g) - 1.0
    args = (x, x_dbl[..., :r], weight.reshape(4 * d, r), A, x_dbl[..., r : r + n], x_dbl[..., r + n :], D, bias, h, w)
    older = _OlderSource(ext)
    adapted = bench_models._ChunkZeroAdapter(older, scan_cpu.CHUNK)
    got = adapted.ss2d_fwd_lowrank(*args)
    assert older.calls == [scan_cpu.CHUNK]
    torch.testing.assert_close(got, ext.ss2d_fwd_lowrank(*args), rtol=1e-5, atol=1e-5)


def test_an_older_source_runs_the_output_stage_through_torch():
    ext = scan_cpu.load_extension()
    if ext is None:
        pytest.skip("native CPU scan not built on this machine")
    g = torch.Generator().manual_seed(4)
    y, z = torch.randn(30, 20, generator=g), torch.randn(30, 40, generator=g)[:, :20]
    w, b = torch.randn(20, generator=g), torch.randn(20, generator=g)
    adapted = bench_models._ChunkZeroAdapter(_OlderSource(ext), scan_cpu.CHUNK)
    got = adapted.ss2d_out_gate(y.clone(), z, w, b, 1e-5)
    torch.testing.assert_close(got, ext.ss2d_out_gate(y.clone(), z, w, b, 1e-5), rtol=1e-5, atol=1e-5)


class _ChunkZeroSource(_OlderSource):
    """A source between 9109c5f and f99439f: its scan_fwd runs chunk 0 as the inference forward (no checkpoints)."""

    def scan_fwd(self, *args):
        self.calls.append(args[-1])
        return self._ext.scan_fwd(*args)


def test_a_source_that_knows_chunk_zero_runs_its_own_inference_forward():
    """Only a source that needs chunk >= 1 has its inference forward turned into the checkpointing one: a baseline
    that knows chunk 0 and ran it as its inference would otherwise be timed writing checkpoints it never wrote."""
    ext = scan_cpu.load_extension()
    if ext is None:
        pytest.skip("native CPU scan not built on this machine")
    g = torch.Generator().manual_seed(5)
    b, h, w, d, n = 1, 4, 6, 16, 4
    x = torch.randn(b, h * w, d, generator=g)
    delta = torch.randn(b, h * w, 4 * d, generator=g)
    A = -torch.exp(0.3 * torch.randn(4 * d, n, generator=g))
    B, C = torch.randn(b, h * w, 4, n, generator=g), torch.randn(b, h * w, 4, n, generator=g)
    args = (x, delta, A, B, C, None, None, True, True, h, w, 0)
    knows = _ChunkZeroSource(ext)
    y, ck = bench_models._ChunkZeroAdapter(knows, scan_cpu.CHUNK, chunk_zero=True).scan_fwd(*args)
    assert knows.calls == [0] and ck.numel() == 0
    older = _OlderSource(ext)
    y_old, ck_old = bench_models._ChunkZeroAdapter(older, scan_cpu.CHUNK).scan_fwd(*args)
    assert older.calls == [scan_cpu.CHUNK] and ck_old.numel() > 0
    torch.testing.assert_close(y, y_old, rtol=1e-5, atol=1e-5)
    source = (Path(scan_cpu.__file__).parent / "csrc" / "selective_scan_cpu.cpp").read_bytes()
    assert bench_models.knows_chunk_zero(source)  # today's source
    assert not bench_models.knows_chunk_zero(source.replace(bench_models.CHUNK_ZERO_MARKER, b"SOMETHING_ELSE"))
