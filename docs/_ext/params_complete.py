"""Griffe extension of the API reference: a docstring that documents parameters documents all of them.

Griffe itself warns when an ``Args:`` section names a parameter the signature lacks; this extension adds the
other direction. For every function, and every class (its ``__init__``), whose docstring has an ``Args:``
section, each parameter of the signature (``self``, ``cls``, ``*args`` and ``**kwargs`` aside) must have an
entry, or a warning names the missing ones. ``mkdocs build --strict`` (``make
docs``) turns the warning into a failed build.
"""

from __future__ import annotations

from typing import Any

from griffe import Class, DocstringSectionKind, Extension, Function, ParameterKind, logger

_VARIADIC = (ParameterKind.var_positional, ParameterKind.var_keyword)


class ParamsComplete(Extension):
    """Warn about signature parameters missing from a docstring's ``Args:`` section."""

    def on_function(self, *, func: Function, **kwargs: Any) -> None:
        if func.name == "__init__" and func.parent is not None and func.parent.is_class:
            return  # checked through its class, whose docstring documents the constructor
        self._check(func, func.parameters)

    def on_class(self, *, cls: Class, **kwargs: Any) -> None:
        self._check(cls, cls.parameters)

    def _check(self, obj: Function | Class, parameters: Any) -> None:
        if obj.docstring is None:
            return
        sections = obj.docstring.parse("google", warnings=False)
        documented = {
            param.name.lstrip("*")
            for section in sections
            if section.kind is DocstringSectionKind.parameters
            for param in section.value
        }
        if not any(section.kind is DocstringSectionKind.parameters for section in sections):
            return
        missing = [
            p.name
            for p in parameters
            if p.name not in ("self", "cls") and p.name not in documented and p.kind not in _VARIADIC
        ]
        if missing:
            logger.warning(
                f"{obj.relative_filepath}:{obj.docstring.lineno}: parameter(s) {', '.join(missing)} of "
                f"{obj.path} missing from its docstring's Args section"
            )
