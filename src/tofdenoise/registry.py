"""One way to choose things by name: backbones, losses, noise models and data sources each keep a ``Registry``.

A registry maps a lower-case name to a factory (a class or a function taking plain keyword arguments):

- ``register(name)``: decorator adding a factory under ``name`` (the same name twice for another factory is an
  error).
- ``build(name, **kwargs)``: the one place a name and its keyword arguments are checked: an unknown name raises
  ValueError naming the kind of thing and listing the valid names; a keyword the factory does not accept raises
  ValueError naming the keyword and listing the accepted ones (a factory with ``**kwargs`` accepts any).
- ``names()``: the registered names in registration order; ``name in registry`` checks a name.

Names are matched without regard to case (``build_loss("L1")`` builds ``l1``).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any, Generic, TypeVar

__all__ = ["Registry"]

T = TypeVar("T")


class Registry(Generic[T]):
    """Named factories of one kind.

    ```python
    LOSSES: Registry[DepthLoss] = Registry("loss")
    LOSSES.register("l1")(L1DepthLoss)
    LOSSES.build("L1")  # an L1DepthLoss; names are matched without regard to case
    ```

    Args:
        kind: what error messages call the things registered: "backbone", "loss", ...
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._factories: dict[str, Callable[..., T]] = {}

    def register(self, name: str) -> Callable[[Callable[..., T]], Callable[..., T]]:
        """Decorator registering a class or factory function under ``name`` (returned unchanged).

        Args:
            name: a non-empty name, stored in lower case.

        Raises:
            ValueError: the name is empty, or already registered for another factory.
        """
        key = self._key(name)

        def deco(factory: Callable[..., T]) -> Callable[..., T]:
            if key in self._factories and self._factories[key] is not factory:
                raise ValueError(f"{self.kind} name {key!r} is already registered")
            self._factories[key] = factory
            return factory

        return deco

    def names(self) -> list[str]:
        """Registered names, in registration order."""
        return list(self._factories)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and self._key(name) in self._factories

    def get(self, name: str) -> Callable[..., T]:
        """The factory registered as ``name``.

        Args:
            name: the registered name (any case).

        Raises:
            ValueError: no factory has that name; the message lists the valid names.
        """
        key = self._key(name)
        if key not in self._factories:
            raise ValueError(f"unknown {self.kind} {name!r}; valid names: {', '.join(sorted(self._factories))}")
        return self._factories[key]

    def accepted_kwargs(self, name: str) -> tuple[list[str], bool]:
        """The keyword arguments the factory of ``name`` accepts, read from its signature.

        Args:
            name: the registered name (any case).

        Returns:
            The keyword names, and whether the factory also takes ``**kwargs``.
        """
        params = inspect.signature(self.get(name)).parameters.values()
        accepted = [p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
        return accepted, any(p.kind == p.VAR_KEYWORD for p in params)

    def build(self, name: str, /, **kwargs: Any) -> T:
        """Call the factory of ``name`` with ``kwargs`` after checking the name and every keyword.

        Args:
            name: the registered name (any case).
            **kwargs: the factory's keyword arguments.

        Raises:
            ValueError: an unknown name (the valid ones are listed) or a keyword the factory does not accept (the
                accepted ones are listed; a factory with ``**kwargs`` accepts any).
        """
        factory = self.get(name)
        accepted, var_keyword = self.accepted_kwargs(name)
        unknown = sorted(k for k in kwargs if k not in accepted)
        if unknown and not var_keyword:
            raise ValueError(
                f"{self.kind} {self._key(name)!r} got unexpected keyword argument(s) "
                f"{', '.join(map(repr, unknown))}; accepted: {', '.join(accepted) or 'none'}"
            )
        return factory(**kwargs)

    def _key(self, name: str) -> str:
        if not isinstance(name, str) or not name:
            raise ValueError(f"{self.kind} name must be a non-empty string, got {name!r}")
        return name.lower()

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, names={self.names()})"
