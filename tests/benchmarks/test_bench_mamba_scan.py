"""The mamba-ssm baseline bench's own parts (its CUDA build runs on a GPU machine only): the autograd wrapper over
the extension's fwd / bwd calls gives the PyTorch scan's output and gradients (with the stand-in extension), and a
source folder without mamba's kernels is refused by name."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from tofdenoise.models.scan.reference import selective_scan_chunked

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))  # benchmark code, not the package
import bench_mamba_scan as bms  # noqa: E402


def test_the_wrapper_passes_the_extensions_gradients_through_autograd():
    g = torch.Generator().manual_seed(0)
    b, dim, length, groups, n = 2, 6, 17, 2, 3
    plain = [
        torch.randn(b, dim, length, generator=g),
        0.5 * torch.randn(b, dim, length, generator=g),
        -torch.exp(0.5 * torch.randn(dim, n, generator=g)),
        torch.randn(b, groups, n, length, generator=g),
        torch.randn(b, groups, n, length, generator=g),
        torch.randn(dim, generator=g),
        torch.randn(dim, generator=g),
    ]
    dy = torch.randn(b, dim, length, generator=g)
    ins = [t.clone().requires_grad_() for t in plain]
    y = bms.mamba_scan(bms.StandInExtension())(*ins, True)
    grads = torch.autograd.grad(y, ins, dy)
    ref_in = [t.clone().requires_grad_() for t in plain]
    y_ref = selective_scan_chunked(*ref_in, True)
    want = torch.autograd.grad(y_ref, ref_in, dy)
    torch.testing.assert_close(y, y_ref)
    assert len(grads) == 7
    for got, ref in zip(grads, want):
        torch.testing.assert_close(got, ref)


def test_a_folder_without_mambas_kernels_is_refused_by_name(tmp_path):
    (tmp_path / "selective_scan.cpp").write_text("// not mamba")
    with pytest.raises(SystemExit, match="lacks selective_scan_fwd_fp32.cu"):
        bms.build_extension(tmp_path, 90, tmp_path / "build", print)


def test_build_only_records_the_build_and_times_nothing(tmp_path):
    out = tmp_path / "build.json"
    assert bms.main(["--dry", "--build-only", "--json", str(out)]) == 0
    import json

    res = json.loads(out.read_text())
    assert res["build"] == {"stand_in": True}
    assert "scan" not in res
