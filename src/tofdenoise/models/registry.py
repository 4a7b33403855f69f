"""Backbone registry: backbones are chosen by name and built from plain keyword arguments.

A backbone is registered as trainable (a network, trained by ``tofdenoise train``) or not (a classical filter
without parameters, such as ``bilateral``: tuned and evaluated by ``tofdenoise classic``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import nn

from tofdenoise.registry import Registry

__all__ = [
    "BACKBONES",
    "register_backbone",
    "build_backbone",
    "available_backbones",
    "trainable_backbones",
    "is_trainable",
    "backbone_factory",
    "accepts_kwarg",
]

BACKBONES: Registry[nn.Module] = Registry("backbone")
#: registered names of methods without trainable parameters (classical filters)
_NOT_TRAINABLE: set[str] = set()


def register_backbone(
    name: str, trainable: bool = True
) -> Callable[[Callable[..., nn.Module]], Callable[..., nn.Module]]:
    """Decorator registering a backbone class or factory under ``name``; ``trainable=False`` for a method
    without trainable parameters (a classical filter)."""
    register = BACKBONES.register(name)

    def deco(factory: Callable[..., nn.Module]) -> Callable[..., nn.Module]:
        register(factory)
        if not trainable:
            _NOT_TRAINABLE.add(name.lower())
        return factory

    return deco


def available_backbones() -> list[str]:
    """Registered backbone names (networks and classical filters), sorted."""
    return sorted(BACKBONES.names())


def trainable_backbones() -> list[str]:
    """Registered backbones with trainable parameters (the networks ``tofdenoise train`` trains), sorted."""
    return sorted(n for n in BACKBONES.names() if n not in _NOT_TRAINABLE)


def is_trainable(name: str) -> bool:
    """Whether the backbone registered as ``name`` has trainable parameters (ValueError for an unknown name)."""
    BACKBONES.get(name)
    return name.lower() not in _NOT_TRAINABLE


def backbone_factory(name: str) -> Callable[..., nn.Module]:
    """The class or factory registered as ``name`` (its class attributes state input requirements)."""
    return BACKBONES.get(name)


def accepts_kwarg(name: str, key: str) -> bool:
    """Whether the backbone ``name`` names the keyword argument ``key`` in its signature (``**kwargs`` aside)."""
    return key in BACKBONES.accepted_kwargs(name)[0]


def build_backbone(name: str, **kwargs: Any) -> nn.Module:
    """Build the backbone registered as ``name`` with plain keyword arguments.

    Raises ValueError for an unknown name (listing the valid ones), for keyword arguments the backbone does not
    accept (listing the accepted ones) or for a keyword given an ``nn.Module`` (hyper-parameters stay plain
    values so checkpoints load with ``weights_only=True``).
    """
    for key, value in kwargs.items():
        if isinstance(value, nn.Module):
            raise ValueError(f"backbone {name!r}: keyword {key!r} must be a plain value, got an nn.Module")
    return BACKBONES.build(name, **kwargs)
