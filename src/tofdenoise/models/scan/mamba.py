"""mamba-ssm's compiled CUDA selective scan (``selective_scan_fn``), used when its extension imports."""

from __future__ import annotations

import functools

import torch

__all__ = ["mamba_ssm_available", "selective_scan_mamba"]


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


def selective_scan_mamba(u, delta, A, B, C, D=None, delta_bias=None, delta_softplus=False) -> torch.Tensor:
    """mamba-ssm's CUDA ``selective_scan_fn`` (raises RuntimeError when it cannot be imported)."""
    fn = _mamba_fn()
    if fn is None or not torch.cuda.is_available():
        raise RuntimeError("selective_scan_mamba: mamba_ssm's compiled selective scan is not importable")
    return fn(u, delta, A, B, C, D, z=None, delta_bias=delta_bias, delta_softplus=delta_softplus)
