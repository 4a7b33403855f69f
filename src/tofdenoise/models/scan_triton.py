"""Optional fused selective-scan paths for CUDA: a Triton kernel pair (forward + recomputing backward) and
mamba-ssm's ``selective_scan_fn`` when its compiled extension imports. Both are chosen automatically by
``tofdenoise.models.selective_scan`` on CUDA tensors, with the pure-PyTorch chunked scan as the fallback.

Triton kernels (same recurrence as ``scan.py``; softplus / delta_bias / D are applied around them in
PyTorch):
- forward: one program per (batch, block of BLOCK_D channels of one group) keeps the (BLOCK_D, N) state in
  registers, walks L sequentially, writes y and a checkpoint of the state at the start of every chunk of
  ``CHUNK`` positions (memory L * dim * N / CHUNK);
- backward: the same programs walk the chunks in reverse; each chunk's states are recomputed from its
  checkpoint into a per-program scratch buffer (CHUNK x BLOCK_D x N, independent of L), then the adjoint
  runs backwards through the chunk. dB and dC (shared by the channels of a group) are accumulated with
  atomic adds; dA is summed over the batch with atomic adds.

Status: written against Triton 3.x and the CPU reference formulas; exercised by the ``gpu``-marked tests
(``tests/models/test_scan.py::test_cuda_backends_match_cpu``) on a CUDA machine only. The development
machine had no GPU, so this path is untested on hardware. As a safeguard, the ``auto`` dispatch prefers
mamba-ssm and uses the Triton kernels only after :func:`triton_verified` has checked them against the
PyTorch scan on the device (once per process); otherwise it falls back to the PyTorch scan.
"""

from __future__ import annotations

import functools
import warnings

import torch

__all__ = [
    "triton_available",
    "triton_verified",
    "mamba_ssm_available",
    "selective_scan_triton",
    "selective_scan_mamba",
]

CHUNK = 64


@functools.lru_cache(maxsize=1)
def _mamba_fn():
    try:  # the compiled extension (selective_scan_cuda) can fail to import even when the package is there
        from mamba_ssm.ops.selective_scan_interface import selective_scan_fn
    except Exception:  # noqa: BLE001 - any import-time failure means "not available"
        return None
    return selective_scan_fn


def mamba_ssm_available() -> bool:
    """True when CUDA is available and mamba-ssm's compiled selective scan imports."""
    return torch.cuda.is_available() and _mamba_fn() is not None


@functools.lru_cache(maxsize=1)
def _triton_kernels():
    try:
        import triton
        import triton.language as tl
    except Exception:  # noqa: BLE001
        return None

    @triton.jit
    def fwd_kernel(
        u_ptr, delta_ptr, A_ptr, B_ptr, C_ptr, y_ptr, ckpt_ptr,
        L, DIM, N, DIM_PER_GROUP, G, NCHUNK,
        CHUNK_T: tl.constexpr, BLOCK_D: tl.constexpr, BLOCK_N: tl.constexpr,
    ):
        pid_b = tl.program_id(0).to(tl.int64)  # 64-bit offsets: batch * dim * L can exceed 2**31
        pid_d = tl.program_id(1)
        d = (pid_d * BLOCK_D + tl.arange(0, BLOCK_D)).to(tl.int64)
        n = tl.arange(0, BLOCK_N)
        nmask = n < N
        grp = ((pid_d * BLOCK_D) // DIM_PER_GROUP).to(tl.int64)
        A = tl.load(A_ptr + d[:, None] * N + n[None, :], mask=nmask[None, :], other=0.0)
        h = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        row = pid_b * DIM * L + d * L
        bc = pid_b * G * N * L + grp * N * L + n * L
        ck = (pid_b * DIM + d)[:, None] * (NCHUNK * BLOCK_N) + n[None, :]
        for c in range(0, NCHUNK):
            tl.store(ckpt_ptr + ck + c * BLOCK_N, h)
            for i in range(0, CHUNK_T):
                t = c * CHUNK_T + i
                valid = t < L
                dt = tl.load(delta_ptr + row + t, mask=(d >= 0) & valid, other=0.0)
                ut = tl.load(u_ptr + row + t, mask=(d >= 0) & valid, other=0.0)
                Bt = tl.load(B_ptr + bc + t, mask=nmask & valid, other=0.0)
                Ct = tl.load(C_ptr + bc + t, mask=nmask & valid, other=0.0)
                a = tl.exp(dt[:, None] * A)
                h = a * h + (dt * ut)[:, None] * Bt[None, :]
                yt = tl.sum(h * Ct[None, :], axis=1)
                tl.store(y_ptr + row + t, yt, mask=(d >= 0) & valid)

    @triton.jit
    def bwd_kernel(
        u_ptr, delta_ptr, A_ptr, B_ptr, C_ptr, dy_ptr, ckpt_ptr, scratch_ptr,
        du_ptr, ddelta_ptr, dA_ptr, dB_ptr, dC_ptr,
        L, DIM, N, DIM_PER_GROUP, G, NCHUNK,
        CHUNK_T: tl.constexpr, BLOCK_D: tl.constexpr, BLOCK_N: tl.constexpr,
    ):
        pid_b = tl.program_id(0).to(tl.int64)  # 64-bit offsets: batch * dim * L can exceed 2**31
        pid_d = tl.program_id(1)
        d = (pid_d * BLOCK_D + tl.arange(0, BLOCK_D)).to(tl.int64)
        n = tl.arange(0, BLOCK_N)
        nmask = n < N
        dmask = d >= 0
        grp = ((pid_d * BLOCK_D) // DIM_PER_GROUP).to(tl.int64)
        A = tl.load(A_ptr + d[:, None] * N + n[None, :], mask=nmask[None, :], other=0.0)
        row = pid_b * DIM * L + d * L
        bc = pid_b * G * N * L + grp * N * L + n * L
        ck = (pid_b * DIM + d)[:, None] * (NCHUNK * BLOCK_N) + n[None, :]
        sc = (pid_b * DIM + d)[:, None] * (CHUNK_T * BLOCK_N) + n[None, :]
        gcarry = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        dA_acc = tl.zeros((BLOCK_D, BLOCK_N), dtype=tl.float32)
        for ci in range(0, NCHUNK):
            c = NCHUNK - 1 - ci
            h0 = tl.load(ckpt_ptr + ck + c * BLOCK_N)
            h = h0
            for i in range(0, CHUNK_T):
                t = c * CHUNK_T + i
                valid = t < L
                dt = tl.load(delta_ptr + row + t, mask=dmask & valid, other=0.0)
                ut = tl.load(u_ptr + row + t, mask=dmask & valid, other=0.0)
                Bt = tl.load(B_ptr + bc + t, mask=nmask & valid, other=0.0)
                h = tl.exp(dt[:, None] * A) * h + (dt * ut)[:, None] * Bt[None, :]
                tl.store(scratch_ptr + sc + i * BLOCK_N, h)
            tl.debug_barrier()
            for i in range(0, CHUNK_T):
                j = CHUNK_T - 1 - i
                t = c * CHUNK_T + j
                valid = t < L
                dt = tl.load(delta_ptr + row + t, mask=dmask & valid, other=0.0)
                ut = tl.load(u_ptr + row + t, mask=dmask & valid, other=0.0)
                dyt = tl.load(dy_ptr + row + t, mask=dmask & valid, other=0.0)
                Bt = tl.load(B_ptr + bc + t, mask=nmask & valid, other=0.0)
                Ct = tl.load(C_ptr + bc + t, mask=nmask & valid, other=0.0)
                h_t = tl.load(scratch_ptr + sc + j * BLOCK_N)
                jm = tl.maximum(j - 1, 0)
                h_prev = tl.where(j > 0, tl.load(scratch_ptr + sc + jm * BLOCK_N), h0)
                a = tl.exp(dt[:, None] * A)
                gr = gcarry + dyt[:, None] * Ct[None, :]
                tl.atomic_add(dC_ptr + bc + t, tl.sum(dyt[:, None] * h_t, axis=0), mask=nmask & valid)
                tl.atomic_add(dB_ptr + bc + t, tl.sum(gr * (dt * ut)[:, None], axis=0), mask=nmask & valid)
                q = gr * a * h_prev
                sr = tl.sum(gr * Bt[None, :], axis=1)
                tl.store(ddelta_ptr + row + t, tl.sum(q * A, axis=1) + ut * sr, mask=dmask & valid)
                tl.store(du_ptr + row + t, dt * sr, mask=dmask & valid)
                dA_acc += q * dt[:, None]
                gcarry = a * gr
            tl.debug_barrier()
        tl.atomic_add(dA_ptr + d[:, None] * N + n[None, :], dA_acc, mask=nmask[None, :])

    return triton, fwd_kernel, bwd_kernel


def triton_available() -> bool:
    """True when CUDA is available and Triton imports."""
    return torch.cuda.is_available() and _triton_kernels() is not None


@functools.lru_cache(maxsize=None)
def triton_verified(device_index: int = 0) -> bool:
    """Triton is importable *and* its kernels reproduce the PyTorch scan (forward and all gradients, 1e-3
    relative) on a small random problem on this device. Run once per device by the ``auto`` dispatch, so a
    kernel or toolchain problem falls back to the PyTorch scan with a warning instead of wrong results."""
    if not triton_available():
        return False
    from .scan import selective_scan_chunked

    try:
        dev = torch.device("cuda", device_index)
        gen = torch.Generator(device="cpu").manual_seed(0)
        batch, dim, length, groups, n = 2, 64, 130, 2, 16
        shapes = [(batch, dim, length), (batch, dim, length), (dim, n), (batch, groups, n, length),
                  (batch, groups, n, length), (dim,), (dim,)]
        base = [torch.randn(s, generator=gen) for s in shapes]
        base[2] = -torch.exp(0.5 * base[2])
        results = []
        with torch.enable_grad():  # the first call may happen under no_grad (inference)
            for fn in (selective_scan_triton, selective_scan_chunked):
                ins = [t.to(dev).requires_grad_() for t in base]
                y = fn(*ins, delta_softplus=True)
                grads = torch.autograd.grad(y.square().sum(), ins)
                results.append([y.detach(), *grads])
        for a, b in zip(*results):
            if not torch.isfinite(a).all() or (a - b).abs().max() > 1e-3 * b.abs().max().clamp_min(1e-6):
                raise RuntimeError("Triton selective scan disagrees with the PyTorch scan")
    except Exception as exc:  # noqa: BLE001 - any failure means: do not use this path
        warnings.warn(f"Triton selective scan disabled ({exc}); using the PyTorch scan", RuntimeWarning, stacklevel=2)
        return False
    return True


def _block_d(dim_per_group: int) -> int:
    """Largest power of two <= 32 dividing the channels per group (a block never straddles two groups)."""
    b = 32
    while dim_per_group % b:
        b //= 2
    return b


class _TritonScanFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, delta, A, B, C):
        triton, fwd_kernel, _ = _triton_kernels()
        batch, dim, length = u.shape
        groups, n = B.shape[1], A.shape[1]
        dpg = dim // groups
        block_d = _block_d(dpg)
        block_n = triton.next_power_of_2(n)
        nchunk = triton.cdiv(length, CHUNK)
        y = torch.empty_like(u)
        ckpt = torch.empty(batch, dim, nchunk, block_n, device=u.device, dtype=torch.float32)
        grid = (batch, dim // block_d)
        fwd_kernel[grid](
            u, delta, A, B, C, y, ckpt, length, dim, n, dpg, groups, nchunk,
            CHUNK_T=CHUNK, BLOCK_D=block_d, BLOCK_N=block_n, num_warps=4,
        )
        ctx.save_for_backward(u, delta, A, B, C, ckpt)
        ctx.meta = (block_d, block_n, nchunk)
        return y

    @staticmethod
    def backward(ctx, dy):
        _, _, bwd_kernel = _triton_kernels()
        u, delta, A, B, C, ckpt = ctx.saved_tensors
        block_d, block_n, nchunk = ctx.meta
        batch, dim, length = u.shape
        groups, n = B.shape[1], A.shape[1]
        dy = dy.contiguous().float()
        du = torch.empty_like(u)
        ddelta = torch.empty_like(delta)
        dA = torch.zeros_like(A)
        dB = torch.zeros_like(B)
        dC = torch.zeros_like(C)
        scratch = torch.empty(batch, dim, CHUNK, block_n, device=u.device, dtype=torch.float32)
        grid = (batch, dim // block_d)
        bwd_kernel[grid](
            u, delta, A, B, C, dy, ckpt, scratch, du, ddelta, dA, dB, dC,
            length, dim, n, dim // groups, groups, nchunk,
            CHUNK_T=CHUNK, BLOCK_D=block_d, BLOCK_N=block_n, num_warps=4,
        )
        return du, ddelta, dA, dB, dC


def selective_scan_triton(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """Triton selective scan (CUDA, float32 compute); same signature and result as ``selective_scan``."""
    from .scan import _check_shapes, _effective_delta, _finish

    if not triton_available():
        raise RuntimeError("selective_scan_triton: Triton with a CUDA device is not available")
    B, C, _ = _check_shapes(u, delta, A, B, C, D, delta_bias)
    dtype = u.dtype
    f32 = torch.float32
    delta = _effective_delta(delta.to(f32), None if delta_bias is None else delta_bias.to(f32), delta_softplus)
    y = _TritonScanFn.apply(
        u.to(f32).contiguous(), delta.contiguous(), A.to(f32).contiguous(),
        B.to(f32).contiguous(), C.to(f32).contiguous(),
    )
    return _finish(y, u.to(f32), None if D is None else D.to(f32)).to(dtype)


def selective_scan_mamba(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """mamba-ssm's CUDA ``selective_scan_fn`` (raises RuntimeError when it cannot be imported)."""
    fn = _mamba_fn()
    if fn is None or not torch.cuda.is_available():
        raise RuntimeError("selective_scan_mamba: mamba_ssm's compiled selective scan is not importable")
    return fn(u, delta, A, B, C, D, z=None, delta_bias=delta_bias, delta_softplus=delta_softplus)
