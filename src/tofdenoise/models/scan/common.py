"""What every selective-scan implementation shares: the input contract (mamba-ssm's shapes), the effective step
delta, the D skip term, full precision under autocast, and SS2D's four-direction layout (``cross_scan`` /
``cross_merge``).

This module imports nothing from the rest of the scan package: the reference scan, the native CPU kernel and the
Triton kernels import it, and the dispatcher (:mod:`~tofdenoise.models.scan.dispatch`) imports them.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = [
    "Dims",
    "check_shapes",
    "check_ss2d_shapes",
    "compute_inputs",
    "effective_delta",
    "add_skip",
    "no_autocast",
    "compile_constant",
    "cross_scan",
    "cross_merge",
]


@dataclass
class Dims:
    """The sizes of one scan call: batch, channels (dim), length L, groups of B/C, states N."""

    batch: int
    dim: int
    length: int
    groups: int
    d_state: int

    @property
    def dim_per_group(self) -> int:
        return self.dim // self.groups


def check_shapes(u, delta, A, B, C, D, delta_bias) -> tuple[torch.Tensor, torch.Tensor, Dims]:
    """``(B, C, dims)`` with B and C as (batch, groups, N, L); a ValueError naming the argument otherwise."""
    if u.dim() != 3:
        raise ValueError(f"selective_scan: u must be (batch, dim, L), got shape {tuple(u.shape)}")
    if delta.shape != u.shape:
        raise ValueError(f"selective_scan: delta must have u's shape {tuple(u.shape)}, got {tuple(delta.shape)}")
    batch, dim, length = u.shape
    if A.dim() != 2 or A.shape[0] != dim:
        raise ValueError(f"selective_scan: A must be (dim={dim}, N), got {tuple(A.shape)}")
    n = A.shape[1]
    if A.is_complex():
        raise ValueError("selective_scan: complex A is not supported")
    if B.dim() == 3:
        B = B.unsqueeze(1)
    if C.dim() == 3:
        C = C.unsqueeze(1)
    for name, t in (("B", B), ("C", C)):
        if t.dim() != 4 or t.shape[0] != batch or t.shape[2] != n or t.shape[3] != length:
            raise ValueError(
                f"selective_scan: {name} must be (batch={batch}, groups, N={n}, L={length}) "
                f"or (batch, N, L), got {tuple(t.shape)}"
            )
    if B.shape[1] != C.shape[1]:
        raise ValueError(f"selective_scan: B and C need the same number of groups, got {B.shape[1]} and {C.shape[1]}")
    groups = B.shape[1]
    if dim % groups != 0:
        raise ValueError(f"selective_scan: dim={dim} must be divisible by groups={groups}")
    for name, t in (("D", D), ("delta_bias", delta_bias)):
        if t is not None and tuple(t.shape) != (dim,):
            raise ValueError(f"selective_scan: {name} must be (dim={dim},), got {tuple(t.shape)}")
    return B, C, Dims(batch, dim, length, groups, n)


def check_ss2d_shapes(name: str, x, delta, A, B, C, D, delta_bias, height: int, width: int) -> None:
    """The SS2D kernels' contract: x (batch, H W, d), delta (batch, H W, 4 d), A (4 d, N), B / C (batch, H W, 4, N),
    D / delta_bias (4 d,) or None; a ValueError naming the argument (``name`` is the caller) otherwise."""
    if x.dim() != 3:
        raise ValueError(f"{name}: x must be (batch, height x width, d), got shape {tuple(x.shape)}")
    batch, length, di = x.shape
    if length != height * width:
        raise ValueError(f"{name}: x has {length} positions, expected height x width = {height * width}")
    n = A.shape[-1]
    want = {"delta": (batch, length, 4 * di), "A": (4 * di, n), "B": (batch, length, 4, n), "C": (batch, length, 4, n)}
    for arg, t in (("delta", delta), ("A", A), ("B", B), ("C", C)):
        if tuple(t.shape) != want[arg]:
            raise ValueError(f"{name}: {arg} has shape {tuple(t.shape)}, expected {want[arg]}")
    for arg, t in (("D", D), ("delta_bias", delta_bias)):
        if t is not None and tuple(t.shape) != (4 * di,):
            raise ValueError(f"{name}: {arg} has shape {tuple(t.shape)}, expected {(4 * di,)}")


def compute_inputs(u, delta, A, B, C, delta_bias, delta_softplus) -> tuple[torch.Tensor, ...]:
    """``(u, delta, A, B, C)`` contiguous in the compute dtype (float64 for float64 input, else float32), with
    ``delta`` already through the bias and softplus (:func:`effective_delta`)."""
    compute = torch.float64 if u.dtype == torch.float64 else torch.float32
    delta = effective_delta(delta.to(compute), None if delta_bias is None else delta_bias.to(compute), delta_softplus)
    return tuple(t.to(compute).contiguous() for t in (u, delta, A, B, C))


def effective_delta(delta: torch.Tensor, delta_bias: torch.Tensor | None, delta_softplus: bool) -> torch.Tensor:
    """softplus(delta + delta_bias) (bias and softplus optional)."""
    if delta_bias is not None:
        delta = delta + delta_bias.to(delta.dtype)[None, :, None]
    if delta_softplus:
        delta = F.softplus(delta)
    return delta


def add_skip(y: torch.Tensor, u: torch.Tensor, D: torch.Tensor | None) -> torch.Tensor:
    """y + D u (the skip term; y itself without D)."""
    if D is not None:
        y = y + D.to(y.dtype)[None, :, None] * u
    return y


def no_autocast(fn):
    """Run a custom Function's forward/backward in full precision even under autocast (the scan's
    matrix products would otherwise run in bf16/fp16)."""

    @functools.wraps(fn)
    def wrapper(ctx, *args):
        device = next((a.device.type for a in args if isinstance(a, torch.Tensor)), "cpu")
        with torch.autocast(device_type=device, enabled=False):
            return fn(ctx, *args)

    return wrapper


def compile_constant(fn):
    """Mark ``fn`` as ``torch.compiler.assume_constant_result`` does: ``torch.compile`` calls it while tracing and
    keeps its result (a route, a kernel's availability) as a constant instead of tracing its body (builds,
    self-checks, caches). Set directly because ``torch.compiler.assume_constant_result`` imports ``torch._dynamo``
    (and with it Triton, about 2 s) when a module using it is imported; ``tests/models/scan/test_ops.py`` checks
    that it still sets this attribute."""
    fn._dynamo_marked_constant = True
    return fn


def cross_scan(x: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) -> (B, 4, C, H*W): row-major, column-major, and both reversed."""
    b, c, h, w = x.shape
    rows = x.reshape(b, c, h * w)
    cols = x.transpose(2, 3).reshape(b, c, h * w)
    fwd = torch.stack([rows, cols], dim=1)
    return torch.cat([fwd, fwd.flip(-1)], dim=1)


def cross_merge(y: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Inverse of :func:`cross_scan` summed over the 4 directions: (B, 4, C, L) -> (B, C, H, W)."""
    b, _, c, _ = y.shape
    y = y[:, :2] + y[:, 2:].flip(-1)
    rows = y[:, 0].reshape(b, c, h, w)
    cols = y[:, 1].reshape(b, c, w, h).transpose(2, 3)
    return rows + cols
