"""The selective-scan kernels as ``torch.library`` custom operators (namespace ``tofdenoise``), so that
``torch.compile`` traces a scan as one opaque node with a known output shape instead of calling a native kernel on
its fake tensors.

Six operators, each with a fake (meta) implementation; the three forward operators carry autograd
(``torch.library.register_autograd``): they return ``(y, ckpt)`` -- the output and the float32 state checkpoints
the backward restarts from -- and save their inputs and ``ckpt``; their backward calls the matching ``*_backward``
operator, itself a custom operator, so a compiled training step holds both kernels as graph nodes.

- ``tofdenoise::selective_scan(u, delta, A, B, C, D?, delta_bias?, delta_softplus, kernel) -> (y, ckpt)``: the
  plain route on mamba-ssm's shapes, u / delta (batch, dim, L), A (dim, N), B / C (batch, groups, N, L) with any
  strides, D / delta_bias (dim,) or None; y (batch, dim, L) contiguous.
- ``tofdenoise::ss2d_scan(x, delta, A, B, C, D?, delta_bias?, height, width, kernel) -> (y, ckpt)``: SS2D's four
  directions read in place (softplus always on), x (batch, H W, d), delta (batch, H W, 4 d), A (4 d, N),
  B / C (batch, H W, 4, N) with any strides, D / delta_bias (4 d,) or None; y (batch, H W, d) contiguous.
- ``tofdenoise::ss2d_scan_lowrank(x, dt_low, dt_weight, A, B, C, D?, delta_bias?, height, width) -> (y, ckpt)``:
  the SS2D route with its dt projection inside the native CPU kernel (training; float32): dt_low (batch, H W, 4, R)
  with any strides (a slice of x_proj's output), dt_weight (4, d, R); the steps ``dt_low @ dt_weight^T`` are
  computed where the kernel reads them, in the forward and again in the backward, which hands their gradient
  straight to d dt_low and d dt_weight. No (batch, H W, 4 d) tensor of steps or of their gradient exists.
- ``tofdenoise::selective_scan_backward`` / ``tofdenoise::ss2d_scan_backward``: ``(du, ddelta, dA, dB, dC, dD,
  ddelta_bias)``; dD / ddelta_bias are empty (0,) tensors when D / delta_bias is None (an operator cannot return
  None), and the autograd formula hands back None for them. ``tofdenoise::ss2d_scan_lowrank_backward``: ``(dx,
  d dt_low, d dt_weight, dA, dB, dC, dD, ddelta_bias)``.

``kernel`` names the implementation: ``"cpu"`` (the native C++ kernel of :mod:`.cpu`, float32 tensors) or
``"triton"`` (the Triton kernels of :mod:`.triton`: CUDA tensors, or CPU tensors in Triton's interpreter, which is
how the tests reach them without a GPU). It is an argument rather than a choice by device so that the interpreter
route stays reachable. Dtype conversions belong to the callers (:func:`.cpu.selective_scan_cpu`,
:func:`.triton.ss2d_scan_triton`, ...), outside the operators, so that autograd converts the gradients back.

The kernel modules are imported inside the implementations, so importing this module builds nothing and does
not import Triton; the package's ``__init__`` imports it, which registers the operators before any kernel module
can run (a submodule is never imported without its package).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["KERNELS", "NAMESPACE"]

NAMESPACE = "tofdenoise"
#: the implementations an operator's ``kernel`` argument names
KERNELS = ("cpu", "triton")


def _check_kernel(kernel: str) -> None:
    if kernel not in KERNELS:
        raise ValueError(f"tofdenoise scan operator: kernel must be one of {', '.join(KERNELS)}, got {kernel!r}")


def _kernel_module(kernel: str):
    """The module implementing ``kernel`` (imported on first use; the CPU kernel builds when first called)."""
    _check_kernel(kernel)
    if kernel == "cpu":
        from . import cpu as module
    else:
        from . import triton as module
    return module


def _ckpt_shape(kernel: str, batch: int, groups: int, dim_per_group: int, length: int, n: int) -> tuple[int, ...]:
    """Shape of the float32 state checkpoints the forward of ``kernel`` returns."""
    _check_kernel(kernel)
    if kernel == "cpu":
        from .cpu import ckpt_shape

        return ckpt_shape(batch, groups, dim_per_group, length, n)
    from .triton import ckpt_shape

    return ckpt_shape(batch, groups * dim_per_group, length, n)


def _grad_or_empty(grad: Tensor | None, like: Tensor | None, ref: Tensor) -> Tensor:
    """The gradient of an optional input (float32, contiguous), or an empty float32 tensor when it is None."""
    if like is None or grad is None:
        return ref.new_empty((0,), dtype=torch.float32)
    return grad.contiguous()


def _empty_like_opt(like: Tensor | None, ref: Tensor) -> Tensor:
    return ref.new_empty((0,) if like is None else tuple(like.shape), dtype=torch.float32)


# ----------------------------------------------------------------------------------------------- plain route


@torch.library.custom_op(f"{NAMESPACE}::selective_scan", mutates_args=())
def _selective_scan(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    delta_bias: Tensor | None,
    delta_softplus: bool,
    kernel: str,
    checkpoints: bool = True,
) -> tuple[Tensor, Tensor]:
    module = _kernel_module(kernel)
    y, ckpt = module.scan_forward(
        u.contiguous(), delta.contiguous(), A.contiguous(), B, C, D, delta_bias, delta_softplus, checkpoints
    )
    return y.contiguous(), _kept(ckpt, checkpoints)


def _kept(ckpt: Tensor, checkpoints: bool) -> Tensor:
    """The checkpoints, or an empty float32 tensor when none were asked for (no backward can follow: the CPU
    kernel then writes none; the Triton kernels write theirs regardless)."""
    return ckpt if checkpoints else ckpt.new_empty((0,), dtype=torch.float32)


@_selective_scan.register_fake
def _selective_scan_fake(u, delta, A, B, C, D, delta_bias, delta_softplus, kernel, checkpoints=True):
    batch, dim, length = u.shape
    groups, n = B.shape[1], A.shape[1]
    shape = _ckpt_shape(kernel, batch, groups, dim // groups, length, n) if checkpoints else (0,)
    return u.new_empty(u.shape), u.new_empty(shape, dtype=torch.float32)


@torch.library.custom_op(f"{NAMESPACE}::selective_scan_backward", mutates_args=())
def _selective_scan_backward(
    u: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    delta_bias: Tensor | None,
    delta_softplus: bool,
    ckpt: Tensor,
    dy: Tensor,
    kernel: str,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    module = _kernel_module(kernel)
    u, delta, A = u.contiguous(), delta.contiguous(), A.contiguous()
    du, ddelta, dA, dB, dC, dD, dbias = module.scan_backward(u, delta, A, B, C, D, delta_bias, delta_softplus, ckpt, dy)
    if kernel == "triton":  # the CPU kernel's dB / dC are (batch, L, G, N) memory seen as (batch, G, N, L)
        dB, dC = dB.contiguous(), dC.contiguous()
    return (
        du.contiguous(),
        ddelta.contiguous(),
        dA.contiguous(),
        dB,
        dC,
        _grad_or_empty(dD, D, u),
        _grad_or_empty(dbias, delta_bias, u),
    )


@_selective_scan_backward.register_fake
def _selective_scan_backward_fake(u, delta, A, B, C, D, delta_bias, delta_softplus, ckpt, dy, kernel):
    _check_kernel(kernel)
    if kernel == "cpu":  # float32; dB / dC are channels-last memory
        batch, groups, n, length = B.shape
        dB = u.new_empty((batch, length, groups, n)).permute(0, 2, 3, 1)
        dC = u.new_empty((batch, length, groups, n)).permute(0, 2, 3, 1)
    else:
        dB, dC = B.new_empty(B.shape), C.new_empty(C.shape)
    return (
        u.new_empty(u.shape),
        delta.new_empty(delta.shape),
        A.new_empty(A.shape),
        dB,
        dC,
        _empty_like_opt(D, u),
        _empty_like_opt(delta_bias, u),
    )


def _selective_scan_setup(ctx, inputs, output):
    u, delta, A, B, C, D, delta_bias, delta_softplus, kernel, _ = inputs
    ckpt = output[1]
    ctx.save_for_backward(u, delta, A, B, C, D, delta_bias, ckpt)
    ctx.delta_softplus, ctx.kernel = delta_softplus, kernel
    ctx.mark_non_differentiable(ckpt)
    ctx.set_materialize_grads(False)  # no zero-filled gradient for the checkpoints (as large as y)


def _selective_scan_grad(ctx, dy, _dckpt):
    if dy is None:  # y took no part in the loss (gradients are not materialised: see the setup)
        return (None,) * 10
    u, delta, A, B, C, D, delta_bias, ckpt = ctx.saved_tensors
    du, ddelta, dA, dB, dC, dD, dbias = _selective_scan_backward(
        u, delta, A, B, C, D, delta_bias, ctx.delta_softplus, ckpt, dy, ctx.kernel
    )
    return (
        du,
        ddelta,
        dA,
        dB,
        dC,
        None if D is None else dD,
        None if delta_bias is None else dbias,
        None,
        None,
        None,
    )


_selective_scan.register_autograd(_selective_scan_grad, setup_context=_selective_scan_setup)


# ------------------------------------------------------------------------------------------------ SS2D route


@torch.library.custom_op(f"{NAMESPACE}::ss2d_scan", mutates_args=())
def _ss2d_scan(
    x: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    delta_bias: Tensor | None,
    height: int,
    width: int,
    kernel: str,
    checkpoints: bool = True,
) -> tuple[Tensor, Tensor]:
    module = _kernel_module(kernel)
    x, delta, A, B, C = _ss2d_prepare(x, delta, A, B, C)
    y, ckpt = module.ss2d_forward(x, delta, A, B, C, D, delta_bias, height, width, checkpoints)
    return y.contiguous(), _kept(ckpt, checkpoints)


def _ss2d_prepare(x, delta, A, B, C):
    """x, delta, A contiguous; B and C with equal strides (the Triton kernels address both with B's)."""
    if B.stride() != C.stride():
        B, C = B.contiguous(), C.contiguous()
    return x.contiguous(), delta.contiguous(), A.contiguous(), B, C


@_ss2d_scan.register_fake
def _ss2d_scan_fake(x, delta, A, B, C, D, delta_bias, height, width, kernel, checkpoints=True):
    batch, length, di = x.shape
    shape = _ckpt_shape(kernel, batch, 4, di, length, A.shape[1]) if checkpoints else (0,)
    return x.new_empty(x.shape), x.new_empty(shape, dtype=torch.float32)


@torch.library.custom_op(f"{NAMESPACE}::ss2d_scan_backward", mutates_args=())
def _ss2d_scan_backward(
    x: Tensor,
    delta: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    delta_bias: Tensor | None,
    ckpt: Tensor,
    dy: Tensor,
    height: int,
    width: int,
    kernel: str,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    module = _kernel_module(kernel)
    x, delta, A, B, C = _ss2d_prepare(x, delta, A, B, C)
    dx, ddelta, dA, dB, dC, dD, dbias = module.ss2d_backward(x, delta, A, B, C, D, delta_bias, ckpt, dy, height, width)
    return (
        dx.contiguous(),
        ddelta.contiguous(),
        dA.contiguous(),
        dB.contiguous(),
        dC.contiguous(),
        _grad_or_empty(dD, D, x),
        _grad_or_empty(dbias, delta_bias, x),
    )


@_ss2d_scan_backward.register_fake
def _ss2d_scan_backward_fake(x, delta, A, B, C, D, delta_bias, ckpt, dy, height, width, kernel):
    _check_kernel(kernel)
    return (
        x.new_empty(x.shape),
        delta.new_empty(delta.shape),
        A.new_empty(A.shape),
        B.new_empty(B.shape),
        C.new_empty(C.shape),
        _empty_like_opt(D, x),
        _empty_like_opt(delta_bias, x),
    )


def _ss2d_scan_setup(ctx, inputs, output):
    x, delta, A, B, C, D, delta_bias, height, width, kernel, _ = inputs
    ckpt = output[1]
    ctx.save_for_backward(x, delta, A, B, C, D, delta_bias, ckpt)
    ctx.size, ctx.kernel = (height, width), kernel
    ctx.mark_non_differentiable(ckpt)
    ctx.set_materialize_grads(False)  # no zero-filled gradient for the checkpoints (as large as y)


def _ss2d_scan_grad(ctx, dy, _dckpt):
    if dy is None:  # y took no part in the loss (gradients are not materialised: see the setup)
        return (None,) * 11
    x, delta, A, B, C, D, delta_bias, ckpt = ctx.saved_tensors
    dx, ddelta, dA, dB, dC, dD, dbias = _ss2d_scan_backward(
        x, delta, A, B, C, D, delta_bias, ckpt, dy, *ctx.size, ctx.kernel
    )
    return (
        dx,
        ddelta,
        dA,
        dB,
        dC,
        None if D is None else dD,
        None if delta_bias is None else dbias,
        None,
        None,
        None,
        None,
    )


_ss2d_scan.register_autograd(_ss2d_scan_grad, setup_context=_ss2d_scan_setup)


# ------------------------------------------------------------------------------- SS2D route, dt projection fused


@torch.library.custom_op(f"{NAMESPACE}::ss2d_scan_lowrank", mutates_args=())
def _ss2d_scan_lowrank(
    x: Tensor,
    dt_low: Tensor,
    dt_weight: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    delta_bias: Tensor | None,
    height: int,
    width: int,
) -> tuple[Tensor, Tensor]:
    from .cpu import ss2d_forward_lowrank_train

    y, ckpt = ss2d_forward_lowrank_train(
        x.contiguous(), dt_low, dt_weight, A.contiguous(), B, C, D, delta_bias, height, width
    )
    return y.contiguous(), ckpt


@_ss2d_scan_lowrank.register_fake
def _ss2d_scan_lowrank_fake(x, dt_low, dt_weight, A, B, C, D, delta_bias, height, width):
    return _ss2d_scan_fake(x, None, A, B, C, D, delta_bias, height, width, "cpu")  # the CPU kernel's y and checkpoints


@torch.library.custom_op(f"{NAMESPACE}::ss2d_scan_lowrank_backward", mutates_args=())
def _ss2d_scan_lowrank_backward(
    x: Tensor,
    dt_low: Tensor,
    dt_weight: Tensor,
    A: Tensor,
    B: Tensor,
    C: Tensor,
    D: Tensor | None,
    delta_bias: Tensor | None,
    ckpt: Tensor,
    dy: Tensor,
    height: int,
    width: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    from .cpu import ss2d_backward_lowrank

    dx, ddt, dA, dB, dC, dD, dbias, dw = ss2d_backward_lowrank(
        x.contiguous(), dt_low, dt_weight, A.contiguous(), B, C, D, delta_bias, ckpt, dy, height, width
    )
    return (
        dx.contiguous(),
        ddt.contiguous(),
        dw.contiguous(),
        dA.contiguous(),
        dB.contiguous(),
        dC.contiguous(),
        _grad_or_empty(dD, D, x),
        _grad_or_empty(dbias, delta_bias, x),
    )


@_ss2d_scan_lowrank_backward.register_fake
def _ss2d_scan_lowrank_backward_fake(x, dt_low, dt_weight, A, B, C, D, delta_bias, ckpt, dy, height, width):
    return (
        x.new_empty(x.shape),
        dt_low.new_empty(dt_low.shape),
        dt_weight.new_empty(dt_weight.shape),
        A.new_empty(A.shape),
        B.new_empty(B.shape),
        C.new_empty(C.shape),
        _empty_like_opt(D, x),
        _empty_like_opt(delta_bias, x),
    )


def _ss2d_scan_lowrank_setup(ctx, inputs, output):
    x, dt_low, dt_weight, A, B, C, D, delta_bias, height, width = inputs
    ctx.save_for_backward(x, dt_low, dt_weight, A, B, C, D, delta_bias, output[1])
    ctx.size = (height, width)
    ctx.mark_non_differentiable(output[1])
    ctx.set_materialize_grads(False)


def _ss2d_scan_lowrank_grad(ctx, dy, _dckpt):
    if dy is None:
        return (None,) * 10
    x, dt_low, dt_weight, A, B, C, D, delta_bias, ckpt = ctx.saved_tensors
    dx, ddt, dw, dA, dB, dC, dD, dbias = _ss2d_scan_lowrank_backward(
        x, dt_low, dt_weight, A, B, C, D, delta_bias, ckpt, dy, *ctx.size
    )
    return (
        dx,
        ddt,
        dw,
        dA,
        dB,
        dC,
        None if D is None else dD,
        None if delta_bias is None else dbias,
        None,
        None,
    )


_ss2d_scan_lowrank.register_autograd(_ss2d_scan_lowrank_grad, setup_context=_ss2d_scan_lowrank_setup)
