"""Selective scan: chunked and sequential implementations against a plain sequential reference."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models import available_scan_backends, selective_scan
from tofdenoise.models.scan import selective_scan_chunked, selective_scan_ref, selective_scan_sequential


def _inputs(batch, dim, length, groups, n, dtype=torch.float32, three_d=False, seed=0):
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(batch, dim, length, generator=g, dtype=dtype)
    delta = 0.5 * torch.randn(batch, dim, length, generator=g, dtype=dtype)
    A = -torch.exp(0.5 * torch.randn(dim, n, generator=g, dtype=dtype))
    shape = (batch, n, length) if three_d else (batch, groups, n, length)
    B = torch.randn(*shape, generator=g, dtype=dtype)
    C = torch.randn(*shape, generator=g, dtype=dtype)
    D = torch.randn(dim, generator=g, dtype=dtype)
    bias = torch.randn(dim, generator=g, dtype=dtype)
    return [t.requires_grad_() for t in (u, delta, A, B, C, D, bias)]


def _rel(a, b):
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()


def _compare(fn, tensors, use_d, use_bias, softplus, tol):
    u, delta, A, B, C, D, bias = tensors
    D_, bias_ = (D if use_d else None), (bias if use_bias else None)
    positive = not softplus and not use_bias  # without softplus, use positive steps as in Mamba

    def d_in():
        return delta.abs() if positive else delta

    inputs = [u, delta, A, B, C] + ([D] if use_d else []) + ([bias] if use_bias else [])
    y_ref = selective_scan_ref(u, d_in(), A, B, C, D_, bias_, softplus)
    y = fn(u, d_in(), A, B, C, D_, bias_, softplus)
    assert y.shape == u.shape
    assert _rel(y, y_ref) < tol
    w = torch.randn_like(y_ref)
    g_ref = torch.autograd.grad((y_ref * w).sum(), inputs)
    g = torch.autograd.grad((y * w).sum(), inputs)
    for name, a, b in zip("u delta A B C D bias".split(), g, g_ref):
        assert a.shape == b.shape, name
        assert _rel(a, b) < tol, f"gradient of {name}: relative error {_rel(a, b):.2e}"


CASES = [
    # batch, dim, L, groups, N, D, delta_bias, softplus
    (2, 6, 23, 1, 4, True, True, True),
    (1, 6, 23, 3, 4, True, False, True),
    (2, 8, 17, 2, 3, False, True, False),
    (1, 4, 31, 4, 5, False, False, False),
]


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("chunk,group", [(5, 200), (4, 1 << 22), (64, 1 << 22)])
def test_chunked_matches_reference(case, chunk, group):
    b, dim, L, G, n, use_d, use_bias, softplus = case
    tensors = _inputs(b, dim, L, G, n)
    fn = lambda *a: selective_scan_chunked(*a, chunk_size=chunk, group_elems=group)  # noqa: E731
    _compare(fn, tensors, use_d, use_bias, softplus, tol=1e-5)


@pytest.mark.parametrize("case", CASES[:2])
def test_sequential_baseline_matches_reference(case):
    b, dim, L, G, n, use_d, use_bias, softplus = case
    _compare(selective_scan_sequential, _inputs(b, dim, L, G, n), use_d, use_bias, softplus, tol=1e-5)


def test_float64_is_tight_and_three_d_bc_accepted():
    tensors = _inputs(1, 4, 19, 1, 3, dtype=torch.float64, three_d=True)
    fn = lambda *a: selective_scan_chunked(*a, chunk_size=4, group_elems=50)  # noqa: E731
    _compare(fn, tensors, True, True, True, tol=1e-12)


def test_chunk_grouping_does_not_change_gradients():
    u, delta, A, B, C, D, bias = _inputs(1, 8, 50, 2, 4)
    outs = []
    for group in (1, 300, 1 << 30):
        y = selective_scan_chunked(u, delta, A, B, C, D, bias, True, chunk_size=7, group_elems=group)
        outs.append(torch.autograd.grad(y.square().sum(), (u, delta, A, B, C)))
    for g in outs[1:]:
        for a, b in zip(g, outs[0]):
            assert _rel(a, b) < 1e-5


def test_long_sequence_is_stable_against_float64():
    """L = 3000 with strong decays and long memory mixed: float32 chunked vs float64 sequential."""
    g = torch.Generator().manual_seed(3)
    dim, n, L = 4, 16, 3000
    u = torch.randn(1, dim, L, generator=g, dtype=torch.float64)
    delta = torch.randn(1, dim, L, generator=g, dtype=torch.float64) * 2 - 3
    A = -torch.arange(1, n + 1, dtype=torch.float64).repeat(dim, 1)
    B = torch.randn(1, 1, n, L, generator=g, dtype=torch.float64)
    C = torch.randn(1, 1, n, L, generator=g, dtype=torch.float64)
    y64 = selective_scan_sequential(u, delta, A, B, C, None, None, True)
    y32 = selective_scan_chunked(u.float(), delta.float(), A.float(), B.float(), C.float(), None, None, True)
    assert torch.isfinite(y32).all()
    assert _rel(y32.double(), y64) < 1e-5


def test_dispatch_and_errors():
    u, delta, A, B, C, D, bias = _inputs(1, 4, 9, 2, 3)
    y = selective_scan(u, delta, A, B, C, D, bias, True)
    torch.testing.assert_close(y, selective_scan_ref(u, delta, A, B, C, D, bias, True), rtol=1e-5, atol=1e-6)
    assert available_scan_backends("cpu")[-1] == "torch"
    assert set(available_scan_backends("cpu")) <= {"cpu", "torch"}
    with pytest.raises(ValueError, match="unknown backend"):
        selective_scan(u, delta, A, B, C, backend="nope")
    with pytest.raises(ValueError, match="needs CUDA"):
        selective_scan(u, delta, A, B, C, backend="triton")
    with pytest.raises(ValueError, match="divisible by groups"):
        selective_scan(u, delta, A, B[:, :1].expand(1, 3, 3, 9), C[:, :1].expand(1, 3, 3, 9))
    with pytest.raises(ValueError, match="A must be"):
        selective_scan(u, delta, A[:2], B, C)
    with pytest.raises(ValueError, match="delta_bias must be"):
        selective_scan(u, delta, A, B, C, delta_bias=bias[:2])


@pytest.mark.gpu
@pytest.mark.parametrize("backend", ["torch", "triton", "mamba_ssm"])
def test_cuda_backends_match_cpu(backend):
    if backend not in available_scan_backends("cuda"):
        pytest.skip(f"{backend} not importable")
    tensors = _inputs(2, 64, 700, 4, 16)
    u, delta, A, B, C, D, bias = (t.detach().cuda().requires_grad_() for t in tensors)
    y = selective_scan(u, delta, A, B, C, D, bias, True, backend=backend)
    y_cpu = selective_scan_chunked(*(t.detach().cpu() for t in (u, delta, A, B, C, D, bias)), True)
    assert _rel(y.detach().cpu(), y_cpu) < 1e-4
    grads = torch.autograd.grad(y.square().sum(), (u, delta, A, B, C, D, bias))
    cpu_in = [t.detach().cpu().requires_grad_() for t in (u, delta, A, B, C, D, bias)]
    y_c = selective_scan_chunked(*cpu_in, True)
    grads_cpu = torch.autograd.grad(y_c.square().sum(), cpu_in)
    for a, b in zip(grads, grads_cpu):
        assert _rel(a.cpu(), b) < 1e-3


@pytest.mark.gpu
def test_triton_reads_bf16_inputs_and_fuses_bias_softplus_and_d():
    """bf16 u, delta, B, C (what SS2D passes under autocast) are read as they are; the result equals the
    float32 PyTorch scan of the same (bf16-rounded) values up to the bf16 rounding of y / du / ddelta."""
    if "triton" not in available_scan_backends("cuda"):
        pytest.skip("triton not importable")
    tensors = [t.detach() for t in _inputs(2, 64, 333, 4, 16)]
    bf = [t.cuda().to(torch.bfloat16) if i in (0, 1, 3, 4) else t.cuda() for i, t in enumerate(tensors)]
    ins = [t.requires_grad_() for t in bf]
    y = selective_scan(*ins, True, backend="triton")
    assert y.dtype == torch.bfloat16
    ref_in = [t.detach().float().requires_grad_() for t in bf]
    y_ref = selective_scan_chunked(*ref_in, True)
    assert _rel(y.float(), y_ref) < 1e-2
    dy = torch.randn(y.shape, device="cuda", generator=torch.Generator(device="cuda").manual_seed(0))
    grads = torch.autograd.grad(y, ins, dy.to(torch.bfloat16))
    grads_ref = torch.autograd.grad(y_ref, ref_in, dy.to(torch.bfloat16).float())
    for i, (a, b) in enumerate(zip(grads, grads_ref)):
        assert a.dtype == ins[i].dtype
        assert _rel(a.float(), b) < (2e-2 if a.dtype == torch.bfloat16 else 1e-3), i


def test_scan_runs_in_float32_under_autocast():
    u, delta, A, B, C, D, bias = (t.detach() for t in _inputs(1, 8, 40, 2, 4))
    ref = selective_scan_ref(u, delta, A, B, C, D, bias, True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = selective_scan(u, delta, A, B, C, D, bias, True)
    assert y.dtype == torch.float32
    assert _rel(y, ref) < 1e-5


def _saved_elements(fn, *args) -> int:
    """Elements of all tensors autograd keeps for the backward of ``fn(*args)``."""
    total = []

    def pack(t):
        total.append(t.numel())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        fn(*args).sum()
    return sum(total)


def test_chunked_scan_never_saves_per_position_states():
    """The chunked scan keeps inputs plus chunk-entry states (L*dim*N/T); the sequential one all states."""
    b, dim, L, G, n = 1, 64, 512, 1, 16
    u, delta, A, B, C, D, bias = _inputs(b, dim, L, G, n)
    states = b * dim * L * n
    inputs = 2 * b * dim * L + 2 * b * G * n * L + dim * n
    chunked = _saved_elements(lambda *a: selective_scan_chunked(*a, chunk_size=64), u, delta, A, B, C, D, bias)
    sequential = _saved_elements(selective_scan_sequential, u, delta, A, B, C, D, bias)
    assert sequential >= 3 * states
    assert chunked <= 4 * inputs + states // 64 + 2 * dim * n
    assert chunked < states / 2
