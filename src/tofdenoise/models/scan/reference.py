"""Selective scan (Mamba S6 recurrence) in pure PyTorch: the reference, the sequential baseline and the chunked scan.

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

:func:`ss2d_scan_reference` computes the kernels' four-direction SS2D contract the plain way (``cross_scan``,
the chunked scan, ``cross_merge``): the reference of their self-checks and tests. The route a call takes is
chosen by :mod:`~tofdenoise.models.scan.dispatch`, never here.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from .common import Dims, add_skip, check_shapes, compute_inputs, cross_merge, cross_scan, effective_delta, no_autocast

__all__ = [
    "selective_scan_ref",
    "selective_scan_sequential",
    "selective_scan_chunked",
    "ss2d_scan_reference",
    "DEFAULT_CHUNK_SIZE",
    "DEFAULT_GROUP_ELEMS",
]

DEFAULT_CHUNK_SIZE = 64
DEFAULT_GROUP_ELEMS = 1 << 22


# --------------------------------------------------------------------------------------- reference
def selective_scan_ref(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """Straightforward sequential reference (autograd through a Python loop; small L only)."""
    B, C, dims = check_shapes(u, delta, A, B, C, D, delta_bias)
    delta = effective_delta(delta, delta_bias, delta_softplus)
    rep = dims.dim_per_group
    Bx = B.repeat_interleave(rep, dim=1)  # (b, dim, N, L)
    Cx = C.repeat_interleave(rep, dim=1)
    h = u.new_zeros(dims.batch, dims.dim, dims.d_state)
    ys = []
    for t in range(dims.length):
        a = torch.exp(delta[:, :, t, None] * A)
        h = a * h + delta[:, :, t, None] * u[:, :, t, None] * Bx[..., t]
        ys.append((h * Cx[..., t]).sum(-1))
    return add_skip(torch.stack(ys, dim=-1), u, D)


# ------------------------------------------------------------------------------------- layouts
# Internal layout: position l = k * T + t of chunk k. Per-channel tensors are (T, b, G, K, Dg), per-group
# B/C are (T, b, G, K, N), states are (T, b, G, K, N, Dg) and A is (G, 1, N, Dg): time-major and contiguous
# with the channel axis innermost, so elementwise products vectorise over Dg and the sums over the state
# index n and over channels d are batched matrix-vector products.
def _to_tk(x: torch.Tensor, dims: Dims, T: int) -> torch.Tensor:
    b, _, lp = x.shape
    return x.view(b, dims.groups, dims.dim_per_group, lp // T, T).permute(4, 0, 1, 3, 2).contiguous()


def _from_tk(x: torch.Tensor, dims: Dims, length: int) -> torch.Tensor:
    T, b, g, k, dg = x.shape
    return x.permute(1, 2, 4, 3, 0).reshape(b, g * dg, k * T)[..., :length]


def _bc_to_tk(x: torch.Tensor, T: int) -> torch.Tensor:
    b, g, n, lp = x.shape
    return x.view(b, g, n, lp // T, T).permute(4, 0, 1, 3, 2).contiguous()


def _bc_from_tk(x: torch.Tensor, length: int) -> torch.Tensor:
    T, b, g, k, n = x.shape
    return x.permute(1, 2, 4, 3, 0).reshape(b, g, n, k * T)[..., :length]


def _a_layout(A: torch.Tensor, dims: Dims) -> torch.Tensor:
    return A.view(dims.groups, dims.dim_per_group, dims.d_state).transpose(1, 2).contiguous().unsqueeze(1)


def _dA_from_layout(dA: torch.Tensor, dims: Dims) -> torch.Tensor:
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


# --------------------------------------------------------------------------- sequential baseline
class _SequentialScanFn(torch.autograd.Function):
    """Loop over L; forward stores exp(delta A), delta u B and every state; hand-written backward."""

    @staticmethod
    @no_autocast
    def forward(ctx, u, delta, A, B, C):
        b, dim, length = u.shape
        g, n = B.shape[1], A.shape[1]
        dims = Dims(b, dim, length, g, n)
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
    @no_autocast
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
    B, C, _ = check_shapes(u, delta, A, B, C, D, delta_bias)
    ins = compute_inputs(u, delta, A, B, C, delta_bias, delta_softplus)
    y = _SequentialScanFn.apply(*ins)
    return add_skip(y, ins[0], None if D is None else D.to(ins[0].dtype)).to(u.dtype)


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
    @no_autocast
    def forward(ctx, u, delta, A, B, C, chunk_size: int, group_elems: int):
        b, dim, length = u.shape
        g, n = B.shape[1], A.shape[1]
        dims = Dims(b, dim, length, g, n)
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
    @no_autocast
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


def _layouts(u, delta, B, C, dims: Dims, T: int, pad: int):
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
    B, C, _ = check_shapes(u, delta, A, B, C, D, delta_bias)
    if chunk_size < 1 or group_elems < 1:
        raise ValueError(
            f"selective_scan_chunked: chunk_size and group_elems must be >= 1, got {chunk_size}, {group_elems}"
        )
    ins = compute_inputs(u, delta, A, B, C, delta_bias, delta_softplus)
    y = _ChunkedScanFn.apply(*ins, int(chunk_size), int(group_elems))
    return add_skip(y, ins[0], None if D is None else D.to(ins[0].dtype)).to(u.dtype)


def ss2d_scan_reference(x, delta, A, B, C, D, delta_bias, height: int, width: int) -> torch.Tensor:
    """The four-direction SS2D contract of the kernels (:func:`~tofdenoise.models.scan.cpu.ss2d_scan_cpu`,
    :func:`~tofdenoise.models.scan.triton.ss2d_scan_triton`) computed the plain way: ``cross_scan`` copies, the
    chunked PyTorch scan over the 4 d channels, ``cross_merge``. The reference for the kernels' self-check and
    tests."""
    batch, length, di = x.shape

    def per_direction(t: torch.Tensor) -> torch.Tensor:
        """(b, 4, c, H, W), block k for direction k -> (b, 4, c, L): block k read in direction k's order."""
        t4 = cross_scan(t.flatten(0, 1)).view(batch, 4, 4, -1, length)
        return t4[:, torch.arange(4), torch.arange(4)]

    xs = cross_scan(x.transpose(1, 2).reshape(batch, di, height, width))  # (b, 4, d, L)
    d4 = per_direction(delta.transpose(1, 2).reshape(batch, 4, di, height, width))
    bc = [per_direction(t.permute(0, 2, 3, 1).reshape(batch, 4, -1, height, width)) for t in (B, C)]
    y = selective_scan_chunked(
        xs.reshape(batch, 4 * di, length), d4.reshape(batch, 4 * di, length), A, bc[0], bc[1], D, delta_bias, True
    ).view(batch, 4, di, length)
    return cross_merge(y, height, width).flatten(2).transpose(1, 2).to(x.dtype)
