"""Selective scan written for ONNX export: plain tensor operations, no loop over the sequence.

``selective_scan_export`` computes what :func:`tofdenoise.models.scan.selective_scan_ref` computes (same
arguments) with a Hillis-Steele parallel scan of the linear recurrence h_t = a_t h_{t-1} + b_t: step s combines
every position with the one 2**s before it, ``(a, b) <- (a * a_prev, a * b_prev + b)``, with identity elements
(a = 1, b = 0) shifted in at the start. After ``steps`` steps every position holds the scan over up to
2**steps positions, so the result is exact (up to the order of float additions) for sequences up to
``2**steps`` long; the loop is over the fixed ``steps`` (unrolled in the exported graph), the length stays
symbolic. Only decays in (0, 1] are multiplied, as in the sequential scan.

Cost: every step reads and writes the whole state (batch, dim, N, L), so memory is that of the full state
(no chunking, unlike the training scan) and work is ``steps`` x L dim N: fine for small frames, heavy for large
ones (docs/denoise.md, "ONNX export").
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["selective_scan_export", "EXPORT_SCAN_STEPS"]

#: doubling steps of the export scan: exact for sequences up to 2**20 positions (a 1024 x 1024 frame)
EXPORT_SCAN_STEPS = 20


def selective_scan_export(
    u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False, steps: int = EXPORT_SCAN_STEPS
) -> torch.Tensor:
    """mamba-ssm ``selective_scan_fn`` semantics (u, delta (b, dim, L); A (dim, N); B, C (b, groups, N, L) or
    (b, N, L); D, delta_bias (dim,)) as a fixed number of tensor steps; returns (b, dim, L) in u's dtype."""
    dtype = u.dtype
    u, delta, A = u.float(), delta.float(), A.float()
    if delta_bias is not None:
        delta = delta + delta_bias.float()[None, :, None]
    if delta_softplus:
        delta = F.softplus(delta)
    if B.dim() == 3:
        B, C = B.unsqueeze(1), C.unsqueeze(1)
    rep = u.shape[1] // B.shape[1]
    Bx = B.float().repeat_interleave(rep, dim=1)  # (b, dim, N, L)
    Cx = C.float().repeat_interleave(rep, dim=1)
    a = torch.exp(delta.unsqueeze(2) * A[None, :, :, None])  # (b, dim, N, L)
    h = (delta * u).unsqueeze(2) * Bx
    length = u.shape[-1]
    for s in range(steps):
        off = 1 << s
        a_prev = F.pad(a, (off, 0), value=1.0)[..., :length]
        h_prev = F.pad(h, (off, 0), value=0.0)[..., :length]
        h = a * h_prev + h
        a = a * a_prev
    y = (h * Cx).sum(dim=2)
    if D is not None:
        y = y + D.float()[None, :, None] * u
    return y.to(dtype)
