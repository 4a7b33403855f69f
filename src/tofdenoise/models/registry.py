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
    """Decorator registering a backbone class or factory under ``name`` (returned unchanged).

    ```python
    @register_backbone("mynet")
    class MyNet(nn.Module):
        def __init__(self, in_channels: int = 1, width: int = 32) -> None: ...
    ```

    Args:
        name: the name ``build_backbone``, ``backbone=`` of the configs and ``tofdenoise train`` use (matched
            without regard to case).
        trainable: False for a method without trainable parameters (a classical filter, evaluated by
            ``tofdenoise classic`` and never trained).

    Raises:
        ValueError: the name is already registered for another factory.
    """
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

    Args:
        name: a registered name (``available_backbones()``), e.g. ``"dvss"`` or ``"unet"``.
        **kwargs: the backbone's constructor arguments (``in_channels``, ``width`` ...), plain values only, so
            that checkpoints load with ``weights_only=True``.

    Raises:
        ValueError: an unknown name (the valid ones are listed), a keyword argument the backbone does not accept
            (the accepted ones are listed) or a keyword given an ``nn.Module``.
    """
    for key, value in kwargs.items():
        if isinstance(value, nn.Module):
            raise ValueError(f"backbone {name!r}: keyword {key!r} must be a plain value, got an nn.Module")
    return BACKBONES.build(name, **kwargs)
