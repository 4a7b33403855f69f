"""Backbone registry: backbones are chosen by name and built from plain keyword arguments."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import nn

from tofdenoise.registry import Registry

__all__ = ["BACKBONES", "register_backbone", "build_backbone", "available_backbones"]

BACKBONES: Registry[nn.Module] = Registry("backbone")


def register_backbone(name: str) -> Callable[[Callable[..., nn.Module]], Callable[..., nn.Module]]:
    """Decorator registering a backbone class or factory under ``name``."""
    return BACKBONES.register(name)


def available_backbones() -> list[str]:
    """Registered backbone names, sorted."""
    return sorted(BACKBONES.names())


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
