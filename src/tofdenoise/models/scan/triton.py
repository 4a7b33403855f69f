"""The Triton selective-scan kernels for CUDA: a kernel pair (forward + recomputing backward), for the plain
(batch, dim, L) route and for SS2D's four directions read in place. ``auto``
(:func:`~tofdenoise.models.scan.dispatch.resolve_scan_backend`) chooses them on CUDA tensors once
:func:`triton_verified` has passed, with the pure-PyTorch chunked scan as the fallback.

Triton kernels (same recurrence as ``reference.py``: h_t = exp(delta_t A) h_{t-1} + delta_t u_t B_t,
y_t = C_t . h_t + D u_t, with delta_t = softplus(delta_raw_t + delta_bias) computed inside the kernels; the decays
are exp2(delta_t A log2 e)):
- the grid is (batch, block of BLOCK_D channels of one group, segment of the sequence). Each program walks its
  segment in chunks of CHUNK positions; each chunk is loaded as (BLOCK_D, CHUNK) / (N, CHUNK) tiles and its states
  are one ``tl.associative_scan`` of the affine maps h -> a h + b over a (BLOCK_D, N, CHUNK) tile, continued from
  the state carried in from the previous chunk;
- the sequence is cut into segments so that the GPU is filled even when batch x channels is small (DVSS's first
  level at 320 x 320, batch 4, has 256 channel blocks): the forward's first pass (``seg_fwd_kernel``) scans each
  segment from a zero state and keeps its end state and summed delta (its whole decay is exp(A sum delta)); the
  second pass (``fwd_kernel``) carries those over the segments before its own (a short loop), runs its segment
  from that true entry state, writes y and the state entering every chunk (memory L * dim * N / CHUNK);
- the backward's first pass (``seg_bwd_kernel``) gets each segment's adjoints from a zero adjoint after its end;
  the second (``bwd_kernel``) carries the adjoint back over the segments after its own, walks its chunks in
  reverse, recomputes a chunk's states from its checkpoint, gets the adjoint g_t = dy_t C_t + a_{t+1} g_{t+1} by a
  reverse associative scan seeded with the next chunk's adjoint, and uses a_t h_{t-1} = h_t - b_t, so no shifted
  state is needed. dB and dC (shared by the channels of a group) are summed over the program's channels, then
  added with atomics; dA, dD and d(delta_bias) are summed over the program's steps, then added with atomics;
- the *sequential* kernels do the same passes one position per step instead of one chunk per step: a thread holds
  one channel's N states (an (N, BLOCK_D) tile, channels fastest, so the sums over states stay in a thread), and a
  step reads one position's channels, adjacent in memory on the SS2D route. ``seq_fwd_kernel`` is the forward's two
  passes, ``seq_adjoint_kernel`` the backward's first, ``seq_bwd_kernel`` its main pass (a chunk's states are
  recomputed into the program's scratch rows and read back in reverse). :data:`FORWARD`, :data:`ADJOINT` and
  :data:`BACKWARD` choose them on the SS2D route (measured: docs/benchmarks.md), :data:`PLAIN_FORWARD` and
  :data:`PLAIN_ADJOINT` on the plain route;
- SS2D's four directions add their outputs (and u-gradients) into one float32 buffer with atomics, so no
  (b, 4, L, d) buffer is written and summed afterwards. Float32 atomic adds make the last bits of y and of
  the gradients depend on the order in which programs finish.

delta_bias, softplus and the D skip term are applied inside the kernels (their gradients too), and bf16/fp16
u, delta, B, C are read as they are, so SS2D under autocast pays for no conversion copies; everything is
computed in float32. Speed and agreement with the PyTorch scan on an H100 and an H200: docs/benchmarks.md
(``benchmarks/bench_gpu.py``, ``benchmarks/bench_gpu_scan.py``). The ``auto`` dispatch uses the Triton kernels only
after :func:`triton_verified` has checked them against the PyTorch scan on the device (once per process), so a
toolchain problem falls back to the PyTorch scan with a warning instead of wrong results.
"""

from __future__ import annotations

import functools
import os
import warnings

import torch

from .common import check_shapes
from .reference import selective_scan_chunked, ss2d_scan_reference

__all__ = [
    "triton_available",
    "triton_verified",
    "selective_scan_triton",
    "ss2d_scan_triton",
    "interpreting",
    "ckpt_shape",
    "scan_forward",
    "scan_backward",
    "ss2d_forward",
    "ss2d_backward",
]

#: positions per chunk (one associative scan over a (BLOCK_D, N, CHUNK) tile; a state checkpoint per chunk)
CHUNK = 32
#: channels per program: the fastest setting on an H100 at the DVSS training size, float32 and bf16 inputs
#: (``benchmarks/tune_scan_triton.py``; the sweep is in docs/benchmarks.md, "GPU")
BLOCK_D_MAX = 2
#: channels per program of the SS2D route's chunked kernels (channels-last: a block's channels are adjacent in
#: memory). 4 is the largest whose backward compiles for sm_90 without register spills at 4 warps, fp32 and bf16
#: (``benchmarks/triton_resources.py``; 8 spills); on an H200 2, 4 and 8 were within 15 % of each other
#: (``benchmarks/tune_scan_triton.py --ss2d``, docs/benchmarks.md)
SS2D_BLOCK_D_MAX = 4
NUM_WARPS = 4
#: the scan is split along the sequence into segments run side by side (a first pass gives each segment's end state
#: and summed step, a short carry over the segments gives each one's true entry state, a second pass runs each
#: segment from it): as many segments as give about this many programs per multiprocessor (16: the fastest of 8, 16
#: and 32 for the SS2D route at DVSS's first level on an H200, docs/benchmarks.md)
SEGMENT_PROGRAMS_PER_SM = 16
#: no segment shorter than this many chunks (a shorter one costs more in its carry than it gives)
MIN_SEGMENT_CHUNKS = 4
#: chunks per segment for every launch, or None: chosen per launch by :func:`segment_chunks` (the tests and
#: ``benchmarks/tune_scan_triton.py`` set it)
SEGMENT_CHUNKS: int | None = None
#: the SS2D route's forward kernels: "chunked" (``seg_fwd_kernel`` + ``fwd_kernel``: associative scans over
#: (channels, states, chunk) tiles) or "sequential" (``seq_fwd_kernel``: each thread walks its channels' states one
#: step at a time; a step reads one position's adjacent channels). Sequential: 3.0 against 13.6 ms for the forward
#: of DVSS's first level on an H200 in bf16, 3.6 against 12.6 in float32 (docs/benchmarks.md)
FORWARD = "sequential"
#: the backward's first pass: "chunked" (``seg_bwd_kernel``) or "sequential" (``seq_adjoint_kernel``, one step at a
#: time, on its own finer split of the sequence). Sequential: the first level's forward + backward 28.2 against 37.4
#: ms (bf16, H200)
ADJOINT = "sequential"
#: the same two choices for the plain (batch, dim, L) route, where a position's channels are L apart in memory (the
#: sequential kernels' per-step reads would not coalesce; not timed there)
PLAIN_FORWARD = "chunked"
PLAIN_ADJOINT = "chunked"
#: the backward's main pass on the SS2D route: "chunked" (``bwd_kernel``) or "sequential" (``seq_bwd_kernel``: one
#: step at a time, a chunk's states recomputed into scratch rows and read back in reverse; it needs ADJOINT
#: "sequential", whose split it shares). Sequential: the first level's forward + backward 14.6 against 28.0 ms in
#: bf16 (H200, same run; docs/benchmarks.md); 14.2 ms in float32
BACKWARD = "sequential"
#: warps of the sequential backward (64 channels: one channel per thread; with one warp it spills registers; 2
#: against 4 warps on an H200: 14.6 against 21.4 ms for the first level's forward + backward in bf16)
SEQ_BWD_NUM_WARPS = 2
#: channels per program and warps of the sequential kernels (64 / 1: the fastest of 64/1, 64/2, 64/4 and 32/1 on an
#: H200)
SEQ_BLOCK_D_MAX = 64
SEQ_NUM_WARPS = 1
#: positions whose states the sequential backward recomputes into its scratch rows at a time (divides CHUNK; None:
#: the whole chunk). A smaller one keeps less scratch per program (SUB + CHUNK / SUB rows of N x channels float32:
#: 12 instead of 33 at 8), so that all programs' scratch can stay in L2, for one more forward walk per chunk
SEQ_BWD_SUB: int | None = None
#: software-pipelining stages of the sequential forward's step loop
SEQ_STAGES = 3


try:  # kernels at module level: Triton resolves the names a kernel calls (_combine) from its module's globals
    import triton
    import triton.language as tl
except Exception:  # noqa: BLE001 - no Triton (CPU-only install): the PyTorch scan is used
    triton = tl = None

if triton is not None:

    @triton.jit
    def _combine(a1, b1, a2, b2):
        # (a1, b1) then (a2, b2) for h -> a h + b: h -> a2 (a1 h + b1) + b2
        return a1 * a2, a2 * b1 + b2

    @triton.jit
    def _softplus(x):
        # log(1 + e^x) without overflow, and e^x where 1 + e^x rounds to 1 (float32)
        return tl.where(x > 20.0, x, tl.where(x < -15.0, tl.exp(x), tl.log(1.0 + tl.exp(x))))

    @triton.jit
    def _delta_eff(raw_ptr, bias_ptr, offs, d, mask, HAS_BIAS: tl.constexpr, SOFTPLUS: tl.constexpr):
        """(delta after bias and softplus, the pre-softplus value) of a (BLOCK_D, T) tile, in float32; delta is 0
        where ``mask`` is off (a masked step is the identity: decay 1, no input)."""
        x = tl.load(raw_ptr + offs, mask=mask, other=0.0).to(tl.float32)
        if HAS_BIAS:
            x = x + tl.load(bias_ptr + d).to(tl.float32)[:, None]
        if SOFTPLUS:
            dt = _softplus(x)
        else:
            dt = x
        return tl.where(mask, dt, 0.0), x

    @triton.jit
    def _positions(t, grp, L, H, W, SS2D: tl.constexpr):
        """Memory position (int64) of scan step t. Plain layout: t. SS2D: direction grp of an H x W image read
        in place -- 0 row-major, 1 column-major, 2 and 3 the same reversed (``cross_scan``'s order). Steps
        past the end map to position 0 (they are masked)."""
        if SS2D:
            lk = tl.where(grp >= 2, L - 1 - t, t)
            p = tl.where((grp % 2) == 1, (lk % H) * W + lk // H, lk)
            p = tl.where(t < L, p, 0)
        else:
            p = t
        return p.to(tl.int64)

    @triton.jit
    def _program_tiles(
        A_ptr,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        su_b,
        su_c,
        sd_b,
        sd_c,
        sB_b,
        sB_g,
        sB_n,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        SS2D: tl.constexpr,
    ):
        """This program's channels d (of delta, A, D, bias), their u/y channel uc (SS2D: the channel within
        its direction), states n (and mask), chunk steps tt, group grp (SS2D: the direction), its A block
        (times log2 e: the decays are exp2(delta A log2 e)), the base offsets of its u and delta channels and of
        its group's B/C rows, the offsets of its checkpoints and segment carries, and the channel count."""
        pid_b = tl.program_id(0).to(tl.int64)  # 64-bit offsets: batch * dim * L can exceed 2**31
        pid_d = tl.program_id(1)
        DIM = tl.num_programs(1) * BLOCK_D
        d = (pid_d * BLOCK_D + tl.arange(0, BLOCK_D)).to(tl.int64)
        n = tl.arange(0, BLOCK_N)
        tt = tl.arange(0, CHUNK_T)
        nmask = n < N
        grp = ((pid_d * BLOCK_D) // DIM_PER_GROUP).to(tl.int64)
        if SS2D:
            uc = d - grp * DIM_PER_GROUP
        else:
            uc = d
        A = tl.load(A_ptr + d[:, None] * N + n[None, :], mask=nmask[None, :], other=0.0)  # (D, N)
        u_row = pid_b * su_b + uc * su_c  # (D,)
        d_row = pid_b * sd_b + d * sd_c  # (D,)
        bc = pid_b * sB_b + grp * sB_g + n * sB_n  # (N,)
        # checkpoints (batch, chunk, state, channel) and carries (batch, segment, state, channel) /
        # (batch, segment, channel): channels fastest, so that the sequential forward stores whole rows
        ck = pid_b * (NCHUNK * BLOCK_N * DIM) + n[None, :] * DIM + d[:, None]  # chunk c: + c * BLOCK_N * DIM
        cs = pid_b * (tl.num_programs(2) * BLOCK_N * DIM) + n[None, :] * DIM + d[:, None]  # segment s: + s BLOCK_N DIM
        cd = pid_b * (tl.num_programs(2) * DIM) + d  # segment s: + s * DIM
        return pid_b, d, uc, grp, n, tt, nmask, A, A * 1.4426950408889634, u_row, d_row, bc, ck, cs, cd, DIM

    @triton.jit
    def _segment_span(NCHUNK, SEG_CHUNKS):
        """The chunks [c0, c1) of this program's segment (axis 2 of the grid)."""
        c0 = tl.program_id(2) * SEG_CHUNKS
        return c0, tl.minimum(c0 + SEG_CHUNKS, NCHUNK)

    @triton.jit
    def _chunk_states(
        u_ptr,
        delta_ptr,
        bias_ptr,
        B_ptr,
        C_ptr,
        A2,
        h0,
        d,
        u_offs,
        d_offs,
        bc_offs,
        tmask,
        nmask,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
    ):
        """Load one chunk's tiles (at the given offsets) and scan it from the entering state h0: (delta,
        pre-softplus delta, u, B, C, b = delta u B, states h_t), all float32; the states are
        (BLOCK_D, BLOCK_N, CHUNK_T). Masked steps leave the state as it is."""
        bmask = nmask[:, None] & tmask[None, :]
        dt, x = _delta_eff(delta_ptr, bias_ptr, d_offs, d, tmask[None, :], HAS_BIAS, SOFTPLUS)  # (D, T)
        ut = tl.load(u_ptr + u_offs, mask=tmask[None, :], other=0.0).to(tl.float32)
        Bt = tl.load(B_ptr + bc_offs, mask=bmask, other=0.0).to(tl.float32)  # (N, T)
        Ct = tl.load(C_ptr + bc_offs, mask=bmask, other=0.0).to(tl.float32)
        a = tl.exp2(dt[:, None, :] * A2[:, :, None])  # (D, N, T)
        b = (dt * ut)[:, None, :] * Bt[None, :, :]
        a_acc, b_acc = tl.associative_scan((a, b), axis=2, combine_fn=_combine)
        return dt, x, ut, Bt, Ct, b, a_acc * h0[:, :, None] + b_acc

    @triton.jit
    def _chunk_adjoints(
        delta_ptr,
        bias_ptr,
        C_ptr,
        dy_ptr,
        A2,
        g_next,
        d,
        d1_offs,
        bc_offs,
        dy_offs,
        tmask,
        t1mask,
        nmask,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
    ):
        """The adjoints g_t = dy_t C_t + a_{t+1} g_{t+1} of one chunk, a reverse scan seeded with ``g_next`` (the
        adjoint of the next chunk's first step): (g, dy, C, delta at t + 1)."""
        dt1, _ = _delta_eff(delta_ptr, bias_ptr, d1_offs, d, t1mask[None, :], HAS_BIAS, SOFTPLUS)
        dyt = tl.load(dy_ptr + dy_offs, mask=tmask[None, :], other=0.0).to(tl.float32)
        Ct = tl.load(C_ptr + bc_offs, mask=nmask[:, None] & tmask[None, :], other=0.0).to(tl.float32)
        a1 = tl.where(t1mask[None, None, :], tl.exp2(dt1[:, None, :] * A2[:, :, None]), 0.0)
        src = dyt[:, None, :] * Ct[None, :, :]
        ga, gb = tl.associative_scan((a1, src), axis=2, combine_fn=_combine, reverse=True)
        return gb + ga * g_next[:, :, None], dyt, Ct, dt1

    @triton.jit
    def seg_fwd_kernel(
        u_ptr,
        delta_ptr,
        A_ptr,
        B_ptr,
        bias_ptr,
        hend_ptr,
        dsum_ptr,
        L,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        SEG_CHUNKS,
        H,
        W,
        su_b,
        su_c,
        su_l,
        sd_b,
        sd_c,
        sd_l,
        sB_b,
        sB_g,
        sB_n,
        sB_l,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
        SS2D: tl.constexpr,
    ):
        """Forward, first pass: each segment scanned from a zero state; its end state and its summed delta (the
        segment's whole decay is exp(A sum delta))."""
        pid_b, d, uc, grp, n, tt, nmask, A, A2, u_row, d_row, bc, ck, cs, cd, DIM = _program_tiles(
            A_ptr, N, DIM_PER_GROUP, NCHUNK, su_b, su_c, sd_b, sd_c, sB_b, sB_g, sB_n, CHUNK_T, BLOCK_D, BLOCK_N, SS2D
        )
        c0, c1 = _segment_span(NCHUNK, SEG_CHUNKS)
        h = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        dsum = tl.zeros((BLOCK_D,), dtype=tl.float32)
        for c in range(c0, c1):
            t = c * CHUNK_T + tt
            tmask = t < L
            p = _positions(t, grp, L, H, W, SS2D)
            dt, _, _, _, _, _, hs = _chunk_states(
                u_ptr,
                delta_ptr,
                bias_ptr,
                B_ptr,
                B_ptr,
                A2,
                h,
                d,
                u_row[:, None] + p[None, :] * su_l,
                d_row[:, None] + p[None, :] * sd_l,
                bc[:, None] + p[None, :] * sB_l,
                tmask,
                nmask,
                HAS_BIAS,
                SOFTPLUS,
            )
            dsum += tl.sum(dt, axis=1)
            h = tl.sum(tl.where((tt == CHUNK_T - 1)[None, None, :], hs, 0.0), axis=2)
        tl.store(hend_ptr + cs + tl.program_id(2) * BLOCK_N * DIM, h)
        tl.store(dsum_ptr + cd + tl.program_id(2) * DIM, dsum)

    @triton.jit
    def fwd_kernel(
        u_ptr,
        delta_ptr,
        A_ptr,
        B_ptr,
        C_ptr,
        D_ptr,
        bias_ptr,
        hend_ptr,
        dsum_ptr,
        y_ptr,
        ckpt_ptr,
        L,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        SEG_CHUNKS,
        H,
        W,
        su_b,
        su_c,
        su_l,
        sd_b,
        sd_c,
        sd_l,
        sB_b,
        sB_g,
        sB_n,
        sB_l,
        so_b,
        so_g,
        so_c,
        so_l,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_D: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
        SS2D: tl.constexpr,
    ):
        """Forward, second pass: each segment from its true entry state (the first pass's end states carried
        over the segments before it), writing y (SS2D: the four directions added into one float32 buffer) and
        the state entering every chunk."""
        pid_b, d, uc, grp, n, tt, nmask, A, A2, u_row, d_row, bc, ck, cs, cd, DIM = _program_tiles(
            A_ptr, N, DIM_PER_GROUP, NCHUNK, su_b, su_c, sd_b, sd_c, sB_b, sB_g, sB_n, CHUNK_T, BLOCK_D, BLOCK_N, SS2D
        )
        c0, c1 = _segment_span(NCHUNK, SEG_CHUNKS)
        o_row = pid_b * so_b + grp * so_g + uc * so_c
        if HAS_D:
            Dv = tl.load(D_ptr + d).to(tl.float32)
        h = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        for s in range(0, tl.program_id(2)):  # the carry: h <- exp(A sum delta_s) h + end state of segment s
            dec = tl.exp2(A2 * tl.load(dsum_ptr + cd + s * DIM)[:, None])
            h = dec * h + tl.load(hend_ptr + cs + s * BLOCK_N * DIM)
        for c in range(c0, c1):
            tl.store(ckpt_ptr + ck + c * BLOCK_N * DIM, h)  # the state entering chunk c
            t = c * CHUNK_T + tt
            tmask = t < L
            p = _positions(t, grp, L, H, W, SS2D)
            _, _, ut, _, Ct, _, hs = _chunk_states(
                u_ptr,
                delta_ptr,
                bias_ptr,
                B_ptr,
                C_ptr,
                A2,
                h,
                d,
                u_row[:, None] + p[None, :] * su_l,
                d_row[:, None] + p[None, :] * sd_l,
                bc[:, None] + p[None, :] * sB_l,
                tmask,
                nmask,
                HAS_BIAS,
                SOFTPLUS,
            )
            yt = tl.sum(hs * Ct[None, :, :], axis=1)
            if HAS_D:
                yt += Dv[:, None] * ut
            if SS2D:
                tl.atomic_add(y_ptr + o_row[:, None] + p[None, :] * so_l, yt, mask=tmask[None, :], sem="relaxed")
            else:
                tl.store(y_ptr + o_row[:, None] + p[None, :] * so_l, yt, mask=tmask[None, :])
            h = tl.sum(tl.where((tt == CHUNK_T - 1)[None, None, :], hs, 0.0), axis=2)  # state after the chunk

    @triton.jit
    def _seq_step_delta(delta_ptr, d_off, valid, bias, HAS_BIAS: tl.constexpr, SOFTPLUS: tl.constexpr):
        """(delta after bias and softplus, the pre-softplus value) of one position's channels; 0 where not valid."""
        x = tl.load(delta_ptr + d_off, mask=valid, other=0.0).to(tl.float32)
        if HAS_BIAS:
            x = x + bias
        if SOFTPLUS:
            dt = _softplus(x)
        else:
            dt = x
        return tl.where(valid, dt, 0.0), x

    @triton.jit
    def _seq_advance(
        h,
        t,
        grp,
        L,
        H,
        W,
        SS2D: tl.constexpr,
        zero_d,
        nmask,
        A2,
        bias,
        delta_ptr,
        d_row,
        sd_l,
        u_ptr,
        u_row,
        su_l,
        B_ptr,
        bc,
        sB_l,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
    ):
        """The (N, channels) state h one step on, to position step t of the group's walk."""
        valid = (zero_d + t) < L
        p = _positions(t, grp, L, H, W, SS2D)
        dt, _pre = _seq_step_delta(delta_ptr, d_row + p * sd_l, valid, bias, HAS_BIAS, SOFTPLUS)
        ut = tl.load(u_ptr + u_row + p * su_l, mask=valid, other=0.0).to(tl.float32)
        Bt = tl.load(B_ptr + bc + p * sB_l, mask=nmask & (t < L), other=0.0).to(tl.float32)
        return tl.exp2(dt[None, :] * A2) * h + Bt[:, None] * (dt * ut)[None, :]

    @triton.jit
    def seq_fwd_kernel(
        u_ptr,
        delta_ptr,
        A_ptr,
        AT_ptr,
        B_ptr,
        C_ptr,
        D_ptr,
        bias_ptr,
        hend_ptr,
        dsum_ptr,
        y_ptr,
        ckpt_ptr,
        L,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        SEG_CHUNKS,
        H,
        W,
        su_b,
        su_c,
        su_l,
        sd_b,
        sd_c,
        sd_l,
        sB_b,
        sB_g,
        sB_n,
        sB_l,
        so_b,
        so_g,
        so_c,
        so_l,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_D: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
        SS2D: tl.constexpr,
        FIRST_PASS: tl.constexpr,
        STAGES: tl.constexpr,
    ):
        """The forward walked one step at a time: each thread holds its channels' N states in registers and each
        step reads one position's channels (adjacent in memory on the SS2D route) and B / C row, so no scan over a
        tile is needed; the sequence's segments give the parallelism. ``FIRST_PASS``: from a zero state, keep
        each segment's end state and summed delta (as ``seg_fwd_kernel``); else from the carried entry state,
        write y and the state entering every chunk (as ``fwd_kernel``). The states are held as an (N, BLOCK_D)
        tile, channels fastest: Triton then lays a channel's N states in one thread, so the sum over the states is
        a sum within a thread and a step's channel vectors need no change of layout."""
        pid_b, d, uc, grp, n, tt, nmask, _, _, u_row, d_row, bc, ck, cs, cd, DIM = _program_tiles(
            A_ptr, N, DIM_PER_GROUP, NCHUNK, su_b, su_c, sd_b, sd_c, sB_b, sB_g, sB_n, CHUNK_T, BLOCK_D, BLOCK_N, SS2D
        )
        # A transposed (N, dim) by the caller: channels fastest in memory, as in the state tile
        A2 = tl.load(AT_ptr + n[:, None] * DIM + d[None, :], mask=nmask[:, None], other=0.0) * 1.4426950408889634
        ck = tl.trans(ck)  # (N, D) offsets
        cs = tl.trans(cs)
        c0, c1 = _segment_span(NCHUNK, SEG_CHUNKS)
        o_row = pid_b * so_b + grp * so_g + uc * so_c
        bias = tl.zeros((BLOCK_D,), dtype=tl.float32)
        if HAS_BIAS:
            bias = tl.load(bias_ptr + d).to(tl.float32)
        if HAS_D:
            Dv = tl.load(D_ptr + d).to(tl.float32)
        h = tl.zeros((BLOCK_N, BLOCK_D), dtype=tl.float32)
        dsum = tl.zeros((BLOCK_D,), dtype=tl.float32)
        if not FIRST_PASS:
            for s in range(0, tl.program_id(2)):  # the carry, as in fwd_kernel
                dec = tl.exp2(A2 * tl.load(dsum_ptr + cd + s * DIM)[None, :])
                h = dec * h + tl.load(hend_ptr + cs + s * BLOCK_N * DIM)
        zero_d = tl.zeros((BLOCK_D,), dtype=tl.int32)
        for c in range(c0, c1):
            if not FIRST_PASS:
                tl.store(ckpt_ptr + ck + c * BLOCK_N * DIM, h)  # the state entering chunk c
            for i in tl.range(0, CHUNK_T, num_stages=STAGES):  # loads of later steps issued early
                t = c * CHUNK_T + i
                valid = (zero_d + t) < L
                p = _positions(t, grp, L, H, W, SS2D)
                dt, _pre = _seq_step_delta(delta_ptr, d_row + p * sd_l, valid, bias, HAS_BIAS, SOFTPLUS)
                ut = tl.load(u_ptr + u_row + p * su_l, mask=valid, other=0.0).to(tl.float32)
                nvalid = nmask & (t < L)
                Bt = tl.load(B_ptr + bc + p * sB_l, mask=nvalid, other=0.0).to(tl.float32)
                h = tl.exp2(dt[None, :] * A2) * h + Bt[:, None] * (dt * ut)[None, :]
                if FIRST_PASS:
                    dsum += dt
                else:
                    Ct = tl.load(C_ptr + bc + p * sB_l, mask=nvalid, other=0.0).to(tl.float32)
                    yt = tl.sum(h * Ct[:, None], axis=0)
                    if HAS_D:
                        yt += Dv * ut
                    if SS2D:
                        tl.atomic_add(y_ptr + o_row + p * so_l, yt, mask=valid, sem="relaxed")
                    else:
                        tl.store(y_ptr + o_row + p * so_l, yt, mask=valid)
        if FIRST_PASS:
            tl.store(hend_ptr + cs + tl.program_id(2) * BLOCK_N * DIM, h)
            tl.store(dsum_ptr + cd + tl.program_id(2) * DIM, dsum)

    @triton.jit
    def seg_bwd_kernel(
        delta_ptr,
        A_ptr,
        C_ptr,
        bias_ptr,
        dy_ptr,
        gstart_ptr,
        dsum_ptr,
        L,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        SEG_CHUNKS,
        H,
        W,
        sd_b,
        sd_c,
        sd_l,
        sB_b,
        sB_g,
        sB_n,
        sB_l,
        sdy_b,
        sdy_c,
        sdy_l,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
        SS2D: tl.constexpr,
    ):
        """Backward, first pass: each segment's adjoints from a zero adjoint after its end; the adjoint of its
        first step and the delta summed over its steps t0 + 1 .. t1 (the decay from the next segment's first step
        back to its own)."""
        pid_b, d, uc, grp, n, tt, nmask, A, A2, u_row, d_row, bc, ck, cs, cd, DIM = _program_tiles(
            A_ptr, N, DIM_PER_GROUP, NCHUNK, 0, 0, sd_b, sd_c, sB_b, sB_g, sB_n, CHUNK_T, BLOCK_D, BLOCK_N, SS2D
        )
        c0, c1 = _segment_span(NCHUNK, SEG_CHUNKS)
        dy_row = pid_b * sdy_b + uc * sdy_c
        g = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        dsum = tl.zeros((BLOCK_D,), dtype=tl.float32)
        for ci in range(0, c1 - c0):
            c = c1 - 1 - ci
            t = c * CHUNK_T + tt
            tmask = t < L
            t1mask = (t + 1) < L
            p = _positions(t, grp, L, H, W, SS2D)
            p1 = _positions(t + 1, grp, L, H, W, SS2D)
            gs, _, _, dt1 = _chunk_adjoints(
                delta_ptr,
                bias_ptr,
                C_ptr,
                dy_ptr,
                A2,
                g,
                d,
                d_row[:, None] + p1[None, :] * sd_l,
                bc[:, None] + p[None, :] * sB_l,
                dy_row[:, None] + p[None, :] * sdy_l,
                tmask,
                t1mask,
                nmask,
                HAS_BIAS,
                SOFTPLUS,
            )
            dsum += tl.sum(dt1, axis=1)
            g = tl.sum(tl.where((tt == 0)[None, None, :], gs, 0.0), axis=2)
        tl.store(gstart_ptr + cs + tl.program_id(2) * BLOCK_N * DIM, g)
        tl.store(dsum_ptr + cd + tl.program_id(2) * DIM, dsum)

    @triton.jit
    def seq_adjoint_kernel(
        delta_ptr,
        A_ptr,
        AT_ptr,
        C_ptr,
        bias_ptr,
        dy_ptr,
        gstart_ptr,
        dsum_ptr,
        L,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        SEG_CHUNKS,
        H,
        W,
        sd_b,
        sd_c,
        sd_l,
        sB_b,
        sB_g,
        sB_n,
        sB_l,
        sdy_b,
        sdy_c,
        sdy_l,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
        SS2D: tl.constexpr,
    ):
        """The backward's first pass walked one step at a time (what ``seg_bwd_kernel`` computes): each segment's
        adjoints g_t = dy_t C_t + a_{t+1} g_{t+1} from a zero adjoint after its end, a thread per channel holding its
        N adjoints; the adjoint of the segment's first step and the delta summed over its steps t0 + 1 .. t1."""
        pid_b, d, uc, grp, n, tt, nmask, _, _, u_row, d_row, bc, ck, cs, cd, DIM = _program_tiles(
            A_ptr, N, DIM_PER_GROUP, NCHUNK, 0, 0, sd_b, sd_c, sB_b, sB_g, sB_n, CHUNK_T, BLOCK_D, BLOCK_N, SS2D
        )
        A2 = tl.load(AT_ptr + n[:, None] * DIM + d[None, :], mask=nmask[:, None], other=0.0) * 1.4426950408889634
        cs = tl.trans(cs)
        c0, c1 = _segment_span(NCHUNK, SEG_CHUNKS)
        t0 = c0 * CHUNK_T
        t1 = c1 * CHUNK_T
        dy_row = pid_b * sdy_b + uc * sdy_c
        bias = tl.zeros((BLOCK_D,), dtype=tl.float32)
        if HAS_BIAS:
            bias = tl.load(bias_ptr + d).to(tl.float32)
        zero_d = tl.zeros((BLOCK_D,), dtype=tl.int32)
        g = tl.zeros((BLOCK_N, BLOCK_D), dtype=tl.float32)
        a1 = tl.zeros((BLOCK_N, BLOCK_D), dtype=tl.float32)  # the decay of step t + 1 (g is 0 until it is used)
        dsum = tl.zeros((BLOCK_D,), dtype=tl.float32)
        for i in range(0, t1 - t0):
            t = t1 - 1 - i
            valid = (zero_d + t) < L
            p = _positions(t, grp, L, H, W, SS2D)
            nvalid = nmask & (t < L)
            Ct = tl.load(C_ptr + bc + p * sB_l, mask=nvalid, other=0.0).to(tl.float32)
            dyt = tl.load(dy_ptr + dy_row + p * sdy_l, mask=valid, other=0.0).to(tl.float32)
            g = a1 * g + Ct[:, None] * dyt[None, :]
            dt, _pre = _seq_step_delta(delta_ptr, d_row + p * sd_l, valid, bias, HAS_BIAS, SOFTPLUS)
            a1 = tl.exp2(dt[None, :] * A2)
            dsum += tl.where(t > t0, dt, 0.0)
        # the first step of the next segment: its delta links this segment's last adjoint to the carry
        p1 = _positions(t1, grp, L, H, W, SS2D)
        valid1 = (zero_d + t1) < L
        dt1, _pre1 = _seq_step_delta(delta_ptr, d_row + p1 * sd_l, valid1, bias, HAS_BIAS, SOFTPLUS)
        dsum += dt1
        tl.store(gstart_ptr + cs + tl.program_id(2) * BLOCK_N * DIM, g)
        tl.store(dsum_ptr + cd + tl.program_id(2) * DIM, dsum)

    @triton.jit
    def seq_bwd_kernel(
        u_ptr,
        delta_ptr,
        A_ptr,
        AT_ptr,
        B_ptr,
        C_ptr,
        D_ptr,
        bias_ptr,
        dy_ptr,
        ckpt_ptr,
        gstart_ptr,
        dsum_ptr,
        scratch_ptr,
        du_ptr,
        ddelta_ptr,
        dA_ptr,
        dB_ptr,
        dC_ptr,
        dD_ptr,
        dbias_ptr,
        L,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        SEG_CHUNKS,
        H,
        W,
        su_b,
        su_c,
        su_l,
        sd_b,
        sd_c,
        sd_l,
        sB_b,
        sB_g,
        sB_n,
        sB_l,
        so_b,
        so_g,
        so_c,
        so_l,
        sdy_b,
        sdy_c,
        sdy_l,
        sdB_b,
        sdB_g,
        sdB_n,
        sdB_l,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_D: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
        SS2D: tl.constexpr,
        OWN_BC: tl.constexpr,
        SUB_T: tl.constexpr,
    ):
        """The backward's main pass walked one step at a time (what ``bwd_kernel`` computes), a thread per channel
        holding its N states and adjoints: for each chunk of its segment, in reverse, the chunk's states are
        recomputed from its checkpoint into this program's own scratch rows (N x BLOCK_D float32 each; SUB_T
        positions at a time, the sub-chunks in reverse from their entry states, kept in NSUB more rows when
        SUB_T < CHUNK_T), then read back in reverse beside the adjoint g_t = dy_t C_t + a_{t+1} g_{t+1}. The sums
        over states stay in a thread; dB and dC are summed over the program's channels at every step, then stored
        (``OWN_BC``: the program holds all of its group's channels, so no other program writes those positions) or
        added with atomics."""
        pid_b, d, uc, grp, n, tt, nmask, _, _, u_row, d_row, bc, ck, cs, cd, DIM = _program_tiles(
            A_ptr, N, DIM_PER_GROUP, NCHUNK, su_b, su_c, sd_b, sd_c, sB_b, sB_g, sB_n, CHUNK_T, BLOCK_D, BLOCK_N, SS2D
        )
        A = tl.load(AT_ptr + n[:, None] * DIM + d[None, :], mask=nmask[:, None], other=0.0)  # (N, D)
        A2 = A * 1.4426950408889634
        ck = tl.trans(ck)
        cs = tl.trans(cs)
        c0, c1 = _segment_span(NCHUNK, SEG_CHUNKS)
        o_row = pid_b * so_b + grp * so_g + uc * so_c
        dy_row = pid_b * sdy_b + uc * sdy_c
        dbc = pid_b * sdB_b + grp * sdB_g + n * sdB_n
        pid = (tl.program_id(0) * tl.num_programs(1) + tl.program_id(1)) * tl.num_programs(2) + tl.program_id(2)
        NSUB: tl.constexpr = CHUNK_T // SUB_T
        # scratch rows: a sub-chunk's states, then (with sub-chunks) the state entering each sub-chunk
        ROWS: tl.constexpr = SUB_T + NSUB if NSUB > 1 else SUB_T
        rows = pid.to(tl.int64) * (ROWS * BLOCK_N * BLOCK_D) + n[:, None] * BLOCK_D + tl.arange(0, BLOCK_D)[None, :]
        bias = tl.zeros((BLOCK_D,), dtype=tl.float32)
        if HAS_BIAS:
            bias = tl.load(bias_ptr + d).to(tl.float32)
        if HAS_D:
            Dv = tl.load(D_ptr + d).to(tl.float32)
        zero_d = tl.zeros((BLOCK_D,), dtype=tl.int32)
        # the carry: the adjoint of the next segment's first step
        g = tl.zeros((BLOCK_N, BLOCK_D), dtype=tl.float32)
        nseg = tl.num_programs(2)
        for i in range(0, nseg - 1 - tl.program_id(2)):
            s = nseg - 1 - i
            dec = tl.exp2(A2 * tl.load(dsum_ptr + cd + s * DIM)[None, :])
            g = tl.load(gstart_ptr + cs + s * BLOCK_N * DIM) + dec * g
        # the decay of the next segment's first step
        t1 = c1 * CHUNK_T
        dt1, _pre1 = _seq_step_delta(
            delta_ptr, d_row + _positions(t1, grp, L, H, W, SS2D) * sd_l, (zero_d + t1) < L, bias, HAS_BIAS, SOFTPLUS
        )
        a_next = tl.exp2(dt1[None, :] * A2)
        dA_acc = tl.zeros((BLOCK_N, BLOCK_D), dtype=tl.float32)
        dD_acc = tl.zeros((BLOCK_D,), dtype=tl.float32)
        dbias_acc = tl.zeros((BLOCK_D,), dtype=tl.float32)
        row = BLOCK_N * BLOCK_D
        for ci in range(0, c1 - c0):
            c = c1 - 1 - ci
            h = tl.load(ckpt_ptr + ck + c * BLOCK_N * DIM)
            # the state entering each sub-chunk of SUB_T positions, into scratch rows SUB_T + k (one sub-chunk: the
            # checkpoint is that state, and it stays in registers)
            for k in range(0, NSUB - 1):
                tl.store(scratch_ptr + rows + (SUB_T + k) * row, h)
                for i in range(0, SUB_T):
                    h = _seq_advance(
                        h,
                        c * CHUNK_T + k * SUB_T + i,
                        grp,
                        L,
                        H,
                        W,
                        SS2D,
                        zero_d,
                        nmask,
                        A2,
                        bias,
                        delta_ptr,
                        d_row,
                        sd_l,
                        u_ptr,
                        u_row,
                        su_l,
                        B_ptr,
                        bc,
                        sB_l,
                        HAS_BIAS,
                        SOFTPLUS,
                    )
            if NSUB > 1:
                tl.store(scratch_ptr + rows + (SUB_T + NSUB - 1) * row, h)
            for kj in range(0, NSUB):
                k = NSUB - 1 - kj
                if NSUB > 1:
                    h = tl.load(scratch_ptr + rows + (SUB_T + k) * row)
                for i in range(0, SUB_T):  # the sub-chunk's states, forward, into scratch rows 0 .. SUB_T - 1
                    h = _seq_advance(
                        h,
                        c * CHUNK_T + k * SUB_T + i,
                        grp,
                        L,
                        H,
                        W,
                        SS2D,
                        zero_d,
                        nmask,
                        A2,
                        bias,
                        delta_ptr,
                        d_row,
                        sd_l,
                        u_ptr,
                        u_row,
                        su_l,
                        B_ptr,
                        bc,
                        sB_l,
                        HAS_BIAS,
                        SOFTPLUS,
                    )
                    tl.store(scratch_ptr + rows + i * row, h)
                for j in range(0, SUB_T):  # and back, with the adjoints
                    i = SUB_T - 1 - j
                    t = c * CHUNK_T + k * SUB_T + i
                    valid = (zero_d + t) < L
                    nvalid = nmask & (t < L)
                    p = _positions(t, grp, L, H, W, SS2D)
                    dt, x = _seq_step_delta(delta_ptr, d_row + p * sd_l, valid, bias, HAS_BIAS, SOFTPLUS)
                    ut = tl.load(u_ptr + u_row + p * su_l, mask=valid, other=0.0).to(tl.float32)
                    Bt = tl.load(B_ptr + bc + p * sB_l, mask=nvalid, other=0.0).to(tl.float32)
                    Ct = tl.load(C_ptr + bc + p * sB_l, mask=nvalid, other=0.0).to(tl.float32)
                    dyt = tl.load(dy_ptr + dy_row + p * sdy_l, mask=valid, other=0.0).to(tl.float32)
                    h = tl.load(scratch_ptr + rows + i * row)
                    g = a_next * g + Ct[:, None] * dyt[None, :]
                    dtu = dt * ut
                    q = g * (h - Bt[:, None] * dtu[None, :])  # g_t a_t h_{t-1}
                    sr = tl.sum(g * Bt[:, None], axis=0)  # (D,)
                    g_dt = tl.sum(q * A, axis=0) + ut * sr
                    if SOFTPLUS:
                        g_dt = g_dt / (1.0 + tl.exp(-x))
                    g_dt = tl.where(valid, g_dt, 0.0)
                    tl.store(ddelta_ptr + d_row + p * sd_l, g_dt, mask=valid)
                    du = dt * sr
                    if HAS_D:
                        du += Dv * dyt
                        dD_acc += dyt * ut
                    if SS2D:
                        tl.atomic_add(du_ptr + o_row + p * so_l, du, mask=valid, sem="relaxed")
                    else:
                        tl.store(du_ptr + o_row + p * so_l, du, mask=valid)
                    dbias_acc += g_dt
                    dA_acc += q * dt[None, :]
                    dbc_off = dbc + p * sdB_l
                    if OWN_BC:
                        tl.store(dC_ptr + dbc_off, tl.sum(h * dyt[None, :], axis=1), mask=nvalid)
                        tl.store(dB_ptr + dbc_off, tl.sum(g * dtu[None, :], axis=1), mask=nvalid)
                    else:
                        tl.atomic_add(dC_ptr + dbc_off, tl.sum(h * dyt[None, :], axis=1), mask=nvalid, sem="relaxed")
                        tl.atomic_add(dB_ptr + dbc_off, tl.sum(g * dtu[None, :], axis=1), mask=nvalid, sem="relaxed")
                    a_next = tl.exp2(dt[None, :] * A2)
        tl.atomic_add(dA_ptr + d[None, :] * N + n[:, None], dA_acc, mask=nmask[:, None], sem="relaxed")
        if HAS_D:
            tl.atomic_add(dD_ptr + d, dD_acc, sem="relaxed")
        if HAS_BIAS:
            tl.atomic_add(dbias_ptr + d, dbias_acc, sem="relaxed")

    @triton.jit
    def bwd_kernel(
        u_ptr,
        delta_ptr,
        A_ptr,
        B_ptr,
        C_ptr,
        D_ptr,
        bias_ptr,
        dy_ptr,
        ckpt_ptr,
        gstart_ptr,
        dsum_ptr,
        du_ptr,
        ddelta_ptr,
        dA_ptr,
        dB_ptr,
        dC_ptr,
        dD_ptr,
        dbias_ptr,
        L,
        N,
        DIM_PER_GROUP,
        NCHUNK,
        SEG_CHUNKS,
        H,
        W,
        CARRY_SEGS,
        CARRY_PER_SEG,
        su_b,
        su_c,
        su_l,
        sd_b,
        sd_c,
        sd_l,
        sB_b,
        sB_g,
        sB_n,
        sB_l,
        so_b,
        so_g,
        so_c,
        so_l,
        sdy_b,
        sdy_c,
        sdy_l,
        sdB_b,
        sdB_g,
        sdB_n,
        sdB_l,
        CHUNK_T: tl.constexpr,
        BLOCK_D: tl.constexpr,
        BLOCK_N: tl.constexpr,
        HAS_D: tl.constexpr,
        HAS_BIAS: tl.constexpr,
        SOFTPLUS: tl.constexpr,
        SS2D: tl.constexpr,
    ):
        """Backward, second pass: each segment's chunks in reverse from the true adjoint after its end (the first
        pass's adjoints carried back over the segments after it); a chunk's states are recomputed from its
        checkpoint. Every gradient: du (SS2D: the four directions added into one float32 buffer), ddelta, and
        dB / dC / dA / dD / dbias summed over this program's channels before their atomic adds."""
        pid_b, d, uc, grp, n, tt, nmask, A, A2, u_row, d_row, bc, ck, cs, cd, DIM = _program_tiles(
            A_ptr, N, DIM_PER_GROUP, NCHUNK, su_b, su_c, sd_b, sd_c, sB_b, sB_g, sB_n, CHUNK_T, BLOCK_D, BLOCK_N, SS2D
        )
        c0, c1 = _segment_span(NCHUNK, SEG_CHUNKS)
        o_row = pid_b * so_b + grp * so_g + uc * so_c  # du: laid out like y
        dy_row = pid_b * sdy_b + uc * sdy_c  # SS2D: every direction reads the merged output's gradient
        dbc = pid_b * sdB_b + grp * sdB_g + n * sdB_n
        if HAS_D:
            Dv = tl.load(D_ptr + d).to(tl.float32)
        # the carry: the adjoint of the next segment's first step, from the segments after this one
        # (the first pass may have cut the sequence finer: CARRY_PER_SEG of its CARRY_SEGS segments make one here)
        g_next = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        cs = pid_b * (CARRY_SEGS * BLOCK_N * DIM) + n[None, :] * DIM + d[:, None]
        cd = pid_b * (CARRY_SEGS * DIM) + d
        for i in range(0, CARRY_SEGS - (tl.program_id(2) + 1) * CARRY_PER_SEG):
            s = CARRY_SEGS - 1 - i
            dec = tl.exp2(A2 * tl.load(dsum_ptr + cd + s * DIM)[:, None])
            g_next = tl.load(gstart_ptr + cs + s * BLOCK_N * DIM) + dec * g_next
        dA_acc = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        dD_acc = tl.zeros((BLOCK_D,), dtype=tl.float32)
        dbias_acc = tl.zeros((BLOCK_D,), dtype=tl.float32)
        for ci in range(0, c1 - c0):
            c = c1 - 1 - ci
            h0 = tl.load(ckpt_ptr + ck + c * BLOCK_N * DIM)
            t = c * CHUNK_T + tt
            tmask = t < L
            t1mask = (t + 1) < L
            bmask = nmask[:, None] & tmask[None, :]
            p = _positions(t, grp, L, H, W, SS2D)
            p1 = _positions(t + 1, grp, L, H, W, SS2D)
            d_offs = d_row[:, None] + p[None, :] * sd_l
            bc_offs = bc[:, None] + p[None, :] * sB_l
            # recompute the chunk's states from its checkpoint
            dt, x, ut, Bt, Ct, b, hs = _chunk_states(
                u_ptr,
                delta_ptr,
                bias_ptr,
                B_ptr,
                C_ptr,
                A2,
                h0,
                d,
                u_row[:, None] + p[None, :] * su_l,
                d_offs,
                bc_offs,
                tmask,
                nmask,
                HAS_BIAS,
                SOFTPLUS,
            )
            gs, dyt, _, _ = _chunk_adjoints(
                delta_ptr,
                bias_ptr,
                C_ptr,
                dy_ptr,
                A2,
                g_next,
                d,
                d_row[:, None] + p1[None, :] * sd_l,
                bc_offs,
                dy_row[:, None] + p[None, :] * sdy_l,
                tmask,
                t1mask,
                nmask,
                HAS_BIAS,
                SOFTPLUS,
            )
            # a_t h_{t-1} = h_t - b_t (no division, no shifted state)
            q = gs * (hs - b)
            sr = tl.sum(gs * Bt[None, :, :], axis=1)  # (D, T)
            dbc_offs = dbc[:, None] + p[None, :] * sdB_l
            tl.atomic_add(dC_ptr + dbc_offs, tl.sum(dyt[:, None, :] * hs, axis=0), mask=bmask, sem="relaxed")
            tl.atomic_add(dB_ptr + dbc_offs, tl.sum(gs * (dt * ut)[:, None, :], axis=0), mask=bmask, sem="relaxed")
            g_dt = tl.sum(q * A[:, :, None], axis=1) + ut * sr  # d loss / d delta (after softplus)
            if SOFTPLUS:
                g_dt = g_dt / (1.0 + tl.exp(-x))  # softplus' = sigmoid
            g_dt = tl.where(tmask[None, :], g_dt, 0.0)
            tl.store(ddelta_ptr + d_offs, g_dt, mask=tmask[None, :])
            du = dt * sr
            if HAS_D:
                du += Dv[:, None] * dyt
                dD_acc += tl.sum(dyt * ut, axis=1)
            if SS2D:
                tl.atomic_add(du_ptr + o_row[:, None] + p[None, :] * so_l, du, mask=tmask[None, :], sem="relaxed")
            else:
                tl.store(du_ptr + o_row[:, None] + p[None, :] * so_l, du, mask=tmask[None, :])
            dbias_acc += tl.sum(g_dt, axis=1)
            dA_acc += tl.sum(q * dt[:, None, :], axis=2)
            g_next = tl.sum(tl.where((tt == 0)[None, None, :], gs, 0.0), axis=2)
        tl.atomic_add(dA_ptr + d[:, None] * N + n[None, :], dA_acc, mask=nmask[None, :], sem="relaxed")
        if HAS_D:
            tl.atomic_add(dD_ptr + d, dD_acc, sem="relaxed")
        if HAS_BIAS:
            tl.atomic_add(dbias_ptr + d, dbias_acc, sem="relaxed")


def _triton_kernels():
    """(triton, forward kernel, backward kernel), or None without Triton."""
    if triton is None:
        return None
    return triton, fwd_kernel, bwd_kernel


def interpreting() -> bool:
    """True when Triton runs its kernels in the interpreter on CPU tensors (``TRITON_INTERPRET=1``, set before
    this module is imported): how the kernels are tested on a machine without a GPU."""
    return triton is not None and os.environ.get("TRITON_INTERPRET", "0") == "1"


def _interpreter_numpy_shim() -> None:
    """Triton 3.6's interpreter turns a scalar kernel argument used as a loop bound (``range(0, NCHUNK)``)
    into a Python int with ``int(array of shape (1,))``, which NumPy >= 2.4 refuses; take the single element
    instead. Interpreter only: compiled kernels never run this code."""
    try:
        from triton.runtime import interpreter
    except Exception:  # noqa: BLE001 - another Triton layout: nothing to mend
        return
    original = getattr(interpreter, "_patch_lang_tensor", None)
    if original is None or getattr(original, "_tofdenoise_shim", False):
        return

    def patched(tensor, scope):
        original(tensor, scope)
        scope.set_attr(tensor, "__index__", lambda self: int(self.handle.data.reshape(-1)[0]))

    patched._tofdenoise_shim = True  # type: ignore[attr-defined]
    interpreter._patch_lang_tensor = patched


if interpreting():
    _interpreter_numpy_shim()


def triton_available() -> bool:
    """True when CUDA is available and Triton imports."""
    return torch.cuda.is_available() and _triton_kernels() is not None


def _check_device(t: torch.Tensor, name: str) -> None:
    if not (t.is_cuda or interpreting()):
        raise RuntimeError(f"{name}: Triton with a CUDA device is not available (tensors on {t.device})")


def _verify_case(dev: torch.device) -> None:
    """Raise when the kernels disagree with the PyTorch scan on a small random problem on ``dev``: the plain
    (batch, dim, L) route and the SS2D direction-reading route, forward and every gradient, 1e-3 relative."""
    gen = torch.Generator(device="cpu").manual_seed(0)
    batch, dim, length, groups, n = 2, 8, 70, 2, 16  # 3 chunks, the last one partial
    shapes = [
        (batch, dim, length),
        (batch, dim, length),
        (dim, n),
        (batch, groups, n, length),
        (batch, groups, n, length),
        (dim,),
        (dim,),
    ]
    base = [torch.randn(s, generator=gen) for s in shapes]
    base[2] = -torch.exp(0.5 * base[2])
    h, w, di = 5, 7, 4
    ss2d_shapes = [(batch, h * w, di), (batch, h * w, 4 * di), (4 * di, n), (batch, h * w, 4, n), (batch, h * w, 4, n)]
    ss2d = [torch.randn(s, generator=gen) for s in ss2d_shapes] + [torch.randn(4 * di, generator=gen) for _ in "DB"]
    ss2d[2] = -torch.exp(0.5 * ss2d[2])
    cases = [
        (ss2d, lambda *t: ss2d_scan_triton(*t, h, w), lambda *t: ss2d_scan_reference(*t, h, w)),
        (base, lambda *t: selective_scan_triton(*t, delta_softplus=True), lambda *t: selective_scan_chunked(*t, True)),
    ]
    with torch.enable_grad():  # the first call may happen under no_grad (inference)
        for tensors, fn, ref in cases:
            results = []
            for f in (fn, ref):
                ins = [t.to(dev).requires_grad_() for t in tensors]
                y = f(*ins)
                grads = torch.autograd.grad(y.square().sum(), ins)
                results.append([y.detach(), *grads])
            for a, b in zip(*results):
                if not torch.isfinite(a).all() or (a - b).abs().max() > 1e-3 * b.abs().max().clamp_min(1e-6):
                    raise RuntimeError("Triton selective scan disagrees with the PyTorch scan")


@functools.cache
def triton_verified(device_index: int = 0) -> bool:
    """Triton is importable *and* its kernels reproduce the PyTorch scan (plain and SS2D routes, forward and
    all gradients, 1e-3 relative) on a small random problem on this device. Run once per device by the
    ``auto`` dispatch, so a kernel or toolchain problem falls back to the PyTorch scan with a warning instead of
    wrong results."""
    if not triton_available():
        return False
    try:
        _verify_case(torch.device("cuda", device_index))
    except Exception as exc:  # noqa: BLE001 - any failure means: do not use this path
        warnings.warn(f"Triton selective scan disabled ({exc}); using the PyTorch scan", RuntimeWarning, stacklevel=2)
        return False
    return True


def _block_d(dim_per_group: int, block_max: int = BLOCK_D_MAX) -> int:
    """Largest power of two <= block_max dividing the channels per group (a block never straddles two
    groups)."""
    b = block_max
    while dim_per_group % b:
        b //= 2
    return b


@functools.cache
def _multiprocessors(device_index: int) -> int:
    return torch.cuda.get_device_properties(device_index).multi_processor_count


def segment_chunks(nchunk: int, programs: int, device: torch.device) -> int:
    """Chunks per segment for a scan of ``nchunk`` chunks over ``programs`` (batch x channel block) programs: enough
    segments for about :data:`SEGMENT_PROGRAMS_PER_SM` programs per multiprocessor, none shorter than
    :data:`MIN_SEGMENT_CHUNKS` chunks. :data:`SEGMENT_CHUNKS` (when set) overrides the choice; Triton's interpreter
    takes 2, so the tests run the carry between segments."""
    if SEGMENT_CHUNKS is not None:
        return max(1, min(int(SEGMENT_CHUNKS), nchunk))
    if device.type != "cuda":
        return min(2, nchunk)
    index = device.index if device.index is not None else torch.cuda.current_device()
    segments = max(1, -(-SEGMENT_PROGRAMS_PER_SM * _multiprocessors(index) // programs))
    return max(min(MIN_SEGMENT_CHUNKS, nchunk), -(-nchunk // segments))


class _Layout:
    """How the kernels address one call's tensors: the (batch, channel, position) strides of u and of delta,
    the (batch, group, state, position) strides of B and C (which share them) and of dB / dC, the
    (batch, group, channel, position) strides of the output y and du, the grid (batch, channel blocks,
    segments), and the SS2D image size (height 0: the plain (batch, dim, L) route)."""

    def __init__(
        self,
        device,
        batch,
        dim,
        groups,
        n,
        length,
        u_s,
        delta_s,
        bc_s,
        out_s,
        dbc_s,
        height=0,
        width=0,
        block_max=None,
        seg_chunks=None,
    ):
        self._args = (device, batch, dim, groups, n, length, u_s, delta_s, bc_s, out_s, dbc_s, height, width)
        dpg = dim // groups
        if block_max is None:
            block_max = SS2D_BLOCK_D_MAX if height else BLOCK_D_MAX
        self.block_d = _block_d(dpg, block_max)
        self.block_n = triton.next_power_of_2(n)
        self.nchunk = triton.cdiv(length, CHUNK)
        programs = batch * (dim // self.block_d)
        self.seg_chunks = seg_chunks or segment_chunks(self.nchunk, programs, torch.device(device))
        self.nseg = triton.cdiv(self.nchunk, self.seg_chunks)
        self.grid = (batch, dim // self.block_d, self.nseg)
        self.sizes = (length, n, dpg, self.nchunk, self.seg_chunks, height, width)
        self.u_strides, self.delta_strides, self.bc_strides, self.out_strides = u_s, delta_s, bc_s, out_s
        self.dbc_strides = dbc_s
        self.ss2d = bool(height)
        self.batch, self.dim = batch, dim

    def sequential(self) -> _Layout:
        """The same call laid out for the sequential kernels (``SEQ_BLOCK_D_MAX`` channels per program, and the
        segments that this program count asks for)."""
        return _Layout(*self._args, block_max=SEQ_BLOCK_D_MAX)

    def coarsened(self, fine: _Layout) -> _Layout:
        """This layout with segments of a whole number of ``fine``'s (at least as long as its own)."""
        per = -(-self.seg_chunks // fine.seg_chunks)
        return _Layout(*self._args, seg_chunks=per * fine.seg_chunks)

    def constants(self, D, bias, softplus: bool) -> dict:
        return dict(
            CHUNK_T=CHUNK,
            BLOCK_D=self.block_d,
            BLOCK_N=self.block_n,
            HAS_D=D is not None,
            HAS_BIAS=bias is not None,
            SOFTPLUS=bool(softplus),
            SS2D=self.ss2d,
            num_warps=NUM_WARPS,
        )

    def carries(self, device) -> tuple[torch.Tensor, torch.Tensor]:
        """Empty float32 (batch, segments, states, dim) and (batch, segments, dim) buffers for the first pass."""
        f32 = torch.float32
        states = torch.empty(self.batch, self.nseg, self.block_n, self.dim, device=device, dtype=f32)
        return states, torch.empty(self.batch, self.nseg, self.dim, device=device, dtype=f32)


def _channels_last_strides(t: torch.Tensor) -> tuple[int, ...]:
    """(batch, channel, position) strides of a (batch, L, C) tensor; (batch, group, state, position) strides
    of a (batch, L, G, N) tensor."""
    s = t.stride()
    return (s[0], s[2], s[1]) if t.dim() == 3 else (s[0], s[2], s[3], s[1])


def _scan_forward(layout: _Layout, u, delta, A, B, C, D, bias, softplus, y):
    """Run the forward passes (:data:`FORWARD` / :data:`PLAIN_FORWARD` choose the kernels) into ``y`` (SS2D: a
    zeroed float32 buffer the directions are added into); returns the state checkpoints."""
    ckpt = torch.empty(layout.batch, layout.nchunk, layout.block_n, layout.dim, device=u.device, dtype=torch.float32)
    dummy = A  # any float32 tensor: never read when HAS_D / HAS_BIAS is off, or with one segment
    sequential = (FORWARD if layout.ss2d else PLAIN_FORWARD) == "sequential"
    if sequential:
        layout = layout.sequential()
    consts = layout.constants(D, bias, softplus)
    if sequential:
        consts.update(num_warps=SEQ_NUM_WARPS, STAGES=SEQ_STAGES)
    hend, dsum = layout.carries(u.device) if layout.nseg > 1 else (dummy, dummy)
    ins = (u, delta, A, B)
    opt = (dummy if D is None else D, dummy if bias is None else bias)
    shape = (*layout.sizes, *layout.u_strides, *layout.delta_strides, *layout.bc_strides)
    if sequential:
        At = A.t().contiguous()
        for first in (True, False) if layout.nseg > 1 else (False,):
            seq_fwd_kernel[layout.grid](
                u,
                delta,
                A,
                At,
                B,
                C,
                *opt,
                hend,
                dsum,
                y,
                ckpt,
                *shape,
                *layout.out_strides,
                **consts,
                FIRST_PASS=first,
            )
        return ckpt
    if layout.nseg > 1:
        seg_consts = {k: v for k, v in consts.items() if k != "HAS_D"}
        seg_fwd_kernel[layout.grid](*ins, opt[1], hend, dsum, *shape, **seg_consts)
    fwd_kernel[layout.grid](*ins, C, *opt, hend, dsum, y, ckpt, *shape, *layout.out_strides, **consts)
    return ckpt


def _scan_backward(layout: _Layout, saved, softplus, dy, dy_strides, du, dB, dC):
    """Run the backward passes (:data:`ADJOINT` / :data:`PLAIN_ADJOINT` choose the first pass's kernel, :data:`BACKWARD`
    the SS2D route's main pass) into du
    (SS2D: a zeroed float32 buffer) / dB / dC (zeroed float32, given) and new ddelta, dA, dD, dbias; returns those
    four."""
    u, delta, A, B, C, D, bias, ckpt = saved
    ddelta = torch.empty_like(delta)
    dA = torch.zeros_like(A)
    dD = torch.zeros(layout.dim, device=u.device, dtype=torch.float32)
    dbias = torch.zeros(layout.dim, device=u.device, dtype=torch.float32)
    dummy = A
    sequential = (ADJOINT if layout.ss2d else PLAIN_ADJOINT) == "sequential"
    carry = layout
    if sequential:
        carry = layout.sequential()
        layout = layout.coarsened(carry)
    consts = layout.constants(D, bias, softplus)
    walk_back = sequential and layout.ss2d and BACKWARD == "sequential"  # the main pass on the first pass's split
    needs_carry = (carry if walk_back else layout).nseg > 1
    gstart, dsum = carry.carries(u.device) if needs_carry else (dummy, dummy)
    At = A.t().contiguous() if sequential else A  # the sequential kernels read A as (N, dim), channels fastest
    if needs_carry:
        seg_consts = {k: v for k, v in consts.items() if k != "HAS_D"}
        args = (C, dummy if bias is None else bias, dy, gstart, dsum, *carry.sizes)
        strides = (*layout.delta_strides, *layout.bc_strides, *dy_strides)
        if sequential:
            seq = {**seg_consts, "BLOCK_D": carry.block_d, "num_warps": SEQ_NUM_WARPS}
            seq_adjoint_kernel[carry.grid](delta, A, At, *args, *strides, **seq)
        else:
            seg_bwd_kernel[layout.grid](delta, A, *args, *strides, **seg_consts)
    if walk_back:
        own_bc = carry.block_d == carry.sizes[2]  # one program per (batch, group, segment)
        sub = SEQ_BWD_SUB or CHUNK
        if CHUNK % sub:
            raise ValueError(f"SEQ_BWD_SUB must divide CHUNK ({CHUNK}), got {sub}")
        seq = {**consts, "BLOCK_D": carry.block_d, "num_warps": SEQ_BWD_NUM_WARPS, "OWN_BC": own_bc, "SUB_T": sub}
        programs = carry.grid[0] * carry.grid[1] * carry.grid[2]
        rows = sub + (CHUNK // sub if sub < CHUNK else 0)  # a sub-chunk's states, and the state entering each
        scratch = torch.empty(programs * rows * carry.block_n * carry.block_d, device=u.device, dtype=torch.float32)
        seq_bwd_kernel[carry.grid](
            u,
            delta,
            A,
            At,
            B,
            C,
            dummy if D is None else D,
            dummy if bias is None else bias,
            dy,
            ckpt,
            gstart,
            dsum,
            scratch,
            du,
            ddelta,
            dA,
            dB,
            dC,
            dD,
            dbias,
            *carry.sizes,
            *carry.u_strides,
            *carry.delta_strides,
            *carry.bc_strides,
            *carry.out_strides,
            *dy_strides,
            *carry.dbc_strides,
            **seq,
        )
        return ddelta, dA, dD, dbias
    per_seg = layout.seg_chunks // carry.seg_chunks
    bwd_kernel[layout.grid](
        u,
        delta,
        A,
        B,
        C,
        dummy if D is None else D,
        dummy if bias is None else bias,
        dy,
        ckpt,
        gstart,
        dsum,
        du,
        ddelta,
        dA,
        dB,
        dC,
        dD,
        dbias,
        *layout.sizes,
        carry.nseg,
        per_seg,
        *layout.u_strides,
        *layout.delta_strides,
        *layout.bc_strides,
        *layout.out_strides,
        *dy_strides,
        *layout.dbc_strides,
        **consts,
    )
    return ddelta, dA, dD, dbias


def _opt_grad(grad: torch.Tensor, like: torch.Tensor | None) -> torch.Tensor | None:
    return None if like is None else grad.to(like.dtype)


def ckpt_shape(batch: int, dim: int, length: int, n: int) -> tuple[int, int, int, int]:
    """Shape of the float32 state checkpoints the forward saves for the backward: (batch, chunks, states padded to
    a power of two, dim); ``dim`` is 4 d for the SS2D route."""
    return (batch, -(-length // CHUNK), 1 << max(n - 1, 0).bit_length(), dim)


def _plain_layout(u, delta, A, B):
    batch, dim, length = u.shape
    su = u.stride()  # y and du: u's layout, no group offset
    out = (su[0], 0, su[1], su[2])
    return _Layout(
        u.device, batch, dim, B.shape[1], A.shape[1], length, su, delta.stride(), B.stride(), out, B.stride()
    )


def scan_forward(u, delta, A, B, C, D, bias, softplus: bool, checkpoints: bool = True):
    """The plain route's forward on prepared tensors (u, delta (b, dim, L) contiguous in their float dtype; A
    float32 (dim, N); B / C (b, G, N, L) contiguous; D / bias float32 (dim,) or None): ``(y, ckpt)``, y in u's
    dtype, ckpt float32 of :func:`ckpt_shape`, written whatever ``checkpoints`` says (the operator drops it when no
    backward follows)."""
    y = torch.empty(u.shape, device=u.device, dtype=u.dtype)
    ckpt = _scan_forward(_plain_layout(u, delta, A, B), u, delta, A, B, C, D, bias, softplus, y)
    return y, ckpt


def scan_backward(u, delta, A, B, C, D, bias, softplus: bool, ckpt, dy):
    """The plain route's backward: ``(du, ddelta, dA, dB, dC, dD, dbias)`` with du / ddelta / dB / dC in the dtypes
    of u / delta / B / C, dA float32, dD / dbias float32 or None (when D / bias is None)."""
    layout = _plain_layout(u, delta, A, B)
    dy = dy.contiguous()
    du = torch.empty_like(u)
    dB = torch.zeros(B.shape, device=B.device, dtype=torch.float32)  # atomics accumulate in float32
    dC = torch.zeros(C.shape, device=C.device, dtype=torch.float32)
    saved = (u, delta, A, B, C, D, bias, ckpt)
    ddelta, dA, dD, dbias = _scan_backward(layout, saved, softplus, dy, dy.stride(), du, dB, dC)
    return du, ddelta, dA, dB.to(B.dtype), dC.to(C.dtype), _opt_grad(dD, D), _opt_grad(dbias, bias)


def selective_scan_triton(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """Triton selective scan (CUDA, float32 compute); same signature and result as ``selective_scan``. The
    result has u's dtype; bf16/fp16 u, delta, B, C are read as they are (no conversion copies)."""
    if not triton_available() and not interpreting():
        raise RuntimeError("selective_scan_triton: Triton with a CUDA device is not available")
    _check_device(u, "selective_scan_triton")
    B, C, _ = check_shapes(u, delta, A, B, C, D, delta_bias)
    f32 = torch.float32
    y, _ = torch.ops.tofdenoise.selective_scan(
        u.contiguous(),
        delta.contiguous(),
        A.to(f32).contiguous(),
        B.contiguous(),
        C.contiguous(),
        None if D is None else D.to(f32).contiguous(),
        None if delta_bias is None else delta_bias.to(f32).contiguous(),
        bool(delta_softplus),
        "triton",
    )
    return y


def _ss2d_layout(x, delta, A, B, out_strides, height, width):
    batch, length, di = x.shape
    n = A.shape[1]
    return _Layout(
        x.device,
        batch,
        4 * di,
        4,
        n,
        length,
        _channels_last_strides(x),
        _channels_last_strides(delta),
        _channels_last_strides(B),
        out_strides,
        (length * 8 * n, 2 * n, 1, 8 * n),  # dB / dC: halves of a contiguous (b, L, 4, 2N) buffer
        height,
        width,
    )


def ss2d_forward(x, delta, A, B, C, D, bias, height: int, width: int, checkpoints: bool = True):
    """The SS2D route's forward on prepared tensors (see :func:`ss2d_scan_triton`: x (b, L, d) and delta
    (b, L, 4 d) contiguous in their float dtype, A float32 (4 d, N), B / C (b, L, 4, N) with equal strides, D / bias
    float32 (4 d,) or None): ``(y, ckpt)``, y (b, L, d) in x's dtype, ckpt float32 of :func:`ckpt_shape`, written
    whatever ``checkpoints`` says (the operator drops it when no backward follows)."""
    batch, length, di = x.shape
    y = torch.zeros(batch, length, di, device=x.device, dtype=torch.float32)  # the four directions add into it
    s = y.stride()
    layout = _ss2d_layout(x, delta, A, B, (s[0], 0, s[2], s[1]), height, width)
    ckpt = _scan_forward(layout, x, delta, A, B, C, D, bias, True, y)
    return y.to(x.dtype), ckpt


def ss2d_backward(x, delta, A, B, C, D, bias, ckpt, dy, height: int, width: int):
    """The SS2D route's backward: ``(dx, ddelta, dA, dB, dC, dD, dbias)``; dx / ddelta / dB / dC in the dtypes of
    x / delta / B / C, dA float32, dD / dbias float32 or None (when D / bias is None)."""
    batch, length, di = x.shape
    n = B.shape[-1]
    dx = torch.zeros(batch, length, di, device=x.device, dtype=torch.float32)  # the four directions add into it
    s = dx.stride()
    layout = _ss2d_layout(x, delta, A, B, (s[0], 0, s[2], s[1]), height, width)
    dBC = torch.zeros(batch, length, 4, 2 * n, device=x.device, dtype=torch.float32)
    dB, dC = dBC[..., :n], dBC[..., n:]
    saved = (x, delta, A, B, C, D, bias, ckpt)
    ddelta, dA, dD, dbias = _scan_backward(layout, saved, True, dy, _channels_last_strides(dy), dx, dB, dC)
    return (
        dx.to(x.dtype),
        ddelta,
        dA,
        dB.to(B.dtype),
        dC.to(C.dtype),
        _opt_grad(dD, D),
        _opt_grad(dbias, bias),
    )


def ss2d_scan_triton(x, delta, A, B, C, D, delta_bias, height: int, width: int) -> torch.Tensor:
    """The four-direction SS2D scan with softplus on the Triton kernels, reading the directions in place:
    the same contract as :func:`tofdenoise.models.scan.cpu.ss2d_scan_cpu` -- x (b, H W, d) channels-last
    (row-major positions), delta (b, H W, 4 d) raw steps, A (4 d, N), B / C (b, H W, 4, N) with any strides
    (SS2D passes views into its x_proj output), D and delta_bias (4 d,) or None. Direction k of channel c is
    channel k d + c; its step l reads position pi_k(l) (row-major, column-major, both reversed). Returns
    sum_k y_k at each position, (b, H W, d), in x's dtype; bf16/fp16 x, delta, B, C are read as they are,
    computation is float32."""
    if not triton_available() and not interpreting():
        raise RuntimeError("ss2d_scan_triton: Triton with a CUDA device is not available")
    _check_device(x, "ss2d_scan_triton")
    batch, length, di = x.shape
    if length != height * width:
        raise ValueError(f"ss2d_scan_triton: x has {length} positions, expected height x width = {height * width}")
    n = A.shape[-1]
    expect = {"delta": (batch, length, 4 * di), "A": (4 * di, n), "B": (batch, length, 4, n)}
    for name, t, want in (
        ("delta", delta, expect["delta"]),
        ("A", A, expect["A"]),
        ("B", B, expect["B"]),
        ("C", C, expect["B"]),
    ):
        if tuple(t.shape) != want:
            raise ValueError(f"ss2d_scan_triton: {name} has shape {tuple(t.shape)}, expected {want}")
    if B.stride() != C.stride():
        B, C = B.contiguous(), C.contiguous()
    f32 = torch.float32
    y, _ = torch.ops.tofdenoise.ss2d_scan(
        x.contiguous(),
        delta.contiguous(),
        A.to(f32).contiguous(),
        B,
        C,
        None if D is None else D.to(f32).contiguous(),
        None if delta_bias is None else delta_bias.to(f32).contiguous(),
        int(height),
        int(width),
        "triton",
    )
    return y
