"""The one place that chooses a selective-scan route: :func:`resolve_scan_backend` (used by :func:`selective_scan` and
by SS2D), :func:`available_scan_backends` and :func:`selective_scan`.

Routes: ``torch`` (the chunked PyTorch scan, :mod:`.reference`), ``sequential`` (its store-every-state baseline),
``cpu`` (the native C++ kernel, :mod:`.cpu`), ``triton`` (the Triton kernels, :mod:`.triton`), ``mamba_ssm``
(:mod:`.mamba`). The kernel modules never import this one; they are imported here lazily, so importing the package
neither builds the CPU kernel nor imports Triton.
"""

from __future__ import annotations

import warnings

import torch

from .common import compile_constant
from .reference import selective_scan_chunked, selective_scan_sequential

__all__ = ["SCAN_BACKENDS", "available_scan_backends", "resolve_scan_backend", "selective_scan"]

SCAN_BACKENDS = ("auto", "cpu", "torch", "sequential", "triton", "mamba_ssm", "export")

_warned: set[str] = set()


def _warn_once(key: str, message: str) -> None:
    if key not in _warned:
        _warned.add(key)
        warnings.warn(message, RuntimeWarning, stacklevel=4)  # past _resolve and resolve_scan_backend


def _cuda_index(dev: torch.device) -> int:
    return dev.index if dev.index is not None else torch.cuda.current_device()


def available_scan_backends(device: torch.device | str | None = None, verify: bool = False) -> list[str]:
    """Backends usable on ``device`` (default: CUDA if available) in ``auto`` preference order; ``torch``
    always last. On CUDA: ``mamba_ssm`` when its compiled extension imports, then ``triton`` when Triton
    imports (with ``verify=True``: only if its kernels pass the on-device self-check). On the CPU: ``cpu``
    (the native kernel of :mod:`.cpu`) when it builds and passes its self-check (this builds it once)."""
    dev = torch.device(device) if device is not None else torch.device("cuda" if torch.cuda.is_available() else "cpu")
    out: list[str] = []
    if dev.type == "cuda":
        from . import triton as scan_triton
        from .mamba import mamba_ssm_available

        if mamba_ssm_available():
            out.append("mamba_ssm")
        if scan_triton.triton_available() and (not verify or scan_triton.triton_verified(_cuda_index(dev))):
            out.append("triton")
    elif dev.type == "cpu":
        from .cpu import cpu_kernel_available

        if cpu_kernel_available():
            out.append("cpu")
    out.append("torch")
    return out


def resolve_scan_backend(backend: str, u: torch.Tensor, ss2d: bool = False) -> str:
    """The route a scan of ``u`` takes for ``backend`` (one of :data:`SCAN_BACKENDS`); the only place that decides.

    - ``auto``: CUDA -> the first of ``available_scan_backends(verify=True)`` (mamba_ssm / triton / torch); with
      ``ss2d=True`` (SS2D's four-direction scan) the verified Triton kernels come before mamba-ssm, since they read
      the four directions in place. CPU -> ``cpu`` for float32/bf16/fp16 when the native kernel builds, else
      ``torch``.
    - ``cpu``: CPU tensors only (a ValueError otherwise). The native kernel, except for float64 input (``torch``
      keeps float64 precision; one warning says so) and when the kernel is not there: a failed build has already
      warned once, naming the PyTorch scan; a kernel switched off by ``TOFDENOISE_SCAN_CPU=0`` warns once here.
    - ``triton`` / ``mamba_ssm``: CUDA tensors only (a ValueError otherwise); a RuntimeError when the package does
      not import. ``torch``, ``sequential`` and ``export`` (two loops over lanes of the
      sequence with memory bounded in L, exported to ONNX as ``Loop`` nodes: ``export.selective_scan_export``) run
      anywhere.
    - anything else: a ValueError naming the valid backends.
    """
    if backend not in SCAN_BACKENDS:
        raise ValueError(f"selective_scan: unknown backend {backend!r}; valid: {', '.join(SCAN_BACKENDS)}")
    if backend == "cpu" and u.is_cuda:
        raise ValueError(f"selective_scan: backend 'cpu' needs CPU tensors, got device {u.device}")
    if backend in ("triton", "mamba_ssm") and not u.is_cuda:
        raise ValueError(f"selective_scan: backend {backend!r} needs CUDA tensors, got device {u.device}")
    return _resolve(backend, u.device, u.dtype, ss2d)


@compile_constant
def _resolve(backend: str, device: torch.device, dtype: torch.dtype, ss2d: bool) -> str:
    """:func:`resolve_scan_backend` past its argument checks. Its answer depends only on its arguments and on
    per-process checks (a kernel's build and self-check), so ``torch.compile`` calls it once while tracing and
    keeps the route as a constant instead of tracing the checks."""
    if backend == "auto":
        if device.type == "cuda":
            choices = available_scan_backends(device, verify=True)
            if ss2d and "triton" in choices:
                return "triton"
            return choices[0]
        from .cpu import cpu_kernel_available

        return "cpu" if dtype != torch.float64 and cpu_kernel_available() else "torch"
    if backend == "cpu":
        from .cpu import ENV_SWITCH, cpu_kernel_available, kernel_switched_off

        if dtype == torch.float64:
            _warn_once(
                "cpu-float64",
                "selective_scan: backend 'cpu' has no float64 kernel; float64 input runs on 'torch' (the chunked "
                "PyTorch scan, float64 precision)",
            )
            return "torch"
        if not cpu_kernel_available():
            if kernel_switched_off():
                _warn_once(
                    "cpu-off",
                    f"selective_scan: backend 'cpu' is switched off ({ENV_SWITCH}=0); using 'torch' (the chunked "
                    "PyTorch scan)",
                )
            return "torch"  # a failed build or self-check has warned once, naming the PyTorch scan
        return "cpu"
    if backend in ("triton", "mamba_ssm"):
        if backend == "triton":
            from .triton import triton_available as available
        else:
            from .mamba import mamba_ssm_available as available
        if not available():
            raise RuntimeError(f"selective_scan: backend {backend!r} is not available (it does not import)")
    return backend


def selective_scan(
    u: torch.Tensor,
    delta: torch.Tensor,
    A: torch.Tensor,
    B: torch.Tensor,
    C: torch.Tensor,
    D: torch.Tensor | None = None,
    delta_bias: torch.Tensor | None = None,
    delta_softplus: bool = False,
    backend: str = "auto",
) -> torch.Tensor:
    """Selective scan (Mamba's S6 recurrence), a drop-in for mamba-ssm's ``selective_scan_fn``.

    Per channel d and state n: h_l = exp(delta_l A[d, n]) h_(l-1) + delta_l B_l[n] u_l,
    y_l = sum_n C_l[n] h_l + D[d] u_l, with delta passed through softplus (after adding ``delta_bias``) when
    ``delta_softplus``. Differentiable on every route.

    Args:
        u: the input, (batch, dim, L).
        delta: the step sizes, same shape as ``u``.
        A: the state matrix, (dim, N), real.
        B: the input projection, (batch, groups, N, L) or (batch, N, L); ``dim`` divisible by ``groups``.
        C: the output projection, same shape as ``B``.
        D: the skip term, (dim,), or None.
        delta_bias: added to ``delta`` before the softplus, (dim,), or None.
        delta_softplus: pass ``delta`` through softplus.
        backend: ``"auto"`` (CUDA: mamba-ssm, else the self-checked Triton kernels, else PyTorch; CPU: the
            native kernel when it builds, else PyTorch), ``"cpu"`` (the native CPU kernel; float64 inputs and a
            failed build fall back to the chunked scan), ``"torch"`` (chunked), ``"sequential"`` (stores all
            states), ``"triton"`` or ``"mamba_ssm"``. ``resolve_scan_backend`` names the route a call takes.

    Returns:
        y, (batch, dim, L), in the dtype of ``u``.

    Raises:
        ValueError: a shape does not fit the others (the message names the argument).
        RuntimeError: ``backend`` names a kernel that is not available here.
    """
    route = resolve_scan_backend(backend, u)
    if route == "cpu":
        from .cpu import selective_scan_cpu as fn
    elif route == "torch":
        fn = selective_scan_chunked
    elif route == "sequential":
        fn = selective_scan_sequential
    elif route == "export":
        from .export import selective_scan_export as fn
    elif route == "triton":
        from .triton import selective_scan_triton as fn
    else:
        from .mamba import selective_scan_mamba as fn
    return fn(u, delta, A, B, C, D, delta_bias, delta_softplus)
