"""The scan kernels as ``torch.library`` custom operators (tofdenoise.models.scan.ops): ``opcheck`` on the native CPU
kernel and on the Triton kernels (in Triton's interpreter without a GPU), and ``torch.compile`` of a DVSS, forward
and backward, equal to the eager model -- on the CPU after an eager DVSS has run a larger frame in the same process
(the case that crashed when the scan was a ``torch.autograd.Function`` around the native kernel), and on CUDA."""

from __future__ import annotations

import os
import shutil

import pytest
import torch

from tofdenoise.models.common import draw_zero_parameters, execution_distances
from tofdenoise.models.registry import build_backbone
from tofdenoise.models.scan import cpu as scan_cpu
from tofdenoise.models.scan import ops
from tofdenoise.models.scan.common import compile_constant
from tofdenoise.models.scan.reference import selective_scan_chunked, ss2d_scan_reference

from .test_scan import _inputs, _rel

NO_BUILD = os.environ.get(scan_cpu.ENV_SWITCH, "1") in ("0", "false", "no", "off") or shutil.which("c++") is None
needs_cpu_kernel = pytest.mark.skipif(NO_BUILD, reason="native CPU scan disabled or no C++ compiler")
OPS = torch.ops.tofdenoise


@pytest.fixture(scope="module")
def cpu_kernel():
    if not scan_cpu.cpu_kernel_available():
        pytest.fail("the native CPU kernel did not build or failed its self-check")


def _plain_args(batch, dim, length, groups, n, use_d, use_bias, kernel, seed=0):
    u, delta, A, B, C, D, bias = (t.detach() for t in _inputs(batch, dim, length, groups, n, seed=seed))
    return (u, delta, A, B, C, D if use_d else None, bias if use_bias else None, True, kernel)


def _ss2d_args(batch, h, w, di, n, use_d_bias, kernel, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, h * w, di, generator=g)
    delta = 0.5 * torch.randn(batch, h * w, 4 * di, generator=g)
    A = -torch.exp(0.5 * torch.randn(4 * di, n, generator=g))
    x_dbl = torch.randn(batch, h * w, 4, 2 * n, generator=g)  # B and C: strided views, as SS2D passes them
    D, bias = torch.randn(4 * di, generator=g), torch.randn(4 * di, generator=g)
    opt = (D, bias) if use_d_bias else (None, None)
    return (x, delta, A, x_dbl[..., :n], x_dbl[..., n:], *opt, h, w, kernel)


def _requires_grad(args):
    return tuple(
        a.detach().requires_grad_() if isinstance(a, torch.Tensor) and a.is_floating_point() else a for a in args
    )


def _backward_args(op, args):
    """Arguments of the backward operator: the forward's inputs, its checkpoints and an output gradient."""
    y, ckpt = op(*args)
    dy = torch.randn_like(y)
    if op is OPS.selective_scan:
        return (*args[:7], args[7], ckpt, dy, args[8])
    return (*args[:7], ckpt, dy, *args[7:])


def test_compile_constant_marks_what_torch_marks():
    """compile_constant sets the attribute torch.compiler.assume_constant_result sets (without importing dynamo at
    the package's import); a torch that changes it fails here instead of silently tracing the kernels' checks."""
    marked = torch.compiler.assume_constant_result(lambda: 0)
    assert compile_constant(lambda: 0)._dynamo_marked_constant is marked._dynamo_marked_constant is True


def test_an_unknown_kernel_name_is_refused():
    args = _plain_args(1, 4, 5, 1, 3, True, True, "cuda")
    with pytest.raises(ValueError, match="kernel must be one of cpu, triton, got 'cuda'"):
        OPS.selective_scan(*args)
    with pytest.raises(ValueError, match="kernel must be one of"):
        ops._ckpt_shape("numba", 1, 1, 4, 5, 3)


@needs_cpu_kernel
@pytest.mark.parametrize("use_d,use_bias", [(True, True), (False, False), (True, False)])
def test_opcheck_cpu_plain_route(cpu_kernel, use_d, use_bias):
    args = _plain_args(2, 20, 70, 2, 5, use_d, use_bias, "cpu")  # 10 channels per group, 2 chunks
    cl = tuple(scan_cpu._channels_last_bc(t) for t in args[3:5])  # what selective_scan_cpu hands over
    for a in (args, (*args[:3], *cl, *args[5:])):
        torch.library.opcheck(OPS.selective_scan, _requires_grad(a))
        torch.library.opcheck(OPS.selective_scan_backward, _backward_args(OPS.selective_scan, a))


@needs_cpu_kernel
@pytest.mark.parametrize("use_d_bias", [True, False])
def test_opcheck_cpu_ss2d_route(cpu_kernel, use_d_bias):
    args = _ss2d_args(2, 5, 7, 18, 4, use_d_bias, "cpu")  # 18 channels: a full and a partial block of lanes
    torch.library.opcheck(OPS.ss2d_scan, _requires_grad(args))
    torch.library.opcheck(OPS.ss2d_scan_backward, _backward_args(OPS.ss2d_scan, args))


@needs_cpu_kernel
def test_cpu_checkpoint_shape_is_the_kernels(cpu_kernel):
    _, ckpt = OPS.selective_scan(*_plain_args(2, 40, 130, 2, 5, True, True, "cpu"))
    assert tuple(ckpt.shape) == scan_cpu.ckpt_shape(2, 2, 20, 130, 5) == (2, 2, 2, 3, 5, scan_cpu.LANES)
    _, ckpt = OPS.ss2d_scan(*_ss2d_args(1, 4, 5, 3, 16, True, "cpu"))
    assert tuple(ckpt.shape) == scan_cpu.ckpt_shape(1, 4, 3, 20, 16)


@needs_cpu_kernel
@pytest.mark.parametrize("use_d_bias", [True, False])
def test_ss2d_operator_gradients_equal_the_reference(cpu_kernel, use_d_bias):
    """Through autograd: every input's gradient, with and without the optional D / delta_bias."""
    args = _requires_grad(_ss2d_args(2, 5, 7, 6, 4, use_d_bias, "cpu"))
    tensors = [a for a in args[:7] if isinstance(a, torch.Tensor)]
    results = []
    for fn in (scan_cpu.ss2d_scan_cpu, ss2d_scan_reference):
        y = fn(*args[:9])
        w = torch.linspace(-1.0, 1.0, y.numel()).view_as(y)
        results.append([y, *torch.autograd.grad((y * w).sum(), tensors)])
    for got, want in zip(*results):
        assert _rel(got, want) < 1e-5


def _lowrank_args(batch, h, w, di, n, r, use_d_bias, seed=0):
    """The fused dt projection's operator: dt_low, B and C as strided slices of one x_proj output (as SS2D passes
    them), the per-direction dt weights (4, d, r)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(batch, h * w, di, generator=g)
    x_dbl = torch.randn(batch, h * w, 4, r + 2 * n, generator=g)
    weight = torch.randn(4, di, r, generator=g) * r**-0.5
    A = -torch.exp(0.5 * torch.randn(4 * di, n, generator=g))
    D, bias = torch.randn(4 * di, generator=g), torch.randn(4 * di, generator=g) - 1.0
    opt = (D, bias) if use_d_bias else (None, None)
    return x, x_dbl, weight, A, opt, h, w


@needs_cpu_kernel
@pytest.mark.parametrize("r,use_d_bias", [(2, True), (5, False)])
def test_opcheck_cpu_ss2d_lowrank_route(cpu_kernel, r, use_d_bias):
    x, x_dbl, weight, A, opt, h, w = _lowrank_args(2, 5, 7, 18, 4, r, use_d_bias)
    x_dbl = x_dbl.detach().requires_grad_()
    dt_low, B, C = x_dbl.split((r, 4, 4), dim=-1)
    args = (x.requires_grad_(), dt_low, weight.requires_grad_(), A.requires_grad_(), B, C, *opt, h, w)
    torch.library.opcheck(OPS.ss2d_scan_lowrank, args)
    y, ckpt = OPS.ss2d_scan_lowrank(*args)
    bargs = (*(a.detach() if isinstance(a, torch.Tensor) else a for a in args[:8]), ckpt, torch.randn_like(y), h, w)
    torch.library.opcheck(OPS.ss2d_scan_lowrank_backward, bargs)


@needs_cpu_kernel
@pytest.mark.parametrize(
    "batch,h,w,di,r,use_d_bias",
    [
        (2, 7, 5, 20, 2, True),  # a full and a partial block of lanes, the rank of DVSS's first level
        (1, 9, 13, 64, 3, False),  # 117 positions: two chunks, the second partial; no D / delta_bias
        (3, 4, 6, 40, 5, True),  # rank 5: the lane sums by a transposing tree
        (1, 3, 11, 33, 20, True),  # rank 20: a tree of 16 and one of 4
    ],
)
def test_ss2d_lowrank_operator_gradients_equal_the_reference(cpu_kernel, batch, h, w, di, r, use_d_bias):
    """The dt projection inside the kernel, forward and backward: y and every input's gradient (x, dt_low, the dt
    weights, A, B, C, D, delta_bias) equal the reference scan on the projected steps, through autograd."""
    from tofdenoise.models.ss2d import dt_projection

    n = 16
    x, x_dbl, weight, A, opt, h, w = _lowrank_args(batch, h, w, di, n, r, use_d_bias)
    leaves = [t.requires_grad_() for t in (x, x_dbl, weight, A, *(o for o in opt if o is not None))]
    results = []
    for fused in (True, False):
        dt_low, B, C = x_dbl.split((r, n, n), dim=-1)
        if fused:
            y, _ = OPS.ss2d_scan_lowrank(x, dt_low, weight, A, B, C, *opt, h, w)
        else:
            delta = dt_projection(dt_low.reshape(-1, 4, r), weight).view(batch, h * w, 4 * di)
            y = ss2d_scan_reference(x, delta, A, B, C, *opt, h, w)
        ramp = torch.linspace(-1.0, 1.0, y.numel()).view_as(y)
        results.append([y, *torch.autograd.grad((y * ramp).sum(), leaves)])
    for i, (got, want) in enumerate(zip(*results)):
        assert _rel(got, want) < 1e-5, f"output {i}"


@needs_cpu_kernel
def test_ss2d_lowrank_operator_refuses_a_wrong_weight(cpu_kernel):
    x, x_dbl, weight, A, opt, h, w = _lowrank_args(1, 4, 5, 8, 4, 2, True)
    dt_low, B, C = x_dbl.split((2, 4, 4), dim=-1)
    with pytest.raises(RuntimeError, match="dt_weight must be a contiguous"):
        OPS.ss2d_scan_lowrank(x, dt_low, torch.randn(4, 8, 3), A, B, C, *opt, h, w)


# --------------------------------------------------------------------------------------- Triton (interpreter)


def _triton():
    pytest.importorskip("triton", reason="Triton is not installed")
    from tofdenoise.models.scan import triton as st

    if not (st.interpreting() or st.triton_available()):
        pytest.skip("neither a CUDA device nor Triton's interpreter (TRITON_INTERPRET=1)")
    return st


def _to(args, device):
    return tuple(a.to(device) if isinstance(a, torch.Tensor) else a for a in args)


@pytest.mark.parametrize("use_d_bias", [True, False])
def test_opcheck_triton_plain_route(use_d_bias):
    st = _triton()
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    args = _to(_plain_args(1, 4, 40, 2, 3, use_d_bias, use_d_bias, "triton"), dev)  # 2 chunks, 2 groups
    torch.library.opcheck(OPS.selective_scan, _requires_grad(args))
    torch.library.opcheck(OPS.selective_scan_backward, _backward_args(OPS.selective_scan, args))
    _, ckpt = OPS.selective_scan(*args)
    assert tuple(ckpt.shape) == st.ckpt_shape(1, 4, 40, 3)


@pytest.mark.parametrize("use_d_bias", [True, False])
def test_opcheck_triton_ss2d_route(use_d_bias):
    st = _triton()
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    args = _to(_ss2d_args(1, 3, 4, 2, 3, use_d_bias, "triton"), dev)
    torch.library.opcheck(OPS.ss2d_scan, _requires_grad(args))
    torch.library.opcheck(OPS.ss2d_scan_backward, _backward_args(OPS.ss2d_scan, args))
    _, ckpt = OPS.ss2d_scan(*args)
    assert tuple(ckpt.shape) == st.ckpt_shape(1, 8, 12, 3)


def test_triton_plain_route_through_the_operator_equals_the_chunked_scan():
    st = _triton()
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    u, delta, A, B, C, D, bias = (t.detach().to(dev).requires_grad_() for t in _inputs(1, 4, 40, 2, 3))
    results = []
    for fn in (st.selective_scan_triton, selective_scan_chunked):
        y = fn(u, delta, A, B, C, None, bias, True)
        results.append([y, *torch.autograd.grad(y.square().sum(), (u, delta, A, B, C, bias))])
    for got, want in zip(*results):
        assert _rel(got, want) < 1e-4


def test_triton_entry_points_compile_in_one_graph():
    """ss2d_scan_triton / selective_scan_triton under torch.compile (fullgraph; AOT autograd with the operators'
    fake implementations): forward and every gradient equal the PyTorch scans."""
    st = _triton()
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    x, delta, A, B, C, D, _, h, w, _ = _ss2d_args(1, 3, 4, 2, 3, True, "triton")
    x_dbl = torch.cat([B, C], dim=-1)
    ss2d = [t.to(dev).requires_grad_() for t in (x, delta, A, x_dbl, D)]
    plain = [t.detach().to(dev).requires_grad_() for t in _inputs(1, 4, 40, 2, 3)[:6]]

    def ss2d_fn(scan):
        return lambda x, delta, A, xd, D: scan(x, delta, A, xd[..., :3], xd[..., 3:], D, None, h, w)

    def plain_fn(scan):
        return lambda u, delta, A, B, C, D: scan(u, delta, A, B, C, D, None, True)

    for tensors, fn, ref in (
        (ss2d, ss2d_fn(st.ss2d_scan_triton), ss2d_fn(ss2d_scan_reference)),
        (plain, plain_fn(st.selective_scan_triton), plain_fn(selective_scan_chunked)),
    ):
        torch._dynamo.reset()
        results = []
        for f in (torch.compile(fn, fullgraph=True, backend="aot_eager"), ref):
            y = f(*tensors)
            results.append([y, *torch.autograd.grad(y.square().sum(), tensors)])
        for got, want in zip(*results):
            assert _rel(got, want) < 1e-5


# --------------------------------------------------------------------------------------------- torch.compile

SMALL_DVSS = dict(in_channels=1, width=8, enc_blocks=[1], bottleneck_blocks=1)


def _forward_backward(net, x, call=None):
    """(output, {parameter name: gradient}) of ``call`` (default: ``net``; a compiled ``net``) on x. The loss weights
    the output with a ramp that does not sum to 0: with one that did (-1 to 1), the head's bias gradient (the weights'
    sum) was 0 in exact arithmetic and the check compared two roundings of it (on an H200 the U-Net's came out
    2.2e-4 apart, at the network's gradient scale, 2026-11-28)."""
    net.zero_grad(set_to_none=True)
    y = (net if call is None else call)(x)
    w = torch.linspace(-0.5, 1.0, y.numel(), device=y.device).view_as(y)
    (y.float() * w).sum().backward()
    return y.detach().float(), {k: p.grad.detach().float().clone() for k, p in net.named_parameters()}


def _distances(reference, run) -> dict[str, float]:
    """:func:`~tofdenoise.models.common.execution_distances` of ``run`` from ``reference``, after checking that every
    parameter but a tenth gets a gradient, so that the comparison reaches the network."""
    g0 = reference[1]
    assert len(g0) > 20
    dead = [n for n, g in g0.items() if not g.any()]
    assert len(dead) <= len(g0) // 10, f"{len(dead)} of {len(g0)} parameters get no gradient: {dead[:5]}"
    return execution_distances(reference, run)


def _assert_none_over(errors: dict[str, float], limits: dict[str, float], what: str) -> None:
    bad = sorted(((e / limits[n], n, e, limits[n]) for n, e in errors.items() if not e <= limits[n]), reverse=True)
    # every tensor over its limit in one message (a GPU run may not get a second try)
    assert not bad, f"{len(bad)} of {len(errors)} {what}: " + ", ".join(
        f"{n} {e:.1e} > {lim:.1e}" for _, n, e, lim in bad[:8]
    )


def _assert_equal_runs(eager, compiled, rel):
    """Float32: the compiled output and every parameter gradient within ``rel`` of eager's (:func:`_distances`)."""
    errors = _distances(eager, compiled)
    _assert_none_over(errors, dict.fromkeys(errors, rel), f"over {rel:g}")


#: bf16 autocast: the compiled run may be this many times further from float32 than eager's own bf16 run ...
BF16_FACTOR = 3.0
#: ... or this far, where eager's own bf16 run is closer than that
BF16_FLOOR = 2e-2


def _assert_within_bf16_rounding(reference, eager, compiled):
    """Under bf16 autocast compiled and eager round in other orders, and a gradient that sums many rounded terms
    (a LayerNorm's bias) can be 100 % off float32 in eager alone (a small DVSS on the CPU, 2026-11-28): so the
    compiled run is held to eager's own bf16 error, per tensor, against the float32 ``reference``: at most
    :data:`BF16_FACTOR` times eager's distance, or :data:`BF16_FLOOR`."""
    own, got = _distances(reference, eager), _distances(reference, compiled)
    limits = {n: BF16_FACTOR * max(own[n], BF16_FLOOR) for n in own}
    _assert_none_over(got, limits, "further from float32 than bf16 rounding allows")


def _compare_compiled(net, x, autocast: bool = False) -> None:
    """Eager against compiled (inductor, one graph) forward + backward of ``net`` on ``x``, under bf16 autocast on
    x's device when ``autocast``: float32 to 1e-4 (:func:`_assert_equal_runs`), bf16 within bf16's own rounding of
    the float32 run (:func:`_assert_within_bf16_rounding`)."""
    reference = _forward_backward(net, x)
    with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=autocast):
        eager = _forward_backward(net, x)
        torch._dynamo.reset()
        compiled = _forward_backward(net, x, torch.compile(net, fullgraph=True))
    if autocast:
        _assert_within_bf16_rounding(reference, eager, compiled)
    else:
        _assert_equal_runs(eager, compiled, 1e-4)


@needs_cpu_kernel
def test_compiled_dvss_equals_eager_after_an_eager_dvss_on_a_larger_frame(cpu_kernel):
    """An eager DVSS first runs a 240 x 320 frame (the default network); then a small DVSS compiled with inductor
    (one graph: ``fullgraph=True``) gives the eager output and every parameter gradient to 1e-4. With the scan as an
    autograd Function around the native kernel the compiled forward failed here ("shape '[94705358677539, ...]' is
    invalid")."""
    big = build_backbone("dvss", in_channels=1)
    with torch.no_grad():
        assert torch.isfinite(big(torch.randn(1, 1, 240, 320))).all()
    torch.manual_seed(0)
    net = draw_zero_parameters(build_backbone("dvss", **SMALL_DVSS))
    block = next(m for m in net.modules() if type(m).__name__ == "SS2D")
    assert block._spatial_scan(torch.zeros(1, 4, 4, block.d_inner)) == "cpu"  # the native kernel's route
    _compare_compiled(net, torch.randn(2, 1, 16, 24))


@pytest.mark.slow
@needs_cpu_kernel
def test_compiled_dvss_under_bf16_autocast_stays_within_bf16_rounding_on_the_cpu(cpu_kernel):
    """The bf16 criterion of the CUDA test, on the CPU (a compile of a few minutes on 2 cores): compiled DVSS under
    bf16 autocast is no further from the float32 run than eager's own bf16 rounding allows."""
    torch.manual_seed(0)
    net = draw_zero_parameters(build_backbone("dvss", **SMALL_DVSS))
    _compare_compiled(net, torch.randn(2, 1, 16, 24), autocast=True)


@pytest.mark.gpu
@pytest.mark.parametrize("autocast", [False, True])
def test_compiled_dvss_equals_eager_on_cuda(autocast):
    """On CUDA the SS2D scan takes the Triton route (its operators); float32 to 1e-4, bf16 autocast within bf16's
    own rounding of a float32 run (:func:`_assert_within_bf16_rounding`)."""
    from tofdenoise.models.scan.triton import triton_verified

    assert triton_verified(torch.cuda.current_device())
    torch.manual_seed(0)
    net = draw_zero_parameters(build_backbone("dvss", **SMALL_DVSS)).cuda()
    block = next(m for m in net.modules() if type(m).__name__ == "SS2D")
    assert block._spatial_scan(torch.zeros(1, 4, 4, block.d_inner, device="cuda")) == "triton"
    _compare_compiled(net, torch.randn(2, 1, 32, 48, device="cuda"), autocast)


@needs_cpu_kernel
def test_cpu_inference_keeps_no_checkpoints_and_gives_the_same_output(cpu_kernel):
    """Without a backward to follow (no_grad, or no input needing a gradient) the SS2D and plain entry points ask
    the operator for no checkpoints: the kernel writes none (an empty tensor comes back) and y is the recorded
    call's (to rounding: without checkpoints the kernel takes its inference exp2 and softplus where it has them)."""
    from tofdenoise.models.scan.cpu import selective_scan_cpu, ss2d_scan_cpu

    args = _ss2d_args(1, 5, 7, 3, 16, True, "cpu")
    _, ckpt_none = OPS.ss2d_scan(*args, False)
    y_keep, ckpt_keep = OPS.ss2d_scan(*args, True)
    assert ckpt_none.numel() == 0 and ckpt_keep.numel() > 0
    x, delta, A, B, C, D, bias, h, w = args[:9]
    with torch.no_grad():
        y_infer = ss2d_scan_cpu(x, delta, A, B, C, D, bias, h, w)
    torch.testing.assert_close(y_infer, y_keep, rtol=1e-5, atol=1e-5)
    plain = _plain_args(1, 16, 70, 2, 5, True, True, "cpu")
    y_plain, _ = OPS.selective_scan(*plain, True)
    with torch.no_grad():
        torch.testing.assert_close(selective_scan_cpu(*plain[:7], plain[7]), y_plain, rtol=1e-5, atol=1e-5)
