"""Checks on a command's output path, made before anything is read or written.

An output file must not destroy what the command reads or what a run records: ``tofdenoise-eval --out
pred/s0.png`` once replaced a prediction with JSON, ``tofdenoise-report runs --out runs/good/metrics.json`` a
run's metrics with HTML. :func:`check_output_file` refuses

- a path that is an existing folder;
- a path without one of the command's extensions (``.json`` for eval, ``.html`` for the report);
- a path that is one of the input files, or that lies in an input folder next to an input of the same name
  stem (``pred/s0.json`` beside ``pred/s0.png``): such a file would pass for, or shadow, an input.

Errors are :class:`OutputPathError` (a ``ValueError``) whose message names the path and what was expected.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

__all__ = ["OutputPathError", "check_output_file"]


class OutputPathError(ValueError):
    """The output path would overwrite an input or a record, or is not a file of the expected kind."""


def _resolved(path: Path) -> Path:
    return Path(os.path.realpath(path.expanduser()))


def check_output_file(
    out: str | os.PathLike[str], suffixes: Iterable[str], inputs: Iterable[Path] = (), what: str = "--out"
) -> Path:
    """Return ``out`` as a Path after the checks in the module docstring; ``inputs`` are the files read."""
    out = Path(out)
    allowed = tuple(s.lower() for s in suffixes)
    if out.is_dir():
        raise OutputPathError(f"{what} {out} is a folder; give a file name such as {out / ('result' + allowed[0])}")
    if out.suffix.lower() not in allowed:
        raise OutputPathError(
            f"{what} {out}: expected a {' or '.join(allowed)} file, got "
            f"{out.suffix or 'no extension'} (refusing to write where an input or a run "
            f"record might live)"
        )
    target = _resolved(out)
    for path in inputs:
        src = _resolved(Path(path))
        if src == target:
            raise OutputPathError(f"{what} {out} is one of the inputs ({path}); choose another output file")
        if src.parent == target.parent and src.stem == target.stem:
            raise OutputPathError(
                f"{what} {out} lies in the input folder {Path(path).parent} next to the input "
                f"{Path(path).name} of the same name; choose another output file"
            )
    return out
