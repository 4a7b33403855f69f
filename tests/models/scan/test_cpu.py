"""Native CPU selective scan (tofdenoise.models.scan.cpu): equality with the PyTorch scans (forward and every gradient),
routing of dtypes and backends, the fallback when the build fails, and SS2D's direction-reading route."""

from __future__ import annotations

import os
import shutil
import warnings

import pytest
import torch
import torch.nn.functional as F

from tofdenoise.models import available_scan_backends, selective_scan
from tofdenoise.models.scan import cpu as scan_cpu
from tofdenoise.models.scan import (
    resolve_scan_backend,
    selective_scan_chunked,
    selective_scan_ref,
    selective_scan_sequential,
    ss2d_scan_reference,
)
from tofdenoise.models.ss2d import SS2D

from .test_scan import _inputs, _rel  # the same random problems as the PyTorch scan tests

NO_BUILD = os.environ.get(scan_cpu.ENV_SWITCH, "1") in ("0", "false", "no", "off") or shutil.which("c++") is None


@pytest.fixture(scope="module")
def ext():
    """The extension, compiled once per test session (cached on disk by torch afterwards). A failed build on a
    machine with a compiler is a test failure, not a skip."""
    if NO_BUILD:
        pytest.skip("native CPU scan disabled or no C++ compiler")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a build failure warning fails here
        mod = scan_cpu.load_extension()
    assert mod is not None
    assert scan_cpu.cpu_kernel_available()
    return mod


def _grads(fn, tensors, use_d, use_bias, softplus, w):
    u, delta, A, B, C, D, bias = tensors
    d_in = delta if (softplus or use_bias) else delta.abs()  # without softplus: positive steps
    inputs = [u, delta, A, B, C] + ([D] if use_d else []) + ([bias] if use_bias else [])
    y = fn(u, d_in, A, B, C, D if use_d else None, bias if use_bias else None, softplus)
    return y, torch.autograd.grad((y * w.to(y.dtype)).sum(), inputs)


CASES = [
    # batch, dim, L, groups, N, D, delta_bias, softplus, three_d B/C
    (2, 6, 23, 1, 4, True, True, True, False),  # one group, fewer channels than lanes
    (1, 6, 23, 3, 5, True, False, True, False),  # 3 groups of 2 channels, N = 5
    (2, 8, 17, 2, 3, False, True, False, False),  # no D, bias without softplus
    (1, 4, 31, 4, 7, False, False, False, False),  # plain steps, 4 groups of 1 channel
    (2, 40, 151, 2, 16, True, True, True, False),  # 20 channels per group: a full and a partial lane block
    (1, 34, 130, 1, 16, True, True, True, True),  # 3-D B/C, N = 16 (the compiled-N path), 3 chunks
    (2, 64, 129, 4, 12, True, True, True, False),  # SS2D-like grouping, 16 channels per group
    # the backward's tasks walk ranges of lane blocks and sum dB / dC in place: 5 blocks of 16 channels in
    # parts of 2, 2, 1 (batch 1) and 3, 2 (batch 3)
    (1, 80, 70, 1, 16, True, True, True, False),
    (3, 160, 45, 2, 16, True, True, True, False),
]


@pytest.mark.parametrize("case", CASES)
def test_kernel_matches_reference_and_chunked(ext, case):
    batch, dim, length, groups, n, use_d, use_bias, softplus, three_d = case
    tensors = _inputs(batch, dim, length, groups, n, three_d=three_d)
    w = torch.randn(batch, dim, length, generator=torch.Generator().manual_seed(1))
    y, g = _grads(scan_cpu.selective_scan_cpu, tensors, use_d, use_bias, softplus, w)
    y_chk, g_chk = _grads(selective_scan_chunked, tensors, use_d, use_bias, softplus, w)
    t64 = [t.detach().double().requires_grad_() for t in tensors]
    y_ref, g_ref = _grads(
        selective_scan_ref if length < 64 else selective_scan_sequential, t64, use_d, use_bias, softplus, w
    )
    assert y.dtype == torch.float32 and y.shape == (batch, dim, length)
    assert _rel(y.double(), y_ref) < 2e-6
    # two float32 computations, each within 2e-6 of the float64 reference (case 2's steps are negative: its states
    # grow to 1e13 in 17 steps, where the two float32 roundings of exp part the most)
    assert _rel(y, y_chk) < 4e-6
    names = ["u", "delta", "A", "B", "C"] + (["D"] if use_d else []) + (["bias"] if use_bias else [])
    for name, a, c, r in zip(names, g, g_chk, g_ref):
        assert a.shape == r.shape, name
        assert _rel(a.double(), r) < 5e-6, f"d{name} vs float64: {_rel(a.double(), r):.1e}"
        assert _rel(a, c) < 5e-6, f"d{name} vs chunked: {_rel(a, c):.1e}"


def test_long_sequence_stays_close_to_float64(ext):
    u, delta, A, B, C, D, bias = _inputs(1, 32, 3001, 2, 16, dtype=torch.float64, seed=3)
    with torch.no_grad():
        delta -= 3.0
        y64 = selective_scan_sequential(u, delta, A, B, C, D, bias, True)
        y32 = scan_cpu.selective_scan_cpu(*(t.float() for t in (u, delta, A, B, C, D, bias)), True)
    assert _rel(y32.double(), y64) < 1e-5


def test_exp_and_backward_save_no_per_position_states(ext):
    x = torch.linspace(-87.0, 88.0, 200001)
    e = ext.exp_fast(x).double()
    assert ((e - torch.exp(x.double())).abs() / torch.exp(x.double())).max() < 3e-7
    # the inference forward's 2^x: as accurate on x <= 0 down to -126 (the smallest normal float), across every
    # integer (where x - floor(x) wraps), then 0 (denormal results flushed) and no NaN beyond
    x2 = torch.cat([torch.linspace(-126.0, 0.0, 200001), torch.arange(-126.0, 1.0), torch.arange(-125.0, 1.0) - 1e-5])
    e2 = ext.exp2_fast(x2).double()
    assert ((e2 - torch.exp2(x2.double())).abs() / torch.exp2(x2.double())).max() < 3e-7
    tail = ext.exp2_fast(torch.tensor([-126.5, -140.0, -149.5, -200.0, -1e4, -1e30, float("-inf")]))
    assert torch.equal(tail, torch.zeros(7))
    batch, dim, length, n = 2, 32, 640, 16
    u, delta, A, B, C, D, bias = _inputs(batch, dim, length, 2, n)
    y = scan_cpu.selective_scan_cpu(u, delta, A, B, C, D, bias, True)
    node = y.grad_fn  # the tofdenoise::selective_scan operator's autograd node
    saved = [t.numel() for t in node.saved_tensors]
    states = batch * dim * n * length  # one (batch, dim, N, L) tensor
    # inputs (u, delta, A, B, C, D, bias) and the chunk checkpoints (states / CHUNK): nothing per position and state
    assert len(saved) == 8 and saved[-1] == states // scan_cpu.CHUNK
    assert max(saved) <= states / 16 and sum(saved) < states / 2


def test_dtype_routes_and_backend_names(ext):
    u, delta, A, B, C, D, bias = _inputs(1, 8, 40, 2, 4, dtype=torch.float64)
    assert resolve_scan_backend("auto", u.float()) == "cpu"
    assert resolve_scan_backend("cpu", u.float()) == "cpu"
    assert resolve_scan_backend("cpu", u) == "torch"  # float64: the chunked scan keeps float64 precision
    assert resolve_scan_backend("auto", u) == "torch"
    assert resolve_scan_backend("torch", u.float()) == "torch"
    assert available_scan_backends("cpu") == ["cpu", "torch"]
    with pytest.raises(ValueError, match="unknown backend"):
        resolve_scan_backend("numba", u)
    with torch.no_grad():
        y64 = selective_scan(u, delta, A, B, C, D, bias, True, backend="cpu")
        assert y64.dtype == torch.float64
        assert _rel(y64, selective_scan_chunked(u, delta, A, B, C, D, bias, True)) < 1e-12
        bf = [t.to(torch.bfloat16) for t in (u, delta, A, B, C, D, bias)]
        ybf = selective_scan(*bf, True, backend="cpu")  # computed in float32, returned in bf16
        assert ybf.dtype == torch.bfloat16
        want = selective_scan_chunked(*(t.float() for t in bf), True)
        assert _rel(ybf.float(), want) < 1e-2


@pytest.fixture
def fresh_loader():
    """Clear the build/availability caches around a test (they are per process)."""
    scan_cpu.load_extension.cache_clear()
    scan_cpu.cpu_kernel_available.cache_clear()
    yield
    scan_cpu.load_extension.cache_clear()
    scan_cpu.cpu_kernel_available.cache_clear()


def test_failed_build_falls_back_with_one_warning(fresh_loader, monkeypatch):
    from torch.utils import cpp_extension

    calls = []

    def broken_load(*args, **kwargs):
        calls.append(kwargs.get("name"))
        raise RuntimeError("Error building extension: c++: command not found")

    monkeypatch.setattr(cpp_extension, "load", broken_load)
    u, delta, A, B, C, D, bias = _inputs(1, 8, 30, 2, 4)
    with pytest.warns(RuntimeWarning, match="could not be built.*command not found"):
        assert not scan_cpu.cpu_kernel_available()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no second warning, no second build attempt
        assert available_scan_backends("cpu") == ["torch"]
        assert resolve_scan_backend("auto", u) == "torch"
        assert resolve_scan_backend("cpu", u) == "torch"
        y = selective_scan(u, delta, A, B, C, D, bias, True, backend="cpu")
        block = SS2D(8, d_state=4)
        x = torch.randn(1, 5, 6, 8)
        assert not block._spatial_scan(x)
        assert block(x).shape == x.shape
    assert len(calls) == 1
    torch.testing.assert_close(y, selective_scan_chunked(u, delta, A, B, C, D, bias, True))
    with pytest.raises(RuntimeError, match="not available"):
        scan_cpu.ss2d_scan_cpu(x, x, A, B, C, D, bias, 5, 6)


def test_environment_switch_skips_the_build(fresh_loader, monkeypatch):
    from torch.utils import cpp_extension

    monkeypatch.setenv(scan_cpu.ENV_SWITCH, "0")
    monkeypatch.setattr(cpp_extension, "load", lambda *a, **k: pytest.fail("must not build"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not scan_cpu.cpu_kernel_available()


def test_explicit_cpu_backend_switched_off_warns_once_naming_torch(fresh_loader, monkeypatch):
    """One dispatcher (scan.dispatch.resolve_scan_backend) for selective_scan and SS2D: an explicit "cpu" that
    cannot run says once what runs instead; "auto" chooses silently; an unknown name is an error in SS2D too."""
    from tofdenoise.models.scan import dispatch

    monkeypatch.setattr(dispatch, "_warned", set())
    monkeypatch.setenv(scan_cpu.ENV_SWITCH, "0")
    u = torch.randn(1, 4, 9)
    with pytest.warns(RuntimeWarning, match="switched off.*using 'torch'"):
        assert resolve_scan_backend("cpu", u) == "torch"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert resolve_scan_backend("cpu", u) == "torch"
        assert resolve_scan_backend("auto", u) == "torch"
        assert SS2D(8, d_state=4, scan_backend="cpu")._spatial_scan(torch.randn(1, 5, 6, 8)) is None
    with pytest.raises(ValueError, match="unknown backend"):
        SS2D(8, d_state=4, scan_backend="numba")(torch.randn(1, 5, 6, 8))


def _ss2d_run(block, x, spatial: bool):
    block.zero_grad(set_to_none=True)
    x = x.detach().requires_grad_()
    original = block._spatial_scan
    block._spatial_scan = lambda t: spatial and original(t)
    try:
        assert original(x) or not spatial
        y = block(x)
    finally:
        block._spatial_scan = original
    w = torch.linspace(-1.0, 1.0, y.numel()).view_as(y)
    (y * w).sum().backward()
    return y.detach(), x.grad, {k: p.grad.clone() for k, p in block.named_parameters()}


@pytest.mark.parametrize(
    "batch,dim,h,w",
    [
        (2, 20, 7, 9),
        (2, 16, 8, 8),
        (2, 24, 1, 5),
        (1, 20, 13, 11),  # batch 1, H != W, 143 positions (3 chunks, the last partial), 40 channels
        (1, 8, 9, 16),  # batch 1, 144 positions, 16 channels: one full lane block
    ],
)
def test_ss2d_direction_reading_equals_cross_scan_route(ext, batch, dim, h, w):
    torch.manual_seed(0)
    block = SS2D(dim, d_state=16 if dim != 24 else 6)
    with torch.no_grad():  # move the parameters off their symmetric initial values
        for p in block.parameters():
            p.add_(0.1 * torch.randn_like(p))
    x = torch.randn(batch, h, w, dim)
    y0, gx0, g0 = _ss2d_run(block, x, spatial=False)
    y1, gx1, g1 = _ss2d_run(block, x, spatial=True)
    assert _rel(y1, y0) < 2e-6
    assert _rel(gx1, gx0) < 2e-6
    for name in g0:
        assert _rel(g1[name], g0[name]) < 5e-6, name


def test_kernel_tasks_run_on_torchs_threads(ext):
    """The build runs at::parallel_for in parallel: with 2 torch threads, tasks land on 2 threads (without
    -fopenmp the OpenMP pragma is ignored and every task runs on the calling thread)."""
    old = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert ext.threads_used(8) == 2
        torch.set_num_threads(1)
        assert ext.threads_used(8) == 1
    finally:
        torch.set_num_threads(old)


def test_roofline_loop_runs(ext, monkeypatch):
    """The roofline of benchmarks/bench_scan_cpu.py (benchmark-only code) runs the kernel's own loop."""
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[3] / "benchmarks"))
    import bench_scan_cpu

    rate, seconds = bench_scan_cpu.roofline_updates_per_s(seconds=0.05)
    assert rate > 1e7 and seconds > 0


def test_threads_give_bitwise_identical_results(ext):
    """Tasks are handed out dynamically to torch's threads; each task's arithmetic is fixed, so 1 and 3
    threads give bit-identical outputs and gradients."""
    tensors = _inputs(3, 48, 97, 3, 16, seed=5)
    w = torch.randn(3, 48, 97, generator=torch.Generator().manual_seed(6))
    threads = torch.get_num_threads()
    out = []
    try:
        for n in (1, 3):
            torch.set_num_threads(n)
            out.append(_grads(scan_cpu.selective_scan_cpu, tensors, True, True, True, w))
    finally:
        torch.set_num_threads(threads)
    (y1, g1), (y3, g3) = out
    assert torch.equal(y1, y3)
    for a, b in zip(g1, g3):
        assert torch.equal(a, b)


def test_ninja_of_the_venv_is_found_when_the_venv_is_not_activated(monkeypatch, tmp_path):
    """`.venv/bin/python -m pytest` on a machine without a system ninja: the ninja wheel's binary sits next to
    the interpreter, and cpp_extension looks for it on PATH."""
    import sys as _sys

    fake_bin = tmp_path / "bin"
    fake_bin.mkdir()
    (fake_bin / "ninja").write_text("#!/bin/sh\necho 1.11.1\n")
    (fake_bin / "ninja").chmod(0o755)
    monkeypatch.setattr(_sys, "executable", str(fake_bin / "python"))
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    scan_cpu._ninja_on_path()
    assert shutil.which("ninja") == str(fake_bin / "ninja")


def test_the_kernel_builds_from_a_copy_shared_by_every_checkout(tmp_path, monkeypatch):
    """ninja rebuilds when the source path changes: the build reads a copy outside the checkout, named by the
    source's hash, written once and rewritten only if it no longer matches."""
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    name = scan_cpu._build_name()
    copy = scan_cpu.stable_source(name)
    assert copy == tmp_path / "tofdenoise_sources" / f"{name}.cpp"
    assert copy.read_bytes() == scan_cpu.SOURCE.read_bytes()
    stamp = copy.stat().st_mtime_ns
    assert scan_cpu.stable_source(name) == copy and copy.stat().st_mtime_ns == stamp  # not rewritten
    copy.write_text("// damaged")
    assert scan_cpu.stable_source(name).read_bytes() == scan_cpu.SOURCE.read_bytes()


def test_a_stale_build_lock_is_removed_and_a_fresh_one_is_waited_for(tmp_path):
    """torch waits without limit on ``<build dir>/lock``; a lock older than STALE_LOCK_S was left by a killed build."""
    lock = tmp_path / "lock"
    assert scan_cpu.clear_stale_build_lock(tmp_path) is False  # no lock: nothing to say
    lock.write_text("")
    with pytest.warns(RuntimeWarning, match=f"another process is building .*{lock}"):
        assert scan_cpu.clear_stale_build_lock(tmp_path) is False
    assert lock.exists()
    old = lock.stat().st_mtime - scan_cpu.STALE_LOCK_S - 5
    os.utime(lock, (old, old))
    with pytest.warns(RuntimeWarning, match=f"removed a stale build lock .*{lock}.*killed"):
        assert scan_cpu.clear_stale_build_lock(tmp_path) is True
    assert not lock.exists()


@pytest.mark.parametrize("b,h,w,dg,n", [(1, 7, 9, 20, 16), (2, 5, 13, 16, 16), (1, 1, 130, 24, 6), (3, 11, 6, 40, 16)])
def test_inference_forward_keeps_no_checkpoints_and_gives_the_same_output(ext, b, h, w, dg, n):
    """chunk 0 (no input needs a gradient): the kernel writes no checkpoints and returns an empty ck, with an output
    equal to the checkpointing forward's -- bit for bit where the build has no AVX-512, to rounding where it has
    (the inference forward's softplus without a division, equally close to the float64 reference); SS2D's route
    passes 0 under no_grad. Odd, non-square sizes, batch 1 and L not a multiple of CHUNK."""
    g = torch.Generator().manual_seed(11)
    length = h * w
    x = torch.randn(b, length, dg, generator=g)
    dts = 0.5 * torch.randn(b, length, 4 * dg, generator=g) - 2.0
    x_dbl = torch.randn(b, length, 4, 3 + 2 * n, generator=g)
    A = -torch.exp(0.3 * torch.randn(4 * dg, n, generator=g))
    D, bias = torch.randn(4 * dg, generator=g), 0.1 * torch.randn(4 * dg, generator=g)
    args = (x, dts, A, x_dbl[..., 3 : 3 + n], x_dbl[..., 3 + n :], D, bias, True, True, h, w)
    y_ck, ck = ext.scan_fwd(*args, scan_cpu.CHUNK)
    y_inf, ck_inf = ext.scan_fwd(*args, 0)
    assert ck.numel() > 0 and ck_inf.numel() == 0
    if ext.inference_exp2:
        ref = ss2d_scan_reference(
            *(t.double() for t in (x, dts, A, x_dbl[..., 3 : 3 + n], x_dbl[..., 3 + n :], D, bias)), h, w
        )
        assert _rel(y_inf.double(), ref) < 2e-6 and _rel(y_ck.double(), ref) < 2e-6
        torch.testing.assert_close(y_inf, y_ck, rtol=1e-5, atol=1e-5)
    else:
        assert torch.equal(y_inf, y_ck)
    with torch.no_grad():
        y_route = scan_cpu.ss2d_scan_cpu(x, dts, A, x_dbl[..., 3 : 3 + n], x_dbl[..., 3 + n :], D, bias, h, w)
    assert torch.equal(y_route, y_inf)
    with pytest.raises(RuntimeError, match="checkpoints"):
        ext.scan_bwd(*args, 0, ck_inf, torch.ones_like(y_ck))


@pytest.mark.parametrize("b,dg", [(1, 40), (1, 80), (2, 80)])
def test_forward_split_into_parts_by_thread_count_is_bitwise_the_same(ext, b, dg):
    """The forward walks a range of lane blocks together chunk by chunk, as many ranges as keep the threads busy
    (ceil(threads / batch)): 1-4 threads split 3 or 5 blocks (the last partial at 40 channels) into 1, 2 or 3
    ranges. Output and checkpoints are the same bit for bit, and equal the reference scan's output."""
    g = torch.Generator().manual_seed(12)
    h, w, n = 9, 23, 16  # L = 207: 4 chunks, the last partial
    x = torch.randn(b, h * w, dg, generator=g)
    dts = 0.5 * torch.randn(b, h * w, 4 * dg, generator=g) - 2.0
    x_dbl = torch.randn(b, h * w, 4, 3 + 2 * n, generator=g)
    A = -torch.exp(0.3 * torch.randn(4 * dg, n, generator=g))
    D, bias = torch.randn(4 * dg, generator=g), 0.1 * torch.randn(4 * dg, generator=g)
    args = (x, dts, A, x_dbl[..., 3 : 3 + n], x_dbl[..., 3 + n :], D, bias, True, True, h, w, scan_cpu.CHUNK)
    threads = torch.get_num_threads()
    runs = []
    try:
        for t in (1, 2, 3, 4):
            torch.set_num_threads(t)
            runs.append(ext.scan_fwd(*args))
    finally:
        torch.set_num_threads(threads)
    for y, ck in runs[1:]:
        assert torch.equal(y, runs[0][0]) and torch.equal(ck, runs[0][1])
    ref = ss2d_scan_reference(x, dts, A, x_dbl[..., 3 : 3 + n], x_dbl[..., 3 + n :], D, bias, h, w)
    assert _rel(runs[0][0], ref) < 2e-6


@pytest.mark.parametrize(
    "b,h,w,dg,n,r",
    [(1, 7, 9, 20, 16, 2), (2, 5, 13, 16, 16, 1), (1, 1, 130, 24, 6, 3), (3, 11, 6, 40, 16, 16), (1, 4, 5, 8, 4, 64)],
)
def test_fused_dt_projection_equals_the_projected_steps(ext, b, h, w, dg, n, r):
    """ss2d_forward_lowrank projects the low-rank steps inside the kernel: its output equals the forward on the
    steps projected beforehand (float64 products, then rounded), at odd sizes, a partial lane block (20, 40
    channels), a runtime d_state (6, 4), ranks 1 to the kernel's bound, and dt_low as the strided slice of x_proj's
    output that SS2D hands over."""
    g = torch.Generator().manual_seed(13)
    length = h * w
    x = torch.randn(b, length, dg, generator=g)
    x_dbl = torch.randn(b, length, 4, r + 2 * n, generator=g)
    dt_low, B, C = x_dbl[..., :r], x_dbl[..., r : r + n], x_dbl[..., r + n :]
    weight = torch.randn(4, dg, r, generator=g) / r**0.5
    A = -torch.exp(0.3 * torch.randn(4 * dg, n, generator=g))
    D, bias = torch.randn(4 * dg, generator=g), 0.1 * torch.randn(4 * dg, generator=g) - 1.0
    dts = torch.einsum("blkr,kdr->blkd", dt_low.double(), weight.double()).float().reshape(b, length, 4 * dg)
    want, _ = scan_cpu.ss2d_forward(x, dts, A, B, C, D, bias, h, w, checkpoints=False)
    got = scan_cpu.ss2d_forward_lowrank(x, dt_low, weight, A, B, C, D, bias, h, w)
    assert got.shape == (b, length, dg)
    torch.testing.assert_close(got, want, rtol=2e-5, atol=2e-5)
    # a wrong weight shows: the projection is really computed from dt_low and the weight
    off = scan_cpu.ss2d_forward_lowrank(x, dt_low, weight.flip(1), A, B, C, D, bias, h, w)
    assert (off - want).abs().max() > 1e-2


def test_fused_dt_projection_refuses_bad_shapes(ext):
    b, h, w, dg, n, r = 1, 3, 4, 8, 4, 2
    x = torch.randn(b, h * w, dg)
    x_dbl = torch.randn(b, h * w, 4, r + 2 * n)
    A, D, bias = -torch.ones(4 * dg, n), torch.ones(4 * dg), torch.zeros(4 * dg)
    B, C = x_dbl[..., r : r + n], x_dbl[..., r + n :]
    with pytest.raises(RuntimeError, match="dt_weight"):
        scan_cpu.ss2d_forward_lowrank(x, x_dbl[..., :r], torch.randn(4, dg, r + 1), A, B, C, D, bias, h, w)
    with pytest.raises(RuntimeError, match="dt_rank"):
        big = torch.randn(b, h * w, 4, scan_cpu.LOWRANK_MAX_RANK + 1)
        scan_cpu.ss2d_forward_lowrank(x, big, torch.randn(4, dg, big.size(-1)), A, B, C, D, bias, h, w)
    with pytest.raises(RuntimeError, match="dt_low"):
        scan_cpu.ss2d_forward_lowrank(x, x_dbl[:, 1:, :, :r], torch.randn(4, dg, r), A, B, C, D, bias, h, w)


@pytest.mark.parametrize("dim", [12, 32, 256])
def test_ss2d_inference_fuses_the_dt_projection_and_training_does_not(ext, dim, monkeypatch):
    """SS2D on the native kernel: under no_grad the kernel projects the steps itself (one call of the fused
    forward per block), with a gradient recorded the projected steps go through the operator (no fused call);
    the two outputs agree to rounding (bit for bit on the machines measured: the products are the same)."""
    import tofdenoise.models.ss2d as ss2d_mod

    calls, gates = [], []
    real = ss2d_mod.ss2d_forward_lowrank
    monkeypatch.setattr(ss2d_mod, "ss2d_forward_lowrank", lambda *a: calls.append(1) or real(*a))
    real_gate = ss2d_mod.ss2d_out_gate
    monkeypatch.setattr(ss2d_mod, "ss2d_out_gate", lambda *a: gates.append(1) or real_gate(*a))
    torch.manual_seed(dim)
    block = SS2D(dim, scan_backend="cpu")
    with torch.no_grad():
        block.dt_projs_weight.normal_()  # steps far from the bias alone
    x = torch.randn(2, 5, 7, dim)
    with torch.no_grad():
        y_inference = block(x)
    assert len(calls) == len(gates) == 1
    y_training = block(x.clone().requires_grad_())
    assert len(calls) == len(gates) == 1
    torch.testing.assert_close(y_inference, y_training.detach(), rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize("rows,d,row_stride", [(1, 64, 128), (37, 20, 40), (300, 256, 256), (5, 3, 7)])
def test_ss2d_out_gate_is_layer_norm_times_silu_in_place(ext, rows, d, row_stride):
    """ss2d_out_gate(y, z, w, b, eps) = layer_norm(y) * silu(z) in y's memory, for partial lane blocks and z as the
    strided half of in_proj's output; large |z| and a constant row (variance 0) stay finite."""
    g = torch.Generator().manual_seed(rows)
    y = 3.0 * torch.randn(rows, d, generator=g) + 1.0
    y[0] = 2.5  # a row without variance
    zz = 4.0 * torch.randn(rows, row_stride, generator=g)
    zz[-1, :d] = torch.linspace(-120.0, 120.0, d)
    z = zz[:, :d]
    w, b = torch.randn(d, generator=g), torch.randn(d, generator=g)
    want = F.layer_norm(y, (d,), w, b, 1e-5) * F.silu(z)
    out = scan_cpu.ss2d_out_gate(y, z, w, b, 1e-5)
    assert out.data_ptr() == y.data_ptr()
    torch.testing.assert_close(out, want, rtol=2e-5, atol=2e-5)
    with pytest.raises(RuntimeError, match="ss2d_out_gate: z"):
        scan_cpu.ss2d_out_gate(
            torch.randn(rows, d), z.t().contiguous().t() if d > 1 and rows > 1 else z[:, :0], w, b, 1e-5
        )
    with pytest.raises(RuntimeError, match="ss2d_out_gate: weight"):
        scan_cpu.ss2d_out_gate(torch.randn(rows, d), z, w[:-1], b, 1e-5)
