"""Tiny numpy/torch shim so the physics equations are written once for both array types.

Imported as ``arrays`` (``from tofdenoise.physics import _backend as arrays``): ``arrays.where``,
``arrays.full_like``, ...; ``xp = arrays.namespace(x)`` is the array library itself (numpy or torch) for the
calls that both spell the same way (``xp.cos``, ``xp.isfinite``).
"""

from __future__ import annotations

from types import ModuleType
from typing import Any

import numpy as np
import torch


def namespace(*arrays: Any) -> ModuleType:
    """`torch` if any argument is a tensor, else `numpy`."""
    return torch if any(isinstance(a, torch.Tensor) for a in arrays) else np


def as_float_array(x: Any, like: Any = None) -> Any:
    """Convert a scalar/list/array to a floating array of the same family as `like` (or `x`)."""
    if isinstance(like, torch.Tensor):
        if isinstance(x, torch.Tensor):
            t = x.to(device=like.device)
        else:
            t = torch.as_tensor(np.asarray(x), device=like.device)
        if not torch.is_floating_point(t):
            t = t.to(like.dtype if torch.is_floating_point(like) else torch.float32)
        return t
    if isinstance(x, torch.Tensor):
        return x if torch.is_floating_point(x) else x.float()
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float64)
    return a


def result_dtype(*arrays: Any) -> Any:
    """The common floating dtype (float64 wins over float32) of numpy arrays or tensors."""
    if any(isinstance(a, torch.Tensor) for a in arrays):
        dtypes = [a.dtype for a in arrays if isinstance(a, torch.Tensor)]
        return torch.float64 if torch.float64 in dtypes else torch.float32
    dtypes = [np.asarray(a).dtype for a in arrays]
    return np.float64 if any(d == np.float64 for d in dtypes) else np.float32


def cast(x: Any, dtype: Any) -> Any:
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return np.asarray(x, dtype=dtype)


def full_like(x: Any, value: float) -> Any:
    if isinstance(x, torch.Tensor):
        return torch.full_like(x, value)
    return np.full_like(x, value)


def where(cond: Any, a: Any, b: Any) -> Any:
    if isinstance(cond, torch.Tensor):
        if not isinstance(a, torch.Tensor):
            a = torch.as_tensor(a, dtype=b.dtype if isinstance(b, torch.Tensor) else None, device=cond.device)
        if not isinstance(b, torch.Tensor):
            b = torch.as_tensor(b, dtype=a.dtype, device=cond.device)
        return torch.where(cond, a, b)
    return np.where(cond, a, b)


def stack_last(items: list[Any]) -> Any:
    if isinstance(items[0], torch.Tensor):
        return torch.stack(items, dim=-1)
    return np.stack(items, axis=-1)
