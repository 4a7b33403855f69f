"""The one guard every writing command runs before it writes: an output never replaces one of its inputs.

``tofdenoise evaluate --out pred/s0.png`` once replaced a prediction with JSON, ``tofdenoise denoise --npy f/b.npy
--out f`` a frame with its own output, ``tofdenoise sensor calibrate --out SWEEP/index.json`` the capture index and
``tofdenoise reproduce --page docs/results/discussion.md`` the discussion it reads. :func:`refuse_overwrite`
checks every output path of a command against every input it reads, before anything is written, and refuses

- an output that is an input (the same path after symlinks, or the same file through a hard link);
- an output that already exists inside an input folder (it would replace a file of that folder);
- an output folder that holds an input (``output_folders``: the command writes names of its own choosing there);
- with ``shadow=True``: an output in the folder of an input file with the same name stem (``pred/s0.json``
  beside ``pred/s0.png``): it would pass for, or shadow, that input the next time the folder is read.

:func:`check_output_file` adds the checks of a single output file (not a folder, one of the command's suffixes)
and then runs :func:`refuse_overwrite`. Refusals are :class:`OutputPathError` (a ``ValueError``): one line that
names the output and the input it would replace; the commands print it and exit with status 2.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

__all__ = ["OutputPathError", "check_output_file", "refuse_overwrite"]


class OutputPathError(ValueError):
    """An output path would overwrite an input or a record, or is not a file of the expected kind."""


def _resolved(path: str | os.PathLike[str]) -> Path:
    return Path(os.path.realpath(Path(path).expanduser()))


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a == b or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def refuse_overwrite(
    outputs: Iterable[str | os.PathLike[str]],
    inputs: Iterable[str | os.PathLike[str]],
    what: str = "--out",
    *,
    output_folders: Iterable[str | os.PathLike[str]] = (),
    shadow: bool = False,
) -> None:
    """Raise :class:`OutputPathError` when an output would replace an input (rules in the module docstring).

    ``outputs``: the files the command will write; ``inputs``: the files and folders it reads (an input file need
    not exist yet: a path the command would read once it exists counts too); ``output_folders``: folders the
    command fills with names of its own choosing; ``what``: the option named in the message."""
    ins = [(Path(i), _resolved(i)) for i in inputs]
    for out in outputs:
        target = _resolved(out)
        for given, src in ins:
            if _same_file(target, src):
                raise OutputPathError(f"{what} {out} would replace the input {given}; choose another output")
            if src.is_dir() and target.is_relative_to(src) and target.exists():
                raise OutputPathError(
                    f"{what} {out} would replace {target.relative_to(src)} of the input folder {given}; "
                    "choose another output"
                )
            if shadow and src.parent == target.parent and src.stem == target.stem and not src.is_dir():
                raise OutputPathError(
                    f"{what} {out} lies in the input folder {given.parent} next to the input {given.name} of the "
                    "same name and would pass for it; choose another output"
                )
    for folder in output_folders:
        target = _resolved(folder)
        for given, src in ins:
            if _same_file(target, src) or src.is_relative_to(target):
                raise OutputPathError(
                    f"{what} {folder}: the output folder holds the input {given}, which its files could replace; "
                    "choose another output folder"
                )


def check_output_file(
    out: str | os.PathLike[str],
    suffixes: Iterable[str],
    inputs: Iterable[str | os.PathLike[str]] = (),
    what: str = "--out",
    shadow: bool = True,
) -> Path:
    """``out`` as a Path once it is known to be a file name with one of ``suffixes`` that replaces no input
    (:func:`refuse_overwrite`; ``shadow`` on by default: a result beside an input of the same name is refused)."""
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
    refuse_overwrite([out], inputs, what, shadow=shadow)
    return out
