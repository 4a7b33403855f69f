"""Selective scan written for ONNX export: two loops over the positions of a lane, memory bounded in L.

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
(docs/benchmarks.md, "ONNX export (issue 26)").

The dynamo exporter (``torch.onnx.export(..., dynamo=True)``, ``tofdenoise export --exporter dynamo``) does not
keep scripted loops: ``torch.export`` runs them with the example's sizes and unrolls them, so the graph would only
run at the example's size. Under ``torch.export`` (:func:`torch.compiler.is_exporting`) the same two loops are
therefore written with the ``scan`` higher-order operator (:func:`_lane_scan_exporting`), which becomes ONNX
``Scan`` nodes with a dynamic trip count. That route takes K = ``state_elems`` // (batch x dim x N) lanes whatever
L (a symbolic ``min`` with L would make ``torch.export`` specialise on the size), padding a short sequence to K.
The two routes give the same numbers; tests/models/scan/test_export.py checks both against the reference scan.
"""

from __future__ import annotations

import warnings

import torch
import torch.nn.functional as F

__all__ = ["selective_scan_export", "export_scan_lanes", "EXPORT_SCAN_STATE_ELEMS"]

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
    from torch._higher_order_ops.scan import scan  # torch.export's loop operator; the ONNX exporter lowers it

    lanes = max(1, state_elems // (u.size(0) * u.size(1) * A.size(1)))
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
    _, y = scan(emit, h, (dl, wl, Bl, Cl))  # (T, b, g, dg, K)
    return _from_lanes(y, u.size(2))


with warnings.catch_warnings():  # the TorchScript exporter is this module's route: its scripting is wanted here
    warnings.filterwarnings("ignore", message=r".*torch\.jit\.script. is deprecated", category=DeprecationWarning)
    _lane_scan = torch.jit.script(_lane_scan)  # compiles the helpers it calls as well


def selective_scan_export(
    u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False, state_elems: int = EXPORT_SCAN_STATE_ELEMS
) -> torch.Tensor:
    """mamba-ssm ``selective_scan_fn`` semantics (u, delta (b, dim, L); A (dim, N); B, C (b, groups, N, L) or
    (b, N, L); D, delta_bias (dim,)) as two loops over lanes of the sequence; returns (b, dim, L) in u's dtype.
    ``state_elems``: the most elements of a state tensor (at least one lane of b x dim x N is always used)."""
    if state_elems < 1:
        raise ValueError(f"selective_scan_export: state_elems must be >= 1, got {state_elems}")
    dtype = u.dtype
    u, delta, A = u.float(), delta.float(), A.float()
    if delta_bias is not None:
        delta = delta + delta_bias.float()[None, :, None]
    if delta_softplus:
        delta = F.softplus(delta)
    if B.dim() == 3:
        B, C = B.unsqueeze(1), C.unsqueeze(1)
    lane_scan = _lane_scan_exporting if torch.compiler.is_exporting() else _lane_scan
    y = lane_scan(u, delta, A, B.float(), C.float(), int(state_elems))
    if D is not None:
        y = y + D.float()[None, :, None] * u
    return y.to(dtype)
