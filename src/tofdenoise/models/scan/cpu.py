"""Native CPU selective scan: a C++ kernel (``csrc/selective_scan_cpu.cpp``) built on first use.

The kernel computes the recurrence of :mod:`tofdenoise.models.scan.reference` in float32 with delta_bias, softplus and
the D skip term fused, forward and a recomputing backward (gradients for u, delta, A, B, C, D, delta_bias):

* one task per (batch, block of 16 channels), run in parallel by ``at::parallel_for`` (torch's threads); the
  16 channels are the vector lanes and the N states of a block (N x 16 floats) stay in L1, so no
  (batch, dim, N, L) tensor exists;
* exp(delta A) -- one per state update, the cost of the scan -- is a range reduction by ln 2 and a polynomial
  written branch-free, so that the loop over lanes vectorises (``-O3 -march=native``); AVX-512 builds take
  ``2^(delta A log2 e)`` by ``vreduceps`` / ``vscalefps`` instead, forward and backward;
* SS2D's dt projection can run inside the kernel (:func:`ss2d_forward_lowrank` for inference,
  :func:`ss2d_forward_lowrank_train` / :func:`ss2d_backward_lowrank` for training), so that no (b, L, 4 d) tensor
  of steps or of their gradient is written;
* the forward saves the state entering every chunk of ``CHUNK`` positions; the backward walks the chunks in
  reverse, recomputes a chunk's states and decays from its checkpoint and runs the adjoint recursion.

Inputs are channels-last, (batch, L, channels), so SS2D hands its activations over without the
``cross_scan`` copies: :func:`ss2d_scan_cpu` reads the four scan directions (row-major, column-major, both
reversed) of an H x W image by index arithmetic and sums their outputs (``cross_merge``) inside the kernel.
The entry points (:func:`selective_scan_cpu`, :func:`ss2d_scan_cpu`) call the ``tofdenoise::selective_scan`` /
``tofdenoise::ss2d_scan`` custom operators of :mod:`.ops` (autograd, ``torch.compile``), whose CPU implementations
are :func:`scan_forward` / :func:`scan_backward` / :func:`ss2d_forward` / :func:`ss2d_backward` here.

Build: ``torch.utils.cpp_extension.load`` compiles the source once into torch's per-user extension cache
(``TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``); the module name carries a hash of the
source, the flags and this CPU's model and flags, so an edited source or another CPU type gets its own build.
It builds from a copy of the source in that cache (:func:`stable_source`), so clones and worktrees with the same
source share the build instead of rebuilding it in turn.
Any failure (no compiler, no ninja, a compile error, a failed self-check against the PyTorch scan) gives one
warning and :func:`cpu_kernel_available` returns False: callers then use the chunked PyTorch scan.
``TOFDENOISE_SCAN_CPU=0`` in the environment disables the kernel without trying to build it.
torch holds a ``lock`` file in the build folder while it builds and makes every other process wait for it, silently
and without limit; a build killed on the way (SIGKILL, out of memory, a stopped process) leaves the file behind.
:func:`clear_stale_build_lock` removes a lock older than :data:`STALE_LOCK_S` with a warning naming it, and names a
younger one that the process is about to wait on.
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import shutil
import sys
import time
import warnings
from pathlib import Path

import torch

from tofdenoise.atomic import atomic_write_bytes

from .common import check_shapes, check_ss2d_shapes, compile_constant
from .reference import selective_scan_chunked

__all__ = [
    "cpu_kernel_available",
    "kernel_switched_off",
    "load_extension",
    "selective_scan_cpu",
    "ss2d_scan_cpu",
    "scan_forward",
    "scan_backward",
    "ss2d_forward",
    "ss2d_backward",
    "ss2d_forward_lowrank",
    "ss2d_forward_lowrank_train",
    "ss2d_backward_lowrank",
    "ss2d_out_gate",
    "ckpt_shape",
    "CHUNK",
    "LANES",
]

#: positions per checkpoint chunk (the backward recomputes one chunk of states at a time)
CHUNK = 64
#: channels per task of the kernel (its vector lanes, ``W`` in the C++ source)
LANES = 16
SOURCE = Path(__file__).resolve().parent / "csrc" / "selective_scan_cpu.cpp"
#: -fopenmp: at::parallel_for is a header template whose OpenMP backend is a ``#pragma omp parallel``; compiled
#: without it, the pragma is ignored and every task runs on the calling thread (measured: 1 and 2 threads gave the
#: same time). The extension then binds to the libgomp.so.1 that libtorch_cpu has already loaded (same soname).
CFLAGS = ["-O3", "-march=native", "-ffp-contract=fast", "-fno-math-errno", "-fno-trapping-math", "-fopenmp"]
LDFLAGS = ["-fopenmp"]
ENV_SWITCH = "TOFDENOISE_SCAN_CPU"
#: a build takes about a minute on 2 cores: a build lock older than this was left by a build that never finished
STALE_LOCK_S = 600.0


def _cpu_signature() -> str:
    """CPU model and feature flags (a -march=native build must not be reused on another CPU type)."""
    info = platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("model name", "flags", "Features")):
                info += line
                if line.startswith(("flags", "Features")):
                    break
    except OSError:
        pass
    return info


def _build_name() -> str:
    digest = hashlib.sha256()
    digest.update(SOURCE.read_bytes())
    digest.update(" ".join(CFLAGS + LDFLAGS).encode())
    digest.update(_cpu_signature().encode())
    digest.update(torch.__version__.encode())
    return f"tofdenoise_scan_cpu_{digest.hexdigest()[:12]}"


def _ninja_on_path() -> None:
    """cpp_extension runs ``ninja`` from PATH; the ``ninja`` wheel (a dependency) installs it next to this
    interpreter, which is not on PATH when the venv is not activated (``.venv/bin/python -m pytest``)."""
    if shutil.which("ninja") is None:
        here = Path(sys.executable).parent
        if (here / "ninja").exists():
            os.environ["PATH"] = str(here) + os.pathsep + os.environ.get("PATH", "")


def stable_source(name: str) -> Path:
    """A copy of ``SOURCE`` at a path that does not depend on the checkout: ``<torch extensions root>/
    tofdenoise_sources/<name>.cpp`` (``name`` carries the source's hash). ninja rebuilds when a source path
    changes, so building from each checkout's own file rebuilt the kernel (about a minute) whenever another
    clone or worktree had built it last; every checkout with the same source now shares one build."""
    from torch.utils.cpp_extension import get_default_build_root

    root = os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()  # torch's own rule
    target = Path(root) / "tofdenoise_sources" / f"{name}.cpp"
    data = SOURCE.read_bytes()
    if not target.is_file() or target.read_bytes() != data:
        atomic_write_bytes(target, data)
    return target


def kernel_switched_off() -> bool:
    """True when ``TOFDENOISE_SCAN_CPU`` (0/false/no/off) switches the kernel off: no build is attempted."""
    return os.environ.get(ENV_SWITCH, "1").strip().lower() in ("0", "false", "no", "off")


def clear_stale_build_lock(build_dir: str | os.PathLike[str], max_age_s: float = STALE_LOCK_S) -> bool:
    """Remove torch's build lock ``<build_dir>/lock`` when it is older than ``max_age_s`` seconds (a build killed on
    the way left it; torch would wait for it forever), with a warning naming it; warn that the process will wait when
    a younger one is there (another process is building). Returns True when a lock was removed."""
    lock = Path(build_dir) / "lock"
    try:
        age_s = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return False
    if age_s <= max_age_s:
        warnings.warn(
            f"tofdenoise: another process is building the native CPU selective scan (lock file {lock}, "
            f"{age_s:.0f} s old); waiting for it",
            RuntimeWarning,
            stacklevel=2,
        )
        return False
    try:
        lock.unlink()
    except FileNotFoundError:  # its builder finished meanwhile
        return False
    warnings.warn(
        f"tofdenoise: removed a stale build lock of the native CPU selective scan ({lock}, {age_s / 60:.0f} min "
        "old): a build was killed before it finished",
        RuntimeWarning,
        stacklevel=2,
    )
    return True


@functools.lru_cache(maxsize=1)
def load_extension():
    """The compiled extension module, or None (with one warning) when it cannot be built or loaded."""
    if kernel_switched_off():
        return None
    try:
        from torch.utils import cpp_extension

        _ninja_on_path()
        name = _build_name()
        clear_stale_build_lock(cpp_extension._get_build_directory(name, verbose=False))
        return cpp_extension.load(
            name=name, sources=[str(stable_source(name))], extra_cflags=CFLAGS, extra_ldflags=LDFLAGS, verbose=False
        )
    except Exception as exc:  # noqa: BLE001 - any build/load failure means "use the PyTorch scan"
        warnings.warn(
            f"tofdenoise: the native CPU selective scan could not be built ({type(exc).__name__}: "
            f"{str(exc).strip().splitlines()[-1][:200] if str(exc).strip() else ''}); using the pure-PyTorch "
            f"chunked scan (slower). Needs a C++ compiler and ninja; set {ENV_SWITCH}=0 to skip the attempt.",
            RuntimeWarning,
            stacklevel=2,
        )
        return None


@functools.lru_cache(maxsize=1)
def cpu_kernel_available() -> bool:
    """True when the extension builds and agrees with the chunked PyTorch scan on a small case (checked once
    per process; a disagreement gives a warning and False)."""
    ext = load_extension()
    if ext is None:
        return False
    g = torch.Generator().manual_seed(0)
    u = torch.randn(2, 20, 37, generator=g)
    delta = 0.5 * torch.randn(2, 20, 37, generator=g)
    A = -torch.exp(0.5 * torch.randn(20, 5, generator=g))
    B, C = torch.randn(2, 2, 5, 37, generator=g), torch.randn(2, 2, 5, 37, generator=g)
    D, bias = torch.randn(20, generator=g), torch.randn(20, generator=g)
    try:
        got = selective_scan_cpu(u, delta, A, B, C, D, bias, True)
    except Exception as exc:  # noqa: BLE001
        warnings.warn(
            f"tofdenoise: the native CPU selective scan failed its self-check ({exc}); using the PyTorch scan",
            RuntimeWarning,
            stacklevel=2,
        )
        return False
    want = selective_scan_chunked(u, delta, A, B, C, D, bias, True)
    err = ((got - want).abs().max() / want.abs().max()).item()
    if not err < 1e-4:
        warnings.warn(
            f"tofdenoise: the native CPU selective scan disagrees with the PyTorch scan (relative error "
            f"{err:.1e}); using the PyTorch scan",
            RuntimeWarning,
            stacklevel=2,
        )
        return False
    return True


def ckpt_shape(batch: int, groups: int, dim_per_group: int, length: int, n: int) -> tuple[int, ...]:
    """Shape of the float32 state checkpoints ``scan_fwd`` returns: the state entering every chunk of
    :data:`CHUNK` positions, per (batch, block of :data:`LANES` channels, group, chunk, state, lane)."""
    return (batch, -(-dim_per_group // LANES), groups, -(-length // CHUNK), n, LANES)


@compile_constant
def _kernel_loaded() -> bool:
    """True when the extension is there (built once per process). A constant to ``torch.compile``, which would
    otherwise trace into the build."""
    return load_extension() is not None


def _extension(name: str):
    ext = load_extension()
    if ext is None:
        raise RuntimeError(f"{name}: the native CPU kernel is not available (see the build warning)")
    return ext


def _opt(t: torch.Tensor | None) -> torch.Tensor | None:
    return None if t is None else t.contiguous()


def scan_forward(u, delta, A, B, C, D, bias, softplus: bool, checkpoints: bool = True):
    """The plain route's forward on prepared float32 tensors: u, delta (b, dim, L) contiguous, A (dim, N)
    contiguous, B / C (b, G, N, L) with any strides (fastest: channels-last memory, a (b, L, G, N) tensor seen
    through ``permute(0, 2, 3, 1)``), D / bias (dim,) or None. Returns ``(y, ckpt)``, y (b, dim, L) contiguous,
    ckpt of :func:`ckpt_shape`. The kernel reads u and delta as (b, L, dim) views (gathered lanes)."""
    ext = _extension("selective_scan_cpu")
    y, ckpt = ext.scan_fwd(
        u.transpose(1, 2),
        delta.transpose(1, 2),
        A,
        B.permute(0, 3, 1, 2),
        C.permute(0, 3, 1, 2),
        _opt(D),
        _opt(bias),
        bool(softplus),
        False,
        0,
        0,
        CHUNK if checkpoints else 0,  # 0: no backward follows, the kernel keeps no checkpoints
    )
    return y.transpose(1, 2), ckpt


def scan_backward(u, delta, A, B, C, D, bias, softplus: bool, ckpt, dy):
    """The plain route's backward: ``(du, ddelta, dA, dB, dC, dD, dbias)``, float32; du / ddelta (b, dim, L)
    contiguous, dB / dC (b, G, N, L) views of (b, L, G, N) memory; dD / dbias are computed with or without D / bias
    (the callers drop them)."""
    ext = _extension("selective_scan_cpu")
    du, ddelta, dA, dB, dC, dD, dbias = ext.scan_bwd(
        u.transpose(1, 2),
        delta.transpose(1, 2),
        A,
        B.permute(0, 3, 1, 2),
        C.permute(0, 3, 1, 2),
        _opt(D),
        _opt(bias),
        bool(softplus),
        False,
        0,
        0,
        CHUNK,
        ckpt,
        dy.transpose(1, 2),
    )
    return du.transpose(1, 2), ddelta.transpose(1, 2), dA, dB.permute(0, 2, 3, 1), dC.permute(0, 2, 3, 1), dD, dbias


def ss2d_forward(x, delta, A, B, C, D, bias, height: int, width: int, checkpoints: bool = True):
    """The SS2D route's forward on prepared float32 tensors (x (b, L, d), delta (b, L, 4 d), A (4 d, N)
    contiguous; B / C (b, L, 4, N) with any strides; D / bias (4 d,) or None): ``(y, ckpt)``, y (b, L, d)
    contiguous, ckpt of :func:`ckpt_shape`."""
    ext = _extension("ss2d_scan_cpu")
    chunk = CHUNK if checkpoints else 0  # 0: no backward follows, the kernel keeps no checkpoints
    return tuple(ext.scan_fwd(x, delta, A, B, C, _opt(D), _opt(bias), True, True, int(height), int(width), chunk))


def ss2d_backward(x, delta, A, B, C, D, bias, ckpt, dy, height: int, width: int):
    """The SS2D route's backward: ``(dx, ddelta, dA, dB, dC, dD, dbias)``, float32 and contiguous (dD / dbias
    computed with or without D / bias)."""
    ext = _extension("ss2d_scan_cpu")
    return tuple(
        ext.scan_bwd(x, delta, A, B, C, _opt(D), _opt(bias), True, True, int(height), int(width), CHUNK, ckpt, dy)
    )


#: the largest dt_rank :func:`ss2d_forward_lowrank` takes (the kernel's RMAX)
LOWRANK_MAX_RANK = 64


def ss2d_forward_lowrank(x, dt_low, dt_weight, A, B, C, D, bias, height: int, width: int) -> torch.Tensor:
    """The SS2D route's forward with SS2D's dt projection fused into the kernel, for inference (no checkpoints,
    no backward): the raw steps ``delta[b, p, k d + c] = sum_j dt_low[b, p, k, j] dt_weight[k, c, j]`` are computed
    per position as the kernel reads them, instead of being written to and read back from a (b, L, 4 d) tensor
    (315 MB per block at DVSS's first level of a 480 x 640 frame). x (b, L, d) and dt_low / B / C (b, L, 4, .)
    float32 with any strides (dt_low, B and C: slices of x_proj's output), dt_weight (4, d, R), A (4 d, N),
    D / bias (4 d,) or None. Returns y (b, L, d), equal to :func:`ss2d_forward` on the projected steps to
    rounding (bit for bit where the batched product sums in the kernel's order, as on the 2-core CPU measured)."""
    ext = _extension("ss2d_scan_cpu")
    return ext.ss2d_fwd_lowrank(
        x, dt_low, _flat_dt_weight(dt_weight), A, B, C, _opt(D), _opt(bias), int(height), int(width)
    )


def _flat_dt_weight(dt_weight: torch.Tensor) -> torch.Tensor:
    """SS2D's dt weights (4, d, R) as the (4 d, R) contiguous matrix the kernel reads."""
    k, d, r = dt_weight.shape
    return dt_weight.reshape(k * d, r).contiguous()


def ss2d_forward_lowrank_train(x, dt_low, dt_weight, A, B, C, D, bias, height: int, width: int):
    """:func:`ss2d_forward_lowrank` for training: ``(y, ckpt)`` with the checkpoints of :func:`ss2d_forward` and
    the training forward's arithmetic; the inputs as there."""
    ext = _extension("ss2d_scan_cpu")
    return tuple(
        ext.ss2d_fwd_lowrank_train(
            x, dt_low, _flat_dt_weight(dt_weight), A, B, C, _opt(D), _opt(bias), int(height), int(width), CHUNK
        )
    )


def ss2d_backward_lowrank(x, dt_low, dt_weight, A, B, C, D, bias, ckpt, dy, height: int, width: int):
    """The backward of :func:`ss2d_forward_lowrank_train`: ``(dx, d dt_low, dA, dB, dC, dD, dbias, d dt_weight)``,
    float32 and contiguous, d dt_low (b, L, 4, R) and d dt_weight of dt_weight's shape (4, d, R). The steps are
    recomputed from dt_low and their gradient goes straight into the projection's two products: no (b, L, 4 d)
    tensor of steps or of their gradient exists (16.8 MB each per block at DVSS's first level of a 64 x 64 batch-4
    training step)."""
    ext = _extension("ss2d_scan_cpu")
    *grads, dw = ext.ss2d_bwd_lowrank(
        x, dt_low, _flat_dt_weight(dt_weight), A, B, C, _opt(D), _opt(bias), int(height), int(width), CHUNK, ckpt, dy
    )
    return (*grads, dw.view(dt_weight.shape))


def ss2d_out_gate(
    y: torch.Tensor, z: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, eps: float
) -> torch.Tensor:
    """SS2D's output stage for inference, in place on y: ``layer_norm(y, (d,), weight, bias, eps) * silu(z)`` row by
    row in one pass (torch runs three, each writing a (rows, d) tensor). y (rows, d) contiguous float32, z (rows, d)
    float32 with unit channel stride (any row stride), weight / bias (d,). Returns y; equal to torch's to rounding."""
    ext = _extension("ss2d_scan_cpu")
    return ext.ss2d_out_gate(y, z, weight.contiguous(), bias.contiguous(), float(eps))


def _channels_last_bc(t: torch.Tensor) -> torch.Tensor:
    """(b, G, N, L) -> the same shape over (b, L, G, N) memory: one cache line per step for the kernel, not N."""
    return t.permute(0, 3, 1, 2).contiguous().permute(0, 2, 3, 1)


def selective_scan_cpu(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """``selective_scan`` on the native kernel (the ``tofdenoise::selective_scan`` operator): mamba-ssm's shapes
    (u, delta (batch, dim, L); B, C (batch, groups, N, L) or (batch, N, L)); CPU tensors, computed in float32 and
    returned in u's dtype (callers route float64 to the PyTorch scan to keep float64 precision). B and C are
    copied once to channels-last memory."""
    if not _kernel_loaded():
        raise RuntimeError("selective_scan_cpu: the native CPU kernel is not available (see the build warning)")
    B, C, _ = check_shapes(u, delta, A, B, C, D, delta_bias)
    if u.device.type != "cpu":
        raise ValueError(f"selective_scan_cpu: CPU tensors expected, got device {u.device}")
    f = torch.float32
    y, _ = torch.ops.tofdenoise.selective_scan(
        u.to(f),
        delta.to(f),
        A.to(f),
        _channels_last_bc(B.to(f)),
        _channels_last_bc(C.to(f)),
        None if D is None else D.to(f),
        None if delta_bias is None else delta_bias.to(f),
        bool(delta_softplus),
        "cpu",
        _needs_backward(u, delta, A, B, C, D, delta_bias),
    )
    return y.to(u.dtype)


def ss2d_scan_cpu(x, delta, A, B, C, D, delta_bias, height: int, width: int) -> torch.Tensor:
    """The four-direction SS2D scan with softplus, read in spatial order (the ``tofdenoise::ss2d_scan``
    operator): x (b, H W, d) channels-last (row-major positions), delta (b, H W, 4 d) raw steps, A (4 d, N),
    B / C (b, H W, 4, N) (any strides), D and delta_bias (4 d,) or None. Direction k of channel c is channel
    k d + c; its step l reads position pi_k(l) (row-major, column-major, both reversed). Returns sum_k y_k at
    each position, (b, H W, d) -- ``cross_merge(selective_scan(cross_scan(x), ...))`` without the layout copies.
    CPU tensors, computed in float32 and returned in x's dtype."""
    if not _kernel_loaded():
        raise RuntimeError("ss2d_scan_cpu: the native CPU kernel is not available (see the build warning)")
    check_ss2d_shapes("ss2d_scan_cpu", x, delta, A, B, C, D, delta_bias, height, width)
    if x.device.type != "cpu":
        raise ValueError(f"ss2d_scan_cpu: CPU tensors expected, got device {x.device}")
    f = torch.float32
    y, _ = torch.ops.tofdenoise.ss2d_scan(
        x.to(f),
        delta.to(f),
        A.to(f),
        B.to(f),
        C.to(f),
        None if D is None else D.to(f),
        None if delta_bias is None else delta_bias.to(f),
        int(height),
        int(width),
        "cpu",
        _needs_backward(x, delta, A, B, C, D, delta_bias),
    )
    return y.to(x.dtype)


def _needs_backward(*tensors) -> bool:
    """True when autograd records this call (grad mode on and an input that needs a gradient): only then does the
    kernel keep its checkpoints."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)
