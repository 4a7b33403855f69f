"""Triton selective-scan kernels (scan_triton): the plain (batch, dim, L) route and the SS2D route that reads the
four scan directions in place, against the PyTorch scans (forward and every gradient). Without a GPU the kernels
run in Triton's interpreter on CPU tensors (tests/conftest.py sets TRITON_INTERPRET=1), so the same kernel code
is checked on every machine; the `gpu` tests compile them on the device."""

from __future__ import annotations

import pytest
import torch

triton = pytest.importorskip("triton", reason="Triton is not installed (make venv installs it next to a CPU torch)")

from tofdenoise.models.scan import selective_scan_chunked, ss2d_scan_reference  # noqa: E402
from tofdenoise.models.scan import triton as st  # noqa: E402
from tofdenoise.models.ss2d import SS2D  # noqa: E402

from .test_scan import _inputs, _rel  # noqa: E402

needs_kernels = pytest.mark.skipif(
    not (st.interpreting() or st.triton_available()),
    reason="neither a CUDA device nor Triton's interpreter (TRITON_INTERPRET=1)",
)
DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def _grads(fn, tensors, weight):
    ins = [t.detach().to(DEVICE).requires_grad_() for t in tensors]
    y = fn(*ins)
    return y, torch.autograd.grad((y * weight.to(y)).sum(), ins)


@needs_kernels
@pytest.mark.parametrize(
    "batch,dim,length,groups,n,use_d,use_bias,softplus",
    [
        (2, 8, 70, 2, 5, True, True, True),  # 3 chunks (the last partial), N = 5 padded to 8 states
        (1, 6, 33, 3, 3, False, False, False),  # plain steps, no D, no bias; 2 channels per group (BLOCK_D 2)
        (1, 4, 31, 1, 16, True, False, True),  # one chunk, 3-D B/C (no group axis)
    ],
)
def test_plain_route_matches_the_chunked_scan(batch, dim, length, groups, n, use_d, use_bias, softplus):
    u, delta, A, B, C, D, bias = (t.detach() for t in _inputs(batch, dim, length, groups, n))
    if groups == 1:
        B, C = B[:, 0], C[:, 0]
    if not (softplus or use_bias):
        delta = delta.abs()  # positive steps without softplus
    tensors = [u, delta, A, B, C] + ([D] if use_d else []) + ([bias] if use_bias else [])

    def call(fn):
        def run(u, delta, A, B, C, *rest):
            rest = list(rest)
            d = rest.pop(0) if use_d else None
            b = rest.pop(0) if use_bias else None
            return fn(u, delta, A, B, C, d, b, softplus)

        return run

    weight = torch.linspace(-1.0, 1.0, u.numel()).view_as(u)
    y, grads = _grads(call(st.selective_scan_triton), tensors, weight)
    y_ref, grads_ref = _grads(call(selective_scan_chunked), tensors, weight)
    assert y.dtype == u.dtype
    assert _rel(y.detach(), y_ref.detach()) < 1e-5
    for i, (a, b) in enumerate(zip(grads, grads_ref)):
        assert a.shape == b.shape
        assert _rel(a, b) < 1e-4, i


def _ss2d_inputs(batch, h, w, di, n, rank=3, seed=0):
    """SS2D's scan inputs as SS2D passes them: B and C are strided views into one x_proj output."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, h * w, di, generator=g)
    delta = 0.5 * torch.randn(batch, h * w, 4 * di, generator=g)
    A = -torch.exp(0.5 * torch.randn(4 * di, n, generator=g))
    x_dbl = torch.randn(batch, h * w, 4, rank + 2 * n, generator=g)
    D, bias = torch.randn(4 * di, generator=g), torch.randn(4 * di, generator=g)
    return x, delta, A, x_dbl, D, bias


def _ss2d_grads(fn, x, delta, A, x_dbl, D, bias, h, w, n, rank=3):
    ins = [t.detach().to(DEVICE).requires_grad_() for t in (x, delta, A, x_dbl)]
    opt = [None if t is None else t.detach().to(DEVICE).requires_grad_() for t in (D, bias)]
    xd = ins[3]
    y = fn(ins[0], ins[1], ins[2], xd[..., rank : rank + n], xd[..., rank + n :], opt[0], opt[1], h, w)
    weight = torch.linspace(-1.0, 1.0, y.numel(), device=y.device).view_as(y)
    wanted = ins + [t for t in opt if t is not None]
    return y, torch.autograd.grad((y * weight).sum(), wanted)


@needs_kernels
@pytest.mark.parametrize(
    "h,w,di,n,use_d_bias",
    [
        (5, 7, 4, 5, True),  # non-square, 35 positions (2 chunks), N not a power of two
        (4, 9, 8, 4, True),  # 36 positions, a full 8-channel block per direction, column-major across rows
        (1, 6, 2, 3, False),  # one row: column-major = row-major; no D, no bias
    ],
)
def test_ss2d_route_reads_the_four_directions_in_place(h, w, di, n, use_d_bias):
    x, delta, A, x_dbl, D, bias = _ss2d_inputs(2, h, w, di, n)
    if not use_d_bias:
        D = bias = None
    y, grads = _ss2d_grads(st.ss2d_scan_triton, x, delta, A, x_dbl, D, bias, h, w, n)
    y_ref, grads_ref = _ss2d_grads(ss2d_scan_reference, x, delta, A, x_dbl, D, bias, h, w, n)
    assert y.shape == (2, h * w, di)
    assert _rel(y.detach(), y_ref.detach()) < 1e-5
    names = ["x", "delta", "A", "x_dbl", "D", "delta_bias"]
    for name, a, b in zip(names, grads, grads_ref):
        assert _rel(a, b) < 1e-4, name


def _assert_split_ss2d_equals_reference(batch, seed):
    """The SS2D route on a 9 x 13 image (117 positions: 4 chunks, the last one partial; the column-major directions
    cross the rows inside a chunk), 4 channels, N = 5, with slow decays (A / 100: a state and an adjoint live on
    across several segments, so what crosses a segment boundary counts): output and every gradient equal the
    reference's."""
    h, w, di, n = 9, 13, 4, 5
    x, delta, A, x_dbl, D, bias = _ss2d_inputs(batch, h, w, di, n, seed=seed)
    A = 0.01 * A
    y, grads = _ss2d_grads(st.ss2d_scan_triton, x, delta, A, x_dbl, D, bias, h, w, n)
    y_ref, grads_ref = _ss2d_grads(ss2d_scan_reference, x, delta, A, x_dbl, D, bias, h, w, n)
    assert _rel(y.detach(), y_ref.detach()) < 1e-5
    for name, a, b in zip(["x", "delta", "A", "x_dbl", "D", "delta_bias"], grads, grads_ref):
        assert _rel(a, b) < 1e-4, name


@needs_kernels
@pytest.mark.parametrize("forward", ["chunked", "sequential"])
# 2 and 100 (unsplit at this length) are slow: 1 and 3 cover the carry over one-chunk and several-chunk segments
@pytest.mark.parametrize(
    "segment_chunks", [1, pytest.param(2, marks=pytest.mark.slow), 3, pytest.param(100, marks=pytest.mark.slow)]
)
def test_ss2d_route_split_into_segments_equals_the_reference(monkeypatch, segment_chunks, forward):
    """The sequence split into segments of 1, 2 or 3 chunks run side by side (a first pass for each segment's end
    state and adjoint, the carry over the segments, a second pass from the true entry values), and unsplit, on the
    chunked and on the sequential forward and first backward pass: every split gives the reference's output and
    gradients."""
    monkeypatch.setattr(st, "SEGMENT_CHUNKS", segment_chunks)
    monkeypatch.setattr(st, "FORWARD", forward)
    monkeypatch.setattr(st, "ADJOINT", forward)
    _assert_split_ss2d_equals_reference(batch=1, seed=2)


@needs_kernels
@pytest.mark.parametrize("fine,coarse", [(1, 3), (2, 2), pytest.param(1, 100, marks=pytest.mark.slow)])
def test_sequential_adjoint_pass_on_a_finer_split_equals_the_reference(monkeypatch, fine, coarse):
    """The backward's first pass walked one step at a time on its own, finer split of the sequence (segments of
    ``fine`` chunks, 4 channels a program) under a backward of ``coarse``-chunk segments (2 channels a program): the
    carry crosses several fine segments per coarse one, and the gradients equal the reference's."""
    monkeypatch.setattr(st, "ADJOINT", "sequential")
    monkeypatch.setattr(st, "FORWARD", "sequential")
    monkeypatch.setattr(st, "SS2D_BLOCK_D_MAX", 2)
    programs_fine = 1 * (4 * 4) // 4
    monkeypatch.setattr(
        st, "segment_chunks", lambda nchunk, programs, device: fine if programs == programs_fine else coarse
    )
    _assert_split_ss2d_equals_reference(batch=1, seed=3)


@needs_kernels
@pytest.mark.parametrize(
    "block_d,segment_chunks,sub,batch",
    [
        (64, 1, 4, 2),
        pytest.param(64, 3, None, 2, marks=pytest.mark.slow),
        pytest.param(64, 100, None, 2, marks=pytest.mark.slow),
        (2, 3, 8, 1),
    ],
)
def test_sequential_backward_equals_the_reference(monkeypatch, segment_chunks, block_d, sub, batch):
    """The SS2D backward walked one step at a time (BACKWARD "sequential": each chunk's states recomputed into
    scratch rows and read back in reverse beside the adjoints) gives the reference's gradients, with and without
    segments; 9 x 13 positions, the last chunk partial, slow decays. With all 4 channels of a direction in one
    program dB and dC are stored; with 2 channels a program, two programs add into them. ``sub``: the chunk
    recomputed 4 or 8 positions at a time (SEQ_BWD_SUB), the last sub-chunks of the partial chunk empty. Batch 2
    where a program holds a direction's channels, batch 1 where two programs share it (the interpreter's time
    grows with the programs: 48 s at batch 2 on the 2-core CI machine)."""
    monkeypatch.setattr(st, "SEQ_BLOCK_D_MAX", block_d)
    monkeypatch.setattr(st, "SEQ_BWD_SUB", sub)
    monkeypatch.setattr(st, "FORWARD", "sequential")
    monkeypatch.setattr(st, "ADJOINT", "sequential")
    monkeypatch.setattr(st, "BACKWARD", "sequential")
    monkeypatch.setattr(st, "SEGMENT_CHUNKS", segment_chunks)
    monkeypatch.setattr(st, "bwd_kernel", None)  # the chunked main pass must not run
    _assert_split_ss2d_equals_reference(batch=batch, seed=4)


@needs_kernels
def test_a_sub_chunk_that_does_not_divide_the_chunk_is_refused(monkeypatch):
    monkeypatch.setattr(st, "FORWARD", "sequential")
    monkeypatch.setattr(st, "ADJOINT", "sequential")
    monkeypatch.setattr(st, "BACKWARD", "sequential")
    monkeypatch.setattr(st, "SEQ_BWD_SUB", 5)
    x, delta, A, x_dbl, D, bias = _ss2d_inputs(1, 3, 4, 4, 2)
    with pytest.raises(ValueError, match="SEQ_BWD_SUB must divide CHUNK"):
        _ss2d_grads(st.ss2d_scan_triton, x, delta, A, x_dbl, D, bias, 3, 4, 2)


@needs_kernels
@pytest.mark.parametrize("forward", ["chunked", "sequential"])
@pytest.mark.parametrize("segment_chunks", [1, 3])
def test_plain_route_split_into_segments_equals_the_chunked_scan(monkeypatch, segment_chunks, forward):
    """The plain route with 7 chunks (the last partial) in segments of 1 and 3 chunks, on either forward."""
    monkeypatch.setattr(st, "SEGMENT_CHUNKS", segment_chunks)
    monkeypatch.setattr(st, "PLAIN_FORWARD", forward)
    monkeypatch.setattr(st, "PLAIN_ADJOINT", forward)
    u, delta, A, B, C, D, bias = (t.detach() for t in _inputs(1, 4, 200, 2, 4))
    A = 0.01 * A  # slow decays: a state (and an adjoint) lives on across several segments
    weight = torch.linspace(-1.0, 1.0, u.numel()).view_as(u)

    def run(fn):
        return _grads(lambda *t: fn(*t, True), [u, delta, A, B, C, D, bias], weight)

    y, grads = run(st.selective_scan_triton)
    y_ref, grads_ref = run(selective_scan_chunked)
    assert _rel(y.detach(), y_ref.detach()) < 1e-5
    for i, (a, b) in enumerate(zip(grads, grads_ref)):
        assert _rel(a, b) < 1e-4, i


def test_segment_split_fills_the_gpu_and_keeps_segments_long():
    """The automatic split: about SEGMENT_PROGRAMS_PER_SM programs per multiprocessor, no segment under
    MIN_SEGMENT_CHUNKS chunks, one segment when the channels alone fill the GPU; the override wins."""
    from unittest import mock

    with (
        mock.patch.object(st, "_multiprocessors", return_value=132),
        mock.patch.object(st, "SEGMENT_CHUNKS", None),
        mock.patch.object(st, "SEGMENT_PROGRAMS_PER_SM", 8),
    ):
        cuda = torch.device("cuda", 0)
        # DVSS level 0 at 320 x 320, batch 4: 4 x 256 / 4 = 256 programs, 3200 chunks -> 5 segments of 640 chunks
        assert st.segment_chunks(3200, 256, cuda) == 640
        assert st.segment_chunks(3200, 8 * 132, cuda) == 3200  # filled already: one segment
        assert st.segment_chunks(10, 1, cuda) == st.MIN_SEGMENT_CHUNKS  # short: segments of the minimum
        assert st.segment_chunks(2, 1, cuda) == 2
    with mock.patch.object(st, "SEGMENT_CHUNKS", 3):
        assert st.segment_chunks(10, 1, torch.device("cuda", 0)) == 3
        assert st.segment_chunks(2, 1, torch.device("cuda", 0)) == 2


@needs_kernels
def test_ss2d_route_reads_bf16_inputs_as_they_are():
    """bf16 x, delta, B, C (SS2D under autocast) are read without conversion copies; the result (bf16) equals
    the float32 reference of the same bf16-rounded values up to bf16 rounding, gradients come back in bf16."""
    h, w, di, n = 4, 6, 4, 4
    x, delta, A, x_dbl, D, bias = _ss2d_inputs(1, h, w, di, n, seed=1)
    x, delta, x_dbl = (t.to(torch.bfloat16) for t in (x, delta, x_dbl))
    y, grads = _ss2d_grads(st.ss2d_scan_triton, x, delta, A, x_dbl, D, bias, h, w, n)
    assert y.dtype == torch.bfloat16
    f32 = [t.float() for t in (x, delta, A, x_dbl)]
    y_ref, grads_ref = _ss2d_grads(ss2d_scan_reference, *f32, D, bias, h, w, n)
    assert _rel(y.detach().float(), y_ref.detach()) < 1e-2
    for i, (a, b) in enumerate(zip(grads, grads_ref)):
        assert a.dtype == (torch.bfloat16 if i in (0, 1, 3) else torch.float32), i
        assert _rel(a.float(), b) < 2e-2, i


@needs_kernels
def test_ss2d_block_on_the_triton_route_equals_the_cross_scan_route():
    """The whole SS2D block (projections, scan, merge, norm, gate) on the Triton route gives the cross_scan
    route's output and every parameter gradient."""
    torch.manual_seed(0)
    block = SS2D(8, d_state=4).to(DEVICE)
    with torch.no_grad():  # move the parameters off their symmetric initial values
        for p in block.parameters():
            p.add_(0.1 * torch.randn_like(p))
    x = torch.randn(2, 5, 6, 8, device=DEVICE)
    runs = []
    for route in ("triton", None):
        block.zero_grad(set_to_none=True)
        block._spatial_scan = lambda t, route=route: route
        xi = x.clone().requires_grad_()
        y = block(xi)
        (y * torch.linspace(-1.0, 1.0, y.numel(), device=DEVICE).view_as(y)).sum().backward()
        runs.append((y.detach(), xi.grad, {k: p.grad.clone() for k, p in block.named_parameters()}))
    (y1, gx1, g1), (y0, gx0, g0) = runs
    assert _rel(y1, y0) < 1e-5
    assert _rel(gx1, gx0) < 1e-4
    for name in g0:
        assert _rel(g1[name], g0[name]) < 1e-4, name


@needs_kernels
def test_self_check_covers_both_routes():
    """The check the auto dispatch runs once per device (plain and SS2D routes) passes; a broken kernel makes it
    raise, so the dispatch falls back to the PyTorch scan."""
    st._verify_case(torch.device(DEVICE))
    original = st.ss2d_scan_triton
    try:
        st.ss2d_scan_triton = lambda *a: 1.01 * original(*a)
        with pytest.raises(RuntimeError, match="disagrees"):
            st._verify_case(torch.device(DEVICE))
    finally:
        st.ss2d_scan_triton = original


def test_ss2d_route_names_bad_shapes():
    x, delta, A, x_dbl, D, bias = (t.to(DEVICE) for t in _ss2d_inputs(1, 3, 4, 2, 3))
    B, C = x_dbl[..., 3:6], x_dbl[..., 6:]
    if not (st.interpreting() or st.triton_available()):
        with pytest.raises(RuntimeError, match="not available"):
            st.ss2d_scan_triton(x, delta, A, B, C, D, bias, 3, 4)
        return
    with pytest.raises(ValueError, match="expected height x width = 15"):
        st.ss2d_scan_triton(x, delta, A, B, C, D, bias, 3, 5)
    with pytest.raises(ValueError, match="delta has shape"):
        st.ss2d_scan_triton(x, delta[..., :4], A, B, C, D, bias, 3, 4)


def test_cpu_tensors_outside_the_interpreter_are_refused(monkeypatch):
    monkeypatch.setenv("TRITON_INTERPRET", "0")
    if torch.cuda.is_available():
        pytest.skip("a CUDA machine runs the compiled kernels")
    x, delta, A, x_dbl, D, bias = _ss2d_inputs(1, 3, 4, 2, 3)
    with pytest.raises(RuntimeError, match="not available"):
        st.ss2d_scan_triton(x, delta, A, x_dbl[..., 3:6], x_dbl[..., 6:], D, bias, 3, 4)


def test_kernels_compile_for_the_h100_without_spills():
    """Both routes' kernels compile for sm_90 ahead of time (Triton -> PTX -> ptxas; no GPU needed), which the
    interpreter cannot check; at the default launch setting neither backward spills registers."""
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    code = (
        "import json, sys; sys.path.insert(0, 'benchmarks'); import triton_resources as tr; "
        "from tofdenoise.models.scan import triton as st; "
        "rows = tr.resources(st, 'SS2D', 'bf16', st.NUM_WARPS, st.SS2D_BLOCK_D_MAX) "
        "+ tr.resources(st, 'plain', 'fp32', st.NUM_WARPS, st.BLOCK_D_MAX); print(json.dumps(rows))"
    )
    env = {**os.environ, "TRITON_INTERPRET": "0"}
    out = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = json.loads(out.stdout.strip().splitlines()[-1])
    ss2d = ["seq_fwd_first", "seq_fwd", "seq_adjoint", "seq_bwd"]  # the default routes: sequential on SS2D
    plain = ["seg_fwd", "fwd", "seg_bwd", "bwd"]
    assert [(r["route"], r["kernel"]) for r in rows] == [("SS2D", k) for k in ss2d] + [("plain", k) for k in plain]
    for r in rows:
        assert 0 < r["registers"] <= 255, r
        assert r["spill_store_bytes"] == 0 and r["spill_load_bytes"] == 0, r


@pytest.mark.gpu
def test_ss2d_under_bf16_autocast_takes_the_triton_route():
    """On a GPU, SS2D under bf16 autocast reads its bf16 activations with the fused-layout kernels (no
    cross_scan copies) and agrees with the cross_scan route run in float32."""
    if not st.triton_available() or not st.triton_verified(torch.cuda.current_device()):
        pytest.skip("Triton not verified on this device")
    torch.manual_seed(0)
    block = SS2D(32).cuda()
    x = torch.randn(2, 24, 20, 32, device="cuda")
    assert block._spatial_scan(x) == "triton"
    with torch.autocast("cuda", dtype=torch.bfloat16):
        y = block(x)
    block._spatial_scan = lambda t: None
    y_ref = block(x)
    assert _rel(y.float(), y_ref) < 3e-2
