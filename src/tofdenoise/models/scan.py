"""Selective scan (Mamba S6 recurrence) in pure PyTorch.

Recurrence, per batch b, channel d and state n (Gu & Dao, "Mamba", Alg. 2; shapes of mamba-ssm's
``selective_scan_fn``)::

    delta_t = softplus(delta_t + delta_bias)          (softplus / bias optional)
    h_t     = exp(delta_t * A[d, n]) * h_{t-1} + delta_t * u_t * B[g(d), n, t]
    y_t     = sum_n C[g(d), n, t] * h_t[n] + D[d] * u_t

with u, delta (batch, dim, L); A (dim, N); B, C (batch, groups, N, L) (or (batch, N, L) = one group),
g(d) = d // (dim / groups); D, delta_bias (dim,).

Three implementations share the gradient formulas of :func:`_state_gradients`:

* :func:`selective_scan_ref` -- a plain Python loop recorded by autograd (test oracle, tiny L only).
* :func:`selective_scan_sequential` -- a loop over L with a hand-written backward that stores every state
  (the memory-hungry baseline of the benchmarks).
* :func:`selective_scan_chunked` -- the default. L is cut into K chunks of T = ``chunk_size`` positions
  and consecutive chunks into *groups* of at most ``group_elems`` state elements. The forward walks the
  groups in order: decays exp(delta A) and inputs delta u B of a group go into reused buffers, a
  zero-start scan over the T positions (vectorised over the group's chunks) gives each chunk's local end
  state, a short carry over the group's chunks gives each chunk's entry state, and a second scan emits y.
  Only the chunk-entry states (L dim N / T elements) are saved. The backward walks the groups in reverse:
  it recomputes the group's states from the saved entry states, runs the adjoint recursion the same way
  (local reverse scans + carry), and forms all gradients from the group's states and adjoints. Only
  decays in (0, 1] are multiplied (as stable as the sequential loop), exp is evaluated once per element
  and direction, and no (L, dim, N) tensor is ever held. No Python loop over L is recorded by autograd:
  the loops (T positions, chunks of a group) run inside a custom ``autograd.Function``.

:func:`selective_scan` dispatches: on CUDA to mamba-ssm when importable, else to the Triton kernels
(``scan_triton``, after an on-device self-check); on the CPU to the native C++ kernel (``scan_cpu``, built
on first use, after a self-check); otherwise to the chunked PyTorch scan.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = [
    "selective_scan",
    "selective_scan_ref",
    "selective_scan_sequential",
    "selective_scan_chunked",
    "available_scan_backends",
    "resolve_scan_backend",
]

DEFAULT_CHUNK_SIZE = 64
DEFAULT_GROUP_ELEMS = 1 << 22


# ----------------------------------------------------------------------------------------------- inputs
@dataclass
class _Dims:
    batch: int
    dim: int
    length: int
    groups: int
    d_state: int

    @property
    def dim_per_group(self) -> int:
        return self.dim // self.groups


def _check_shapes(u, delta, A, B, C, D, delta_bias) -> tuple[torch.Tensor, torch.Tensor, _Dims]:
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
    return B, C, _Dims(batch, dim, length, groups, n)


def _compute_inputs(u, delta, A, B, C, delta_bias, delta_softplus) -> tuple[torch.Tensor, ...]:
    """``(u, delta, A, B, C)`` contiguous in the compute dtype (float64 for float64 input, else float32), with
    ``delta`` already through the bias and softplus (:func:`_effective_delta`)."""
    compute = torch.float64 if u.dtype == torch.float64 else torch.float32
    delta = _effective_delta(delta.to(compute), None if delta_bias is None else delta_bias.to(compute), delta_softplus)
    return tuple(t.to(compute).contiguous() for t in (u, delta, A, B, C))


def _effective_delta(delta: torch.Tensor, delta_bias: torch.Tensor | None, delta_softplus: bool) -> torch.Tensor:
    if delta_bias is not None:
        delta = delta + delta_bias.to(delta.dtype)[None, :, None]
    if delta_softplus:
        delta = F.softplus(delta)
    return delta


def _finish(y: torch.Tensor, u: torch.Tensor, D: torch.Tensor | None) -> torch.Tensor:
    if D is not None:
        y = y + D.to(y.dtype)[None, :, None] * u
    return y


# --------------------------------------------------------------------------------------- reference
def selective_scan_ref(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """Straightforward sequential reference (autograd through a Python loop; small L only)."""
    B, C, dims = _check_shapes(u, delta, A, B, C, D, delta_bias)
    delta = _effective_delta(delta, delta_bias, delta_softplus)
    rep = dims.dim_per_group
    Bx = B.repeat_interleave(rep, dim=1)  # (b, dim, N, L)
    Cx = C.repeat_interleave(rep, dim=1)
    h = u.new_zeros(dims.batch, dims.dim, dims.d_state)
    ys = []
    for t in range(dims.length):
        a = torch.exp(delta[:, :, t, None] * A)
        h = a * h + delta[:, :, t, None] * u[:, :, t, None] * Bx[..., t]
        ys.append((h * Cx[..., t]).sum(-1))
    return _finish(torch.stack(ys, dim=-1), u, D)


# ------------------------------------------------------------------------------------- layouts
# Internal layout: position l = k * T + t of chunk k. Per-channel tensors are (T, b, G, K, Dg), per-group
# B/C are (T, b, G, K, N), states are (T, b, G, K, N, Dg) and A is (G, 1, N, Dg): time-major and contiguous
# with the channel axis innermost, so elementwise products vectorise over Dg and the sums over the state
# index n and over channels d are batched matrix-vector products.
def _to_tk(x: torch.Tensor, dims: _Dims, T: int) -> torch.Tensor:
    b, _, lp = x.shape
    return x.view(b, dims.groups, dims.dim_per_group, lp // T, T).permute(4, 0, 1, 3, 2).contiguous()


def _from_tk(x: torch.Tensor, dims: _Dims, length: int) -> torch.Tensor:
    T, b, g, k, dg = x.shape
    return x.permute(1, 2, 4, 3, 0).reshape(b, g * dg, k * T)[..., :length]


def _bc_to_tk(x: torch.Tensor, T: int) -> torch.Tensor:
    b, g, n, lp = x.shape
    return x.view(b, g, n, lp // T, T).permute(4, 0, 1, 3, 2).contiguous()


def _bc_from_tk(x: torch.Tensor, length: int) -> torch.Tensor:
    T, b, g, k, n = x.shape
    return x.permute(1, 2, 4, 3, 0).reshape(b, g, n, k * T)[..., :length]


def _a_layout(A: torch.Tensor, dims: _Dims) -> torch.Tensor:
    return A.view(dims.groups, dims.dim_per_group, dims.d_state).transpose(1, 2).contiguous().unsqueeze(1)


def _dA_from_layout(dA: torch.Tensor, dims: _Dims) -> torch.Tensor:
    return dA.transpose(1, 2).reshape(dims.dim, dims.d_state)


def _pad_len(x: torch.Tensor, pad: int) -> torch.Tensor:
    return F.pad(x, (0, pad)) if pad else x


def _decay(dl_t: torch.Tensor, A5: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """exp(delta_t * A): (..., K, Dg) x (G, 1, N, Dg) -> (..., K, N, Dg) (into ``out`` when given)."""
    if out is None:
        return torch.exp_(dl_t.unsqueeze(-2) * A5)
    return torch.mul(dl_t.unsqueeze(-2), A5, out=out).exp_()


def _inject(dul_t: torch.Tensor, B_t: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """delta_t u_t B_t: (..., K, Dg) x (..., K, N) -> (..., K, N, Dg) (into ``out`` when given)."""
    if out is None:
        return B_t.unsqueeze(-1) * dul_t.unsqueeze(-2)
    return torch.mul(B_t.unsqueeze(-1), dul_t.unsqueeze(-2), out=out)


def _readout(H: torch.Tensor, C: torch.Tensor) -> torch.Tensor:
    """sum_n C_n h_n: (..., K, N, Dg) x (..., K, N) -> (..., K, Dg)."""
    return (C.unsqueeze(-2) @ H).squeeze(-2)


# ------------------------------------------------------------------------------- shared gradients
def _state_gradients(bb, H, Gm, A5, dl, ul, dul, dyl, Bl, Cl, tmp):
    """Gradients from stored states of a block of positions (any leading time axis).

    bb = delta u B, H = states, Gm = adjoint dL/dh (all (S, b, G, K, N, Dg)); dl, ul, dul = delta, u,
    delta*u and dyl = dL/dy (S, b, G, K, Dg); Bl, Cl (S, b, G, K, N); A5 (G, 1, N, Dg).
    Returns d_delta, d_u (S, b, G, K, Dg), dA (G, N, Dg), dB, dC (S, b, G, K, N). Overwrites ``bb`` and
    ``tmp`` (a scratch tensor of the states' shape).
    """
    # Sums over the channel axis (innermost) as multiply + sum: faster here than batched mat-vec products.
    dC = torch.mul(H, dyl.unsqueeze(-2), out=tmp).sum(-1)
    dB = torch.mul(Gm, dul.unsqueeze(-2), out=tmp).sum(-1)
    q = torch.sub(H, bb, out=bb)  # a_t * h_{t-1}
    q.mul_(Gm)  # dL/d(a_t) * a_t
    torch.mul(q, dl.unsqueeze(-2), out=tmp)
    lead = tmp.shape[0] * tmp.shape[1]  # sum over (time, batch) as a matrix product: much faster than .sum
    dA = (tmp.new_ones(1, lead) @ tmp.view(lead, -1)).view(tmp.shape[2:]).sum(1)
    d_delta = q.mul_(A5).sum(-2)
    sr = (Bl.unsqueeze(-2) @ Gm).squeeze(-2)  # sum_n B_n dL/dh_n
    d_delta += ul * sr
    d_u = dl * sr
    return d_delta, d_u, dA, dB, dC


def _no_autocast(fn):
    """Run a custom Function's forward/backward in full precision even under autocast (the scan's
    matrix products would otherwise run in bf16/fp16)."""

    @functools.wraps(fn)
    def wrapper(ctx, *args):
        device = next((a.device.type for a in args if isinstance(a, torch.Tensor)), "cpu")
        with torch.autocast(device_type=device, enabled=False):
            return fn(ctx, *args)

    return wrapper


# --------------------------------------------------------------------------- sequential baseline
class _SequentialScanFn(torch.autograd.Function):
    """Loop over L; forward stores exp(delta A), delta u B and every state; hand-written backward."""

    @staticmethod
    @_no_autocast
    def forward(ctx, u, delta, A, B, C):
        b, dim, length = u.shape
        g, n = B.shape[1], A.shape[1]
        dims = _Dims(b, dim, length, g, n)
        dl, ul = _to_tk(delta, dims, length), _to_tk(u, dims, length)  # (L, b, G, 1, Dg)
        dul = dl * ul
        Bl, Cl = _bc_to_tk(B, length), _bc_to_tk(C, length)  # (L, b, G, 1, N)
        A5 = _a_layout(A, dims)
        a = _decay(dl, A5)
        bb = _inject(dul, Bl)
        H = torch.empty_like(a)
        h = torch.zeros_like(a[0])
        for t in range(length):
            h = torch.addcmul(bb[t], a[t], h, out=H[t])
        y = _readout(H, Cl)
        ctx.save_for_backward(a, bb, H, A5, dl, ul, dul, Bl, Cl)
        ctx.dims = dims
        return _from_tk(y, dims, length)

    @staticmethod
    @_no_autocast
    def backward(ctx, dy):
        if getattr(ctx, "consumed", False):
            raise RuntimeError(
                "selective_scan_sequential: backward reuses its saved buffers; retain_graph is not supported"
            )
        ctx.consumed = True
        a, bb, H, A5, dl, ul, dul, Bl, Cl = ctx.saved_tensors
        dims = ctx.dims
        length = dims.length
        dyl = _to_tk(dy.contiguous(), dims, length)
        Gm = Cl.unsqueeze(-1) * dyl.unsqueeze(-2)
        for t in range(length - 2, -1, -1):
            Gm[t].addcmul_(a[t + 1], Gm[t + 1])
        d_delta, d_u, dA, dB, dC = _state_gradients(bb, H, Gm, A5, dl, ul, dul, dyl, Bl, Cl, tmp=a)
        return (
            _from_tk(d_u, dims, length),
            _from_tk(d_delta, dims, length),
            _dA_from_layout(dA, dims),
            _bc_from_tk(dB, length),
            _bc_from_tk(dC, length),
        )


def selective_scan_sequential(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """Sequential loop over L with a hand-written backward storing all states (benchmark baseline)."""
    B, C, _ = _check_shapes(u, delta, A, B, C, D, delta_bias)
    ins = _compute_inputs(u, delta, A, B, C, delta_bias, delta_softplus)
    y = _SequentialScanFn.apply(*ins)
    return _finish(y, ins[0], None if D is None else D.to(ins[0].dtype)).to(u.dtype)


# ------------------------------------------------------------------------------------ chunked scan
class _ChunkedScanFn(torch.autograd.Function):
    """Chunked scan; saves only its inputs and the chunk-entry states (L*dim*N / chunk_size elements).

    Both passes walk *groups* of consecutive chunks in order (forward) or in reverse (backward), carrying
    the state (adjoint) across group boundaries; inside a group the recurrence runs over the T positions
    of a chunk for all chunks of the group at once, and chunk boundaries inside the group are bridged by
    a zero-start local scan plus a short carry over the group's chunks. exp(delta A) is computed once per
    position in each direction, into buffers of ``group_elems`` elements.
    """

    @staticmethod
    @_no_autocast
    def forward(ctx, u, delta, A, B, C, chunk_size: int, group_elems: int):
        b, dim, length = u.shape
        g, n = B.shape[1], A.shape[1]
        dims = _Dims(b, dim, length, g, n)
        T = max(1, min(chunk_size, length))
        K = math.ceil(length / T)
        pad = K * T - length
        dl, ul, Bl, Cl = _layouts(u, delta, B, C, dims, T, pad)
        A5 = _a_layout(A, dims)
        y = torch.empty_like(dl)
        Hin = dl.new_empty(dl.shape[1:-1] + A5.shape[-2:])
        carry = dl.new_zeros(Hin.shape[:2] + A5.shape[-2:])
        bufs = _Buffers(dl)
        for sl in _group_slices(K, T * b * dim * n, group_elems):
            dlg, ulg, Blg, Clg = (x[:, :, :, sl].contiguous() for x in (dl, ul, Bl, Cl))
            dulg = dlg * ulg
            a, bb = bufs.get(dlg.shape[:-1] + A5.shape[-2:], 2)
            _decay(dlg, A5, a)
            _inject(dulg, Blg, bb)
            entry = _entry_states(a, bb, dlg, A5, carry)
            Hin[:, :, sl] = entry
            h = entry
            yg = y[:, :, :, sl] if sl.stop - sl.start == K else torch.empty_like(dlg)
            for t in range(T):
                torch.addcmul(bb[t], a[t], h, out=h)
                torch.matmul(Clg[t].unsqueeze(-2), h, out=yg[t].unsqueeze(-2))
            if yg.data_ptr() != y.data_ptr():
                y[:, :, :, sl] = yg
            carry = h[:, :, -1].clone()
        # Inputs are saved in their own layout (usually kept alive by upstream ops anyway); the internal
        # layouts are rebuilt in the backward.
        ctx.save_for_backward(u, delta, B, C, A5, Hin)
        ctx.dims, ctx.T, ctx.K, ctx.group_elems = dims, T, K, group_elems
        return _from_tk(y, dims, length)

    @staticmethod
    @_no_autocast
    def backward(ctx, dy):
        u, delta, B, C, A5, Hin = ctx.saved_tensors
        dims, T, K = ctx.dims, ctx.T, ctx.K
        length = dims.length
        pad = K * T - length
        dl, ul, Bl, Cl = _layouts(u, delta, B, C, dims, T, pad)
        dyl = _to_tk(_pad_len(dy.contiguous(), pad), dims, T)
        d_delta = torch.empty_like(dl)
        d_u = torch.empty_like(dl)
        dB = torch.empty_like(Bl)
        dC = torch.empty_like(Cl)
        dA = torch.zeros_like(A5[:, 0])
        gcarry = dl.new_zeros(Hin.shape[:2] + A5.shape[-2:])  # adjoint handed back from later groups
        bufs = _Buffers(dl)
        for sl in reversed(_group_slices(K, T * dims.batch * dims.dim * dims.d_state, ctx.group_elems)):
            dlg, ulg, dylg, Blg, Clg = (x[:, :, :, sl].contiguous() for x in (dl, ul, dyl, Bl, Cl))
            dulg = dlg * ulg
            a, bb, H, Gm = bufs.get(dlg.shape[:-1] + A5.shape[-2:], 4)
            _decay(dlg, A5, a)
            _inject(dulg, Blg, bb)
            h = Hin[:, :, sl]
            for t in range(T):
                h = torch.addcmul(bb[t], a[t], h, out=H[t])
            torch.mul(Clg.unsqueeze(-1), dylg.unsqueeze(-2), out=Gm)  # C_t dy_t
            Gm[T - 1] += _exit_adjoints(a, Gm, dlg, A5, gcarry)
            for t in range(T - 2, -1, -1):
                Gm[t].addcmul_(a[t + 1], Gm[t + 1])
            gcarry = a[0, :, :, 0] * Gm[0, :, :, 0]
            gd, gu, gA, gB, gC = _state_gradients(bb, H, Gm, A5, dlg, ulg, dulg, dylg, Blg, Clg, tmp=a)
            d_delta[:, :, :, sl] = gd
            d_u[:, :, :, sl] = gu
            dB[:, :, :, sl] = gB
            dC[:, :, :, sl] = gC
            dA += gA
        return (
            _from_tk(d_u, dims, length),
            _from_tk(d_delta, dims, length),
            _dA_from_layout(dA, dims),
            _bc_from_tk(dB, length),
            _bc_from_tk(dC, length),
            None,
            None,
        )


def _layouts(u, delta, B, C, dims: _Dims, T: int, pad: int):
    """Internal layouts of delta, u (T, b, G, K, Dg) and B, C (T, b, G, K, N). Padded positions have
    delta = 0 (decay 1, no input) and C = 0: they change nothing."""
    return (
        _to_tk(_pad_len(delta, pad), dims, T),
        _to_tk(_pad_len(u, pad), dims, T),
        _bc_to_tk(_pad_len(B, pad), T),
        _bc_to_tk(_pad_len(C, pad), T),
    )


class _Buffers:
    """Reusable scratch tensors of one shape (fresh large allocations cost page faults every time)."""

    def __init__(self, like: torch.Tensor) -> None:
        self.like = like
        self.tensors: tuple[torch.Tensor, ...] = ()

    def get(self, shape, count: int) -> tuple[torch.Tensor, ...]:
        shape = tuple(shape)
        if len(self.tensors) < count or tuple(self.tensors[0].shape) != shape:
            self.tensors = tuple(self.like.new_empty(shape) for _ in range(count))
        return self.tensors[:count]


def _group_slices(K: int, per_chunk: int, group_elems: int) -> list[slice]:
    """Near-equal groups of consecutive chunks, each holding at most ``group_elems`` state elements."""
    step = max(1, min(K, group_elems // max(per_chunk, 1)))
    groups = math.ceil(K / step)
    step = math.ceil(K / groups)
    return [slice(k0, min(K, k0 + step)) for k0 in range(0, K, step)]


def _carry(local: torch.Tensor, P: torch.Tensor, init: torch.Tensor, reverse: bool) -> torch.Tensor:
    """Carry across chunks (axis 2 of (b, G, K, N, Dg)): out_k = carry before chunk k, starting from
    ``init``; carry <- local_k + P_k * carry, walking forwards (states) or backwards (adjoints)."""
    out = torch.empty_like(local)
    carry = init
    order = range(local.shape[2] - 1, -1, -1) if reverse else range(local.shape[2])
    for k in order:
        out[:, :, k] = carry
        carry = torch.addcmul(local[:, :, k], P[:, :, k], carry)
    return out


def _entry_states(a, bb, dlg, A5, carry) -> torch.Tensor:
    """State entering each chunk of a group (b, G, Kg, N, Dg), given the state ``carry`` entering the group."""
    if a.shape[3] == 1:
        return carry.unsqueeze(2).clone()
    h = bb[0].clone()  # zero-start local scans: chunk-end states
    for t in range(1, a.shape[0]):
        torch.addcmul(bb[t], a[t], h, out=h)
    P = _decay(dlg.sum(0), A5)  # whole-chunk decay exp(A * sum_t delta_t)
    return _carry(h, P, carry, reverse=False)


def _exit_adjoints(a, Gm, dlg, A5, gcarry) -> torch.Tensor:
    """Adjoint flowing into the last position of each chunk of a group from later positions,
    (b, G, Kg, N, Dg), given ``gcarry`` handed back to the group from the next group.
    ``Gm`` holds C_t dy_t (the direct adjoint) on entry and is not modified."""
    if a.shape[3] == 1:
        return gcarry.unsqueeze(2)
    e = torch.zeros_like(Gm[0])  # zero-start local reverse scans: a_0 g_0 per chunk
    for t in range(a.shape[0] - 1, -1, -1):
        e.add_(Gm[t]).mul_(a[t])
    P = _decay(dlg.sum(0), A5)
    return _carry(e, P, gcarry, reverse=True)


def selective_scan_chunked(
    u,
    delta,
    A,
    B,
    C,
    D=None,
    delta_bias=None,
    delta_softplus=False,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    group_elems: int = DEFAULT_GROUP_ELEMS,
) -> torch.Tensor:
    """Chunked pure-PyTorch selective scan with a recomputing custom backward (CPU and CUDA).

    ``chunk_size`` positions per chunk; the backward recomputes states for as many chunks at a time as
    fit in ``group_elems`` elements per (positions, batch, dim, N) tensor.
    """
    B, C, _ = _check_shapes(u, delta, A, B, C, D, delta_bias)
    if chunk_size < 1 or group_elems < 1:
        raise ValueError(
            f"selective_scan_chunked: chunk_size and group_elems must be >= 1, got {chunk_size}, {group_elems}"
        )
    ins = _compute_inputs(u, delta, A, B, C, delta_bias, delta_softplus)
    y = _ChunkedScanFn.apply(*ins, int(chunk_size), int(group_elems))
    return _finish(y, ins[0], None if D is None else D.to(ins[0].dtype)).to(u.dtype)


# ------------------------------------------------------------------------------------- dispatch
def available_scan_backends(device: torch.device | str | None = None, verify: bool = False) -> list[str]:
    """Backends usable on ``device`` (default: CUDA if available) in ``auto`` preference order; ``torch``
    always last. On CUDA: ``mamba_ssm`` when its compiled extension imports, then ``triton`` when Triton
    imports (with ``verify=True``: only if its kernels pass the on-device self-check). On the CPU: ``cpu``
    (the native kernel of ``scan_cpu``) when it builds and passes its self-check (this builds it once)."""
    dev = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    out: list[str] = []
    if dev.type == "cuda":
        from . import scan_triton

        if scan_triton.mamba_ssm_available():
            out.append("mamba_ssm")
        index = dev.index if dev.index is not None else torch.cuda.current_device()
        if scan_triton.triton_available() and (not verify or scan_triton.triton_verified(index)):
            out.append("triton")
    elif dev.type == "cpu":
        from .scan_cpu import cpu_kernel_available

        if cpu_kernel_available():
            out.append("cpu")
    out.append("torch")
    return out


SCAN_BACKENDS = ("auto", "cpu", "torch", "sequential", "triton", "mamba_ssm", "export")


def resolve_scan_backend(backend: str, u: torch.Tensor) -> str:
    """The route ``selective_scan`` takes for ``u``: ``auto`` -> the first of
    :func:`available_scan_backends` (CUDA: mamba_ssm / triton / torch; CPU: cpu / torch); ``cpu`` -> the
    native kernel for float32/bf16/fp16 CPU tensors, else (float64, or the kernel failed to build: one
    warning at build time) the chunked ``torch`` scan."""
    if backend not in SCAN_BACKENDS:
        raise ValueError(f"selective_scan: unknown backend {backend!r}; valid: {', '.join(SCAN_BACKENDS)}")
    if backend == "auto":
        if u.is_cuda:
            return available_scan_backends(u.device, verify=True)[0]
        backend = "cpu"
    if backend == "cpu":
        if u.is_cuda:
            raise ValueError(f"selective_scan: backend 'cpu' needs CPU tensors, got device {u.device}")
        from .scan_cpu import cpu_kernel_available

        return "cpu" if u.dtype != torch.float64 and cpu_kernel_available() else "torch"
    return backend


def selective_scan(
    u,
    delta,
    A,
    B,
    C,
    D=None,
    delta_bias=None,
    delta_softplus=False,
    backend: str = "auto",
) -> torch.Tensor:
    """Selective scan with mamba-ssm's ``selective_scan_fn`` signature and shapes; returns (batch, dim, L).

    ``backend``: ``"auto"`` (CUDA: mamba-ssm, else the self-checked Triton kernels, else PyTorch; CPU: the
    native kernel when it builds, else PyTorch), ``"cpu"`` (native CPU kernel; float64 inputs and a failed
    build fall back to the chunked scan), ``"torch"`` (chunked), ``"sequential"`` (stores all states),
    ``"triton"``, ``"mamba_ssm"``, ``"export"`` (``scan_export``: a fixed number of tensor steps, for ONNX).
    :func:`resolve_scan_backend` names the route a call takes.
    """
    backend = resolve_scan_backend(backend, u)
    if backend == "cpu":
        from .scan_cpu import selective_scan_cpu

        return selective_scan_cpu(u, delta, A, B, C, D, delta_bias, delta_softplus)
    if backend == "torch":
        return selective_scan_chunked(u, delta, A, B, C, D, delta_bias, delta_softplus)
    if backend == "sequential":
        return selective_scan_sequential(u, delta, A, B, C, D, delta_bias, delta_softplus)
    if backend == "export":  # plain tensor ops, no loop over L: the ONNX export (scan_export.py)
        from .scan_export import selective_scan_export

        return selective_scan_export(u, delta, A, B, C, D, delta_bias, delta_softplus)
    if not u.is_cuda:
        raise ValueError(f"selective_scan: backend {backend!r} needs CUDA tensors, got device {u.device}")
    from . import scan_triton

    fn = scan_triton.selective_scan_triton if backend == "triton" else scan_triton.selective_scan_mamba
    return fn(u, delta, A, B, C, D, delta_bias, delta_softplus)
