"""Backbone registry: backbones are chosen by name and built from plain keyword arguments."""

from __future__ import annotations

import inspect
from typing import Any, Callable

from torch import nn

__all__ = ["register_backbone", "build_backbone", "available_backbones"]

_REGISTRY: dict[str, Callable[..., nn.Module]] = {}


def register_backbone(name: str) -> Callable[[Callable[..., nn.Module]], Callable[..., nn.Module]]:
    """Decorator registering a backbone class or factory under ``name``."""

    def deco(factory: Callable[..., nn.Module]) -> Callable[..., nn.Module]:
        if name in _REGISTRY and _REGISTRY[name] is not factory:
            raise ValueError(f"backbone name {name!r} is already registered")
        _REGISTRY[name] = factory
        return factory

    return deco


def available_backbones() -> list[str]:
    """Registered backbone names, sorted."""
    return sorted(_REGISTRY)


def _accepted_kwargs(factory: Callable[..., nn.Module]) -> tuple[list[str], bool]:
    sig = inspect.signature(factory)
    names = [p.name for p in sig.parameters.values() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    var_kw = any(p.kind == p.VAR_KEYWORD for p in sig.parameters.values())
    return names, var_kw


def build_backbone(name: str, **kwargs: Any) -> nn.Module:
    """Build the backbone registered as ``name`` with plain keyword arguments.

    Raises ValueError for an unknown name (listing the valid ones) or for keyword arguments the
    backbone does not accept (listing the accepted ones).
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown backbone {name!r}; valid names: {', '.join(available_backbones())}")
    factory = _REGISTRY[name]
    accepted, var_kw = _accepted_kwargs(factory)
    unknown = sorted(k for k in kwargs if k not in accepted)
    if unknown and not var_kw:
        raise ValueError(
            f"backbone {name!r} got unexpected keyword argument(s) {unknown}; accepted: {', '.join(accepted)}"
        )
    for key, value in kwargs.items():
        if isinstance(value, nn.Module):
            raise ValueError(f"backbone {name!r}: keyword {key!r} must be a plain value, got an nn.Module")
    return factory(**kwargs)
