"""Backbone registry: backbones are chosen by name and built from plain keyword arguments.

A backbone is registered as trainable (a network, trained by ``tofdenoise-train``) or not (a classical filter
without parameters, such as ``bilateral``: tuned and evaluated by ``tofdenoise-classic``)."""

from __future__ import annotations

import inspect
from typing import Any, Callable

from torch import nn

__all__ = ["register_backbone", "build_backbone", "available_backbones", "trainable_backbones", "is_trainable",
           "backbone_factory", "accepts_kwarg"]

_REGISTRY: dict[str, Callable[..., nn.Module]] = {}
_NOT_TRAINABLE: set[str] = set()


def register_backbone(name: str,
                      trainable: bool = True) -> Callable[[Callable[..., nn.Module]], Callable[..., nn.Module]]:
    """Decorator registering a backbone class or factory under ``name``; ``trainable=False`` for a method
    without trainable parameters (a classical filter)."""

    def deco(factory: Callable[..., nn.Module]) -> Callable[..., nn.Module]:
        if name in _REGISTRY and _REGISTRY[name] is not factory:
            raise ValueError(f"backbone name {name!r} is already registered")
        _REGISTRY[name] = factory
        if not trainable:
            _NOT_TRAINABLE.add(name)
        return factory

    return deco


def available_backbones() -> list[str]:
    """Registered backbone names (networks and classical filters), sorted."""
    return sorted(_REGISTRY)


def trainable_backbones() -> list[str]:
    """Registered backbones with trainable parameters (the networks ``tofdenoise-train`` trains), sorted."""
    return sorted(n for n in _REGISTRY if n not in _NOT_TRAINABLE)


def is_trainable(name: str) -> bool:
    """Whether the backbone registered as ``name`` has trainable parameters (ValueError for an unknown name)."""
    backbone_factory(name)
    return name not in _NOT_TRAINABLE


def backbone_factory(name: str) -> Callable[..., nn.Module]:
    """The class or factory registered as ``name`` (its class attributes state input requirements)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown backbone {name!r}; valid names: {', '.join(available_backbones())}")
    return _REGISTRY[name]


def accepts_kwarg(name: str, key: str) -> bool:
    """Whether the backbone ``name`` names the keyword argument ``key`` in its signature (``**kwargs`` aside)."""
    return key in _accepted_kwargs(backbone_factory(name))[0]


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
    factory = backbone_factory(name)
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
