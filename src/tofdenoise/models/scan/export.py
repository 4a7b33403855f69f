"""Selective scan written for ONNX export: loops over the positions (or chunks) of lanes, memory bounded in L.

``selective_scan_export`` computes what :func:`tofdenoise.models.scan.selective_scan_ref` computes (same
arguments) with plain tensor operations whose state tensors have at most ``state_elems`` elements (or one lane's,
if that is more), whatever the sequence length L; every other tensor has the size of an input, (batch, dim, L) or
(batch, groups, N, L):

1. The sequence is cut into K consecutive *lanes* of T = ceil(L / K) positions, K = ``state_elems`` // (batch x dim
   x N) (at most L), padded at the end with steps delta = 0 (decay 1, no input). Every step of the loops below
   handles position t of all K lanes at once: a state of (batch, dim, N, K) elements.
2. First loop, over t = 0..T-1, from a zero state: h <- exp(delta_t A) h + delta_t u_t B_t. It leaves each lane's
   local end state; the lane's whole decay is exp(A sum_t delta_t).
3. Carry across lanes: a Hillis-Steele scan over the K lanes of (decay, end state), ceil(log2 K) doubling steps on
   (batch, dim, N, K) tensors, gives the state entering each lane.
4. Second loop, over t again, from the entry states: the same recurrence, emitting y_t = sum_n C_t h_t per step.

Work: every position's state is formed twice (steps 2 and 4), plus the small carry: 12 elementwise operators per
position over the lane state (5 in the first loop: delta x A, exp, decay x state, delta u x B, add; 7 in the second:
the same, C x state, the sum over N). The former export scan (a Hillis-Steele scan over the whole sequence) made 20
doubling steps of about 5 operators over the full (batch, dim, N, L) state and held it whole. Only decays in (0, 1]
are multiplied, as in the sequential scan. Speed: ONNX has no fused recurrence, so each of those operators reads and
writes the lane state in memory, where the native CPU kernel forms each state element once in registers; in
onnxruntime this scan costs about 7-9x the native kernel per state element (docs/benchmarks.md).

In the exported graph the loops are ONNX ``Loop`` nodes with a dynamic trip count T: :func:`_lane_scan` is a
``torch.jit.script`` function, which the TorchScript-based exporter (``torch.onnx.export(..., dynamo=False)``, the
route of :mod:`tofdenoise.inference.export`) keeps as loops when it traces the network around it. Every size is
read from the tensors inside the scripted function (a Python ``int`` handed to it from the traced code would be
frozen to the example's value), so height and width stay dynamic. The per-step outputs leave the loop as an ONNX
sequence; :func:`tofdenoise.inference.onnx_loops.sequences_to_scan_outputs` turns them into the ``Loop``'s scan
outputs after export. ``state_elems`` (:data:`EXPORT_SCAN_STATE_ELEMS`) was chosen by measurement
(docs/benchmarks.md, "ONNX export").

The dynamo exporter (``torch.onnx.export(..., dynamo=True)``, ``tofdenoise export --exporter dynamo``) does not
keep scripted loops: ``torch.export`` runs them with the example's sizes and unrolls them, so the graph would only
run at the example's size. Under ``torch.export`` (:func:`torch.compiler.is_exporting`) the same two loops are
therefore written with the ``scan`` higher-order operator (:func:`_lane_scan_exporting`), which becomes ONNX
``Scan`` nodes with a dynamic trip count. That route takes K = ``state_elems`` // (batch x dim x N) lanes whatever
L (a symbolic ``min`` with L would make ``torch.export`` specialise on the size), padding a short sequence to K.
The two routes give the same numbers; tests/models/scan/test_export.py checks both against the reference scan.

**Chunked form** (``form="chunked"``, :func:`_chunk_scan`; the default form is :data:`EXPORT_SCAN_FORM`). The lanes
are cut into chunks of T = ``chunk`` positions (16), and a loop step handles a chunk of every lane at once. Within
a chunk, with S_t the summed delta up to position t and m the midpoint of the range of 0, S_0, ..., S_{T-1},

    h_t = exp(A (S_t - m)) (exp(A m) h_in + cumsum_{s<=t} exp(-A (S_s - m)) delta_s u_s B_s),

standard operators only (``CumSum`` over the chunk's positions). The first loop forms each lane's end state the same
way (a sum in place of the cumulative sum), the carry across lanes is the one above, the second loop emits. The loops
make 1/T of the step form's iterations over tensors T times larger, with 14 elementwise passes per state element
against 12. Every exponent lies within |A| |S_t - m|, at most |A| times half a chunk's range of summed delta; the
form computes the largest over the whole input at run time and takes the step loops above it
(:data:`EXPORT_SCAN_EXP_BOUND`): a ``torch.jit.script`` ``if`` (ONNX ``If``) on the TorchScript route, a
``torch.cond`` (ONNX ``If``) under ``torch.export``. The guard is global: one chunk of one channel above the bound
sends the whole scan to the step loops. Measured on onnxruntime's CPU provider it is not faster than the step form
(docs/benchmarks.md, "Export scan forms"), so it is not the default; it makes 1/16 of the loop iterations, which is
what a launch-bound GPU provider pays for (not measured).
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator

import torch
import torch.nn.functional as F

__all__ = [
    "selective_scan_export",
    "export_scan_lanes",
    "export_chunk_lanes",
    "export_scan_form",
    "EXPORT_SCAN_STATE_ELEMS",
    "EXPORT_SCAN_FORMS",
    "EXPORT_SCAN_FORM",
    "EXPORT_SCAN_CHUNK",
    "EXPORT_SCAN_EXP_BOUND",
]

#: the export scan's forms: ``steps`` (one loop step per position of a lane) and ``chunked`` (one per chunk)
EXPORT_SCAN_FORMS = ("steps", "chunked")
#: the form :func:`selective_scan_export` takes unless told (docs/benchmarks.md, "export scan forms")
EXPORT_SCAN_FORM = "steps"
#: positions per chunk of the chunked form
EXPORT_SCAN_CHUNK = 16
#: the largest exponent |A| |S_t - m| the chunked form forms (float32 overflows at 88.7); above it the step loops
#: run. 60 leaves a factor e^28 (1.4e12) for |delta u B| summed over a chunk before float32 overflows.
EXPORT_SCAN_EXP_BOUND = 60.0

#: elements of the scan state handled per loop step (batch x dim x N x lanes): 2**18 float32 = 1 MiB per
#: tensor (64 lanes of the default DVSS's first level)
EXPORT_SCAN_STATE_ELEMS = 1 << 18


def export_scan_lanes(lane_elems: int, length: int, state_elems: int) -> int:
    """Lanes K of a scan whose state has ``lane_elems`` (batch x dim x N) elements per lane: as many as
    ``state_elems`` allows, at least 1, at most ``length`` (so K depends on L only while L is below that)."""
    return max(1, min(length, state_elems // max(1, lane_elems)))


def _lanes_layout(x: torch.Tensor, groups: int, lanes: int, steps: int, pad: int) -> torch.Tensor:
    """(b, c, L) -> (T, b, groups, c / groups, K): position k T + t of the padded sequence at [t, ..., k]."""
    b, c = x.size(0), x.size(1)
    x = F.pad(x, [0, pad]).reshape(b, groups, c // groups, lanes, steps)
    return x.permute(4, 0, 1, 2, 3)


def _lane_inputs(
    u: torch.Tensor, delta: torch.Tensor, A: torch.Tensor, B: torch.Tensor, C: torch.Tensor, lanes: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The scan's inputs cut into ``lanes`` lanes of T = ceil(L / K) positions: delta and delta u as
    (T, b, g, dg, 1, K), B and C as (T, b, g, 1, N, K), and A as (1, g, dg, N, 1), so that each broadcasts against
    a state (b, g, dg, N, K)."""
    b, dim, length = u.size(0), u.size(1), u.size(2)
    g, n = B.size(1), A.size(1)
    steps = (length + lanes - 1) // lanes
    pad = steps * lanes - length
    dl = _lanes_layout(delta, g, lanes, steps, pad).unsqueeze(4)
    wl = _lanes_layout(delta * u, g, lanes, steps, pad).unsqueeze(4)
    Bl = _lanes_layout(B.reshape(b, g * n, length), g, lanes, steps, pad).unsqueeze(3)
    Cl = _lanes_layout(C.reshape(b, g * n, length), g, lanes, steps, pad).unsqueeze(3)
    return dl, wl, Bl, Cl, A.reshape(1, g, dim // g, n, 1)


def _from_lanes(y: torch.Tensor, length: int) -> torch.Tensor:
    """Per-position outputs (T, b, g, dg, K) back to the sequence (b, dim, L): the inverse of :func:`_lanes_layout`,
    padding dropped."""
    return y.permute(1, 2, 3, 4, 0).reshape(y.size(1), y.size(2) * y.size(3), -1)[..., :length]


def _entry_states(h: torch.Tensor, decay: torch.Tensor, lanes: int) -> torch.Tensor:
    """The state entering each lane (last axis) from each lane's local end state ``h`` and whole ``decay``: an
    inclusive Hillis-Steele scan of (decay, end state) over the lanes, shifted by one lane."""
    off = 1
    while off < lanes:
        h_prev = F.pad(h, [off, 0])[..., :lanes]
        decay_prev = F.pad(decay, [off, 0], value=1.0)[..., :lanes]
        h = decay * h_prev + h
        decay = decay * decay_prev
        off = off * 2
    return F.pad(h, [1, 0])[..., :lanes]


def _lane_scan(
    u: torch.Tensor, delta: torch.Tensor, A: torch.Tensor, B: torch.Tensor, C: torch.Tensor, state_elems: int
) -> torch.Tensor:
    """y = sum_n C h of the recurrence h_t = exp(delta_t A) h_{t-1} + delta_t u_t B_t (no skip term).

    u, delta (b, dim, L) float32 (delta already through bias and softplus); A (dim, N); B, C (b, g, N, L).
    Layouts: a lane's index is the innermost axis; states are (b, g, dim/g, N, K)."""
    lanes = export_scan_lanes(u.size(0) * u.size(1) * A.size(1), u.size(2), state_elems)
    dl, wl, Bl, Cl, A5 = _lane_inputs(u, delta, A, B, C, lanes)
    h = torch.zeros([dl.size(1), dl.size(2), dl.size(3), A5.size(3), lanes], dtype=u.dtype, device=u.device)
    for t in range(dl.size(0)):
        h = torch.exp(dl[t] * A5) * h + wl[t] * Bl[t]
    decay = torch.exp(dl.sum(0) * A5)  # a lane's whole decay

    h = _entry_states(h, decay, lanes)

    ys: list[torch.Tensor] = []
    for t in range(dl.size(0)):
        h = torch.exp(dl[t] * A5) * h + wl[t] * Bl[t]
        ys.append((h * Cl[t]).sum(3))  # (b, g, dg, K)
    return _from_lanes(torch.stack(ys, 0), u.size(2))


def _lane_scan_exporting(
    u: torch.Tensor, delta: torch.Tensor, A: torch.Tensor, B: torch.Tensor, C: torch.Tensor, state_elems: int
) -> torch.Tensor:
    """:func:`_lane_scan` for ``torch.export`` (the dynamo exporter): its two loops as ``scan`` operators (ONNX
    ``Scan``), K = ``state_elems`` // (b x dim x N) lanes whatever L (module docstring)."""
    lanes = max(1, state_elems // (u.size(0) * u.size(1) * A.size(1)))
    return _from_lanes(_lane_loops_exporting(u, delta, A, B, C, lanes), u.size(2))


def _lane_loops_exporting(
    u: torch.Tensor, delta: torch.Tensor, A: torch.Tensor, B: torch.Tensor, C: torch.Tensor, lanes: int
) -> torch.Tensor:
    """The per-position outputs (T, b, g, dg, K) of :func:`_lane_scan_exporting` over ``lanes`` lanes."""
    from torch._higher_order_ops.scan import scan  # torch.export's loop operator; the ONNX exporter lowers it

    # contiguous: scan requires its carry to keep the initial state's strides
    dl, wl, Bl, Cl, A5 = (x.contiguous() for x in _lane_inputs(u, delta, A, B, C, lanes))

    def local_end(h: torch.Tensor, xs: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, torch.Tensor]:
        d, w, bb = xs
        return torch.exp(d * A5) * h + w * bb, d.new_zeros(1)

    def emit(h: torch.Tensor, xs: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, torch.Tensor]:
        d, w, bb, cc = xs
        h = torch.exp(d * A5) * h + w * bb
        return h, (h * cc).sum(3)

    h0 = torch.zeros([dl.size(1), dl.size(2), dl.size(3), A5.size(3), lanes], dtype=u.dtype, device=u.device)
    h, _ = scan(local_end, h0, (dl, wl, Bl))
    h = _entry_states(h, torch.exp(dl.sum(0) * A5), lanes).contiguous()
    _, y = scan(emit, h, (dl, wl, Bl, Cl))
    return y


def export_chunk_lanes(lane_elems: int, length: int, state_elems: int, chunk: int) -> int:
    """Lanes K of the chunked form: as many as ``state_elems`` allows (state elements per loop step, as in
    :func:`export_scan_lanes`), at least 1, at most the number of chunks of ``chunk`` positions in ``length``."""
    return max(1, min((length + chunk - 1) // chunk, state_elems // max(1, lane_elems)))


def _chunk_inputs(
    u: torch.Tensor, delta: torch.Tensor, B: torch.Tensor, C: torch.Tensor, lanes: int, chunk: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The scan's inputs cut into ``lanes`` lanes of M chunks of ``chunk`` positions (a lane's length a multiple of
    the chunk, the sequence padded at the end with delta = 0): delta and delta u as (M, chunk, b, g, dg, 1, K), B and
    C as (M, chunk, b, g, 1, N, K); position k T + j chunk + i at [j, i, ..., k]."""
    b, dim, length = u.size(0), u.size(1), u.size(2)
    g, n = B.size(1), B.size(2)
    chunks = (length + lanes * chunk - 1) // (lanes * chunk)
    steps = chunks * chunk
    pad = steps * lanes - length
    shape = [chunks, chunk, b, g, dim // g, 1, lanes]
    dl = _lanes_layout(delta, g, lanes, steps, pad).reshape(shape)
    wl = _lanes_layout(delta * u, g, lanes, steps, pad).reshape(shape)
    shape = [chunks, chunk, b, g, 1, n, lanes]
    Bl = _lanes_layout(B.reshape(b, g * n, length), g, lanes, steps, pad).reshape(shape)
    Cl = _lanes_layout(C.reshape(b, g * n, length), g, lanes, steps, pad).reshape(shape)
    return dl, wl, Bl, Cl


def _chunk_offsets(dl: torch.Tensor, A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Within each chunk of ``dl`` (M, T, b, g, dg, 1, K): the summed delta S_t = delta_0 + ... + delta_t taken from
    the chunk's reference m (the midpoint of the range of 0, S_0, ..., S_{T-1}) as ``S - m`` (M, T, ...); m (M, b,
    g, dg, 1, K); the chunk's whole sum less m (M, b, g, dg, 1, K); and the largest |A| (S_t - m) or |A| m of all
    chunks (a 0-d tensor), the exponent bound the chunked form needs (every exponent it forms is within it)."""
    S = torch.cumsum(dl, 1)
    hi = torch.amax(S, [1], True).clamp_min(0.0)
    lo = torch.amin(S, [1], True).clamp_max(0.0)
    mid = 0.5 * (hi + lo)
    a_max = torch.amax(A.abs(), [1]).reshape(1, 1, 1, dl.size(3), dl.size(4), 1, 1)
    bound = (0.5 * (hi - lo) * a_max).max()
    return S - mid, mid.squeeze(1), S[:, -1] - mid.squeeze(1), bound


def _chunk_loops(
    dl: torch.Tensor,
    wl: torch.Tensor,
    Bl: torch.Tensor,
    Cl: torch.Tensor,
    A: torch.Tensor,
    s_mid: torch.Tensor,
    mid: torch.Tensor,
    end_mid: torch.Tensor,
) -> torch.Tensor:
    """y = sum_n C h per position (M, T, b, g, dg, K), chunk by chunk, from :func:`_chunk_inputs` and
    :func:`_chunk_offsets`. Within a chunk, with E_t = A (S_t - m):

        h_t = exp(E_t) (exp(A m) h_in + cumsum_{s<=t} exp(-E_s) delta_s u_s B_s)

    which is h_t = exp(A S_t) h_in + sum_{s<=t} exp(A (S_t - S_s)) delta_s u_s B_s, the recurrence's state. A
    first loop over the chunks (only with more than one lane) gives each lane's local end state, the carry across
    lanes (:func:`_entry_states`) their entry states, a second loop the outputs."""
    g, dg, n, lanes = dl.size(3), dl.size(4), A.size(1), dl.size(6)
    A5 = A.reshape(1, g, dg, n, 1)  # against a state (b, g, dg, N, K)
    A6 = A5.unsqueeze(0)  # against a chunk (T, b, g, dg, N, K)
    h = torch.zeros([dl.size(2), g, dg, n, lanes], dtype=dl.dtype, device=dl.device)
    if lanes > 1:
        for j in range(dl.size(0)):
            s = (torch.exp(-A6 * s_mid[j]) * wl[j] * Bl[j]).sum(0)
            h = torch.exp(A5 * end_mid[j]) * (s + torch.exp(A5 * mid[j]) * h)
        h = _entry_states(h, torch.exp(dl.sum([0, 1]) * A5), lanes)

    ys: list[torch.Tensor] = []
    for j in range(dl.size(0)):
        decay = torch.exp(A6 * s_mid[j])  # exp(E_t), (T, b, g, dg, N, K)
        hs = decay * (torch.cumsum(wl[j] * Bl[j] / decay, 0) + torch.exp(A5 * mid[j]) * h)
        ys.append((hs * Cl[j]).sum(4))  # (T, b, g, dg, K)
        h = hs[-1]
    return torch.stack(ys, 0)


def _chunk_scan(
    u: torch.Tensor,
    delta: torch.Tensor,
    A: torch.Tensor,
    B: torch.Tensor,
    C: torch.Tensor,
    state_elems: int,
    chunk: int,
    exp_bound: float,
) -> torch.Tensor:
    """:func:`_lane_scan`'s result through the chunked form (:func:`_chunk_loops`) when every exponent it forms is
    within ``exp_bound``, through :func:`_lane_scan` (the step loops) otherwise: the bound is computed from the
    inputs, so in the exported graph it is an ONNX ``If`` decided at run time."""
    lanes = export_chunk_lanes(u.size(0) * u.size(1) * A.size(1), u.size(2), state_elems, chunk)
    dl, wl, Bl, Cl = _chunk_inputs(u, delta, B, C, lanes, chunk)
    s_mid, mid, end_mid, bound = _chunk_offsets(dl, A)
    if bool(bound <= exp_bound):
        y = _chunk_loops(dl, wl, Bl, Cl, A, s_mid, mid, end_mid)
        return _from_lanes(y.reshape(y.size(0) * y.size(1), y.size(2), y.size(3), y.size(4), y.size(5)), u.size(2))
    return _lane_scan(u, delta, A, B, C, state_elems)


def _chunk_scan_exporting(
    u: torch.Tensor,
    delta: torch.Tensor,
    A: torch.Tensor,
    B: torch.Tensor,
    C: torch.Tensor,
    state_elems: int,
    chunk: int,
    exp_bound: float,
) -> torch.Tensor:
    """:func:`_chunk_scan` for ``torch.export``: the loops as ``scan`` operators (ONNX ``Scan``), the guard as
    ``torch.cond`` (ONNX ``If``), K = ``state_elems`` // (b x dim x N) lanes whatever L (module docstring).

    ``torch.cond`` traces each branch with fresh symbols for its inputs' sizes and requires both branches to return
    the same dense shape, so the branches read every size from this function's Python ints, the sequence is padded
    here to a whole number of chunks in every lane (both forms then take it unpadded), and the padding is dropped
    after the ``cond``."""
    from torch._higher_order_ops.scan import scan

    b, dim, n, g, length = u.size(0), u.size(1), A.size(1), B.size(1), u.size(2)
    dg = dim // g
    lanes = max(1, state_elems // (b * dim * n))
    span = lanes * chunk
    pad = (length + span - 1) // span * span - length
    u, delta, B, C = (F.pad(x, [0, pad]) for x in (u, delta, B, C))
    # contiguous: scan requires its carry to keep the initial state's strides
    dl, wl, Bl, Cl = (x.contiguous() for x in _chunk_inputs(u, delta, B, C, lanes, chunk))
    s_mid, mid, end_mid, bound = (x.contiguous() for x in _chunk_offsets(dl, A))

    def chunked(u, delta, A, B, C, dl, wl, Bl, Cl, s_mid, mid, end_mid):
        A6 = A.reshape(1, 1, g, dg, n, 1)  # the one view of A the loop bodies take (scan refuses aliased inputs)

        def local_end(h, xs):
            sm, w, bb, m, em = xs
            A5 = A6.squeeze(0)
            s = (torch.exp(-A6 * sm) * w * bb).sum(0)
            return (torch.exp(A5 * em) * (s + torch.exp(A5 * m) * h)).contiguous(), em.new_zeros(1)

        def emit(h, xs):
            sm, w, bb, cc, m = xs
            A5 = A6.squeeze(0)
            decay = torch.exp(A6 * sm)
            hs = decay * (torch.cumsum(w * bb / decay, 0) + torch.exp(A5 * m) * h)
            return hs[-1].clone(), (hs * cc).sum(4)

        h = dl.new_zeros([b, g, dg, n, lanes])
        if lanes > 1:
            h, _ = scan(local_end, h, (s_mid, wl, Bl, mid, end_mid))
            h = _entry_states(h, torch.exp(dl.sum([0, 1]) * A6.squeeze(0)), lanes).contiguous()
        _, y = scan(emit, h, (s_mid, wl, Bl, Cl, mid))
        return y  # (M, T, b, g, dg, K)

    def steps(u, delta, A, B, C, dl, wl, Bl, Cl, s_mid, mid, end_mid):
        y = _lane_loops_exporting(u, delta, A.reshape(dim, n), B.reshape(b, g, n, -1), C.reshape(b, g, n, -1), lanes)
        return y.reshape(dl.size(0), chunk, b, g, dg, lanes)  # the same layout: T = M chunk positions per lane

    # A cloned: a traced tensor, where a constant A (a module's plain attribute) would reach the branches' tracer
    # as a real tensor
    operands = (u, delta, A.clone(), B, C, dl, wl, Bl, Cl, s_mid, mid, end_mid)
    y = torch.cond(bound <= exp_bound, chunked, steps, operands)
    return _from_lanes(y.flatten(0, 1), length)


with warnings.catch_warnings():  # the TorchScript exporter is this module's route: its scripting is wanted here
    warnings.filterwarnings("ignore", message=r".*torch\.jit\.script. is deprecated", category=DeprecationWarning)
    _lane_scan = torch.jit.script(_lane_scan)  # compiles the helpers it calls as well
    _chunk_scan = torch.jit.script(_chunk_scan)


@contextlib.contextmanager
def export_scan_form(form: str | None) -> Iterator[None]:
    """Within the block, :func:`selective_scan_export` takes ``form`` (one of :data:`EXPORT_SCAN_FORMS`) unless told
    otherwise (``None``: the default, :data:`EXPORT_SCAN_FORM`); how an export picks the form of every scan of a
    network (``tofdenoise.inference.export.export_onnx(..., scan_form=...)``)."""
    global _FORM
    if form is not None and form not in EXPORT_SCAN_FORMS:
        raise ValueError(f"export scan form {form!r}; expected one of {', '.join(EXPORT_SCAN_FORMS)}")
    before, _FORM = _FORM, form
    try:
        yield
    finally:
        _FORM = before


_FORM: str | None = None  # the form set by export_scan_form, None: EXPORT_SCAN_FORM


def selective_scan_export(
    u,
    delta,
    A,
    B,
    C,
    D=None,
    delta_bias=None,
    delta_softplus=False,
    state_elems: int = EXPORT_SCAN_STATE_ELEMS,
    form: str | None = None,
    chunk: int = EXPORT_SCAN_CHUNK,
) -> torch.Tensor:
    """mamba-ssm ``selective_scan_fn`` semantics (u, delta (b, dim, L); A (dim, N); B, C (b, groups, N, L) or
    (b, N, L); D, delta_bias (dim,)) as loops over lanes of the sequence; returns (b, dim, L) in u's dtype.
    ``state_elems``: the most elements of a state tensor (at least one lane of b x dim x N is always used).
    ``form``: ``"steps"`` or ``"chunked"`` (chunks of ``chunk`` positions; the step loops where its exponent bound
    fails); ``None``: the form of :func:`export_scan_form`, else :data:`EXPORT_SCAN_FORM`."""
    if state_elems < 1:
        raise ValueError(f"selective_scan_export: state_elems must be >= 1, got {state_elems}")
    if chunk < 1:
        raise ValueError(f"selective_scan_export: chunk must be >= 1, got {chunk}")
    dtype = u.dtype
    u, delta, A = u.float(), delta.float(), A.float()
    if delta_bias is not None:
        delta = delta + delta_bias.float()[None, :, None]
    if delta_softplus:
        delta = F.softplus(delta)
    if B.dim() == 3:
        B, C = B.unsqueeze(1), C.unsqueeze(1)
    form = form or _FORM or EXPORT_SCAN_FORM
    exporting = torch.compiler.is_exporting()
    if form == "chunked":
        scan = _chunk_scan_exporting if exporting else _chunk_scan
        y = scan(u, delta, A, B.float(), C.float(), int(state_elems), int(chunk), float(EXPORT_SCAN_EXP_BOUND))
    elif form == "steps":
        scan = _lane_scan_exporting if exporting else _lane_scan
        y = scan(u, delta, A, B.float(), C.float(), int(state_elems))
    else:
        raise ValueError(f"selective_scan_export: form {form!r}; expected one of {', '.join(EXPORT_SCAN_FORMS)}")
    if D is not None:
        y = y + D.float()[None, :, None] * u
    return y.to(dtype)
