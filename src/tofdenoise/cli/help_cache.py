"""The help text of Lightning's verbs (``tofdenoise fit|validate|test|predict --help``), kept between calls.

LightningCLI builds its help from the classes' signatures and docstrings, so it imports torch and Lightning first:
about 5 s on an idle 2-core machine, where every other help text of ``tofdenoise`` takes under 0.1 s. The text of a
bare ``tofdenoise <verb> --help`` (no other argument) depends only on the code and the installed packages, so the
first call stores what LightningCLI printed and later calls print it without importing either.

A stored text is used only while everything it was built from is unchanged; its key is a digest of

- the verb and its arguments (``--help`` or ``-h``) and the terminal width argparse wraps the text to
  (``shutil.get_terminal_size``, which reads ``COLUMNS``);
- the Python version and every ``site-packages`` (or ``dist-packages``) folder on ``sys.path`` with its
  modification time (installing, upgrading or removing a distribution adds or removes a ``*.dist-info`` entry
  there, which changes it);
- every ``.py`` file of the ``tofdenoise`` package with its size and modification time (an edited docstring, an
  added parameter).

The folder is ``$TOFDENOISE_CACHE_DIR/cli-help``, else ``$XDG_CACHE_HOME/tofdenoise/cli-help``, else
``~/.cache/tofdenoise/cli-help``; ``TOFDENOISE_CACHE_DIR=`` (empty) turns the cache off. Files are written
atomically, and a cache that cannot be read or written is passed over (the help is built as without it): it is a
copy of what the code prints, never the only copy of anything.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

__all__ = ["HELP_FLAGS", "cache_dir", "cache_key", "is_bare_help", "read_help", "store_help"]

#: the arguments of a bare help request
HELP_FLAGS = (["--help"], ["-h"])

#: stored texts kept per verb (other terminal widths, ``-h`` beside ``--help``)
KEEP = 4

#: the folders on ``sys.path`` that distributions are installed into
SITE_FOLDERS = ("site-packages", "dist-packages")

PACKAGE_DIR = Path(__file__).resolve().parents[1]


def is_bare_help(args: Sequence[str]) -> bool:
    """``True`` for ``--help`` or ``-h`` alone (the only help whose text no file or option changes)."""
    return list(args) in HELP_FLAGS


def cache_dir() -> Path | None:
    """The help cache's folder, or ``None`` when ``TOFDENOISE_CACHE_DIR`` is set empty (cache off)."""
    configured = os.environ.get("TOFDENOISE_CACHE_DIR")
    if configured is not None:
        return Path(configured).expanduser() / "cli-help" if configured.strip() else None
    xdg = os.environ.get("XDG_CACHE_HOME", "").strip()
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "tofdenoise" / "cli-help"


def _stat_line(path: Path) -> str:
    try:
        stat = path.stat()
    except OSError:
        return f"{path} -"
    return f"{path} {stat.st_size} {stat.st_mtime_ns}"


def cache_key(verb: str, args: Sequence[str], package_dir: Path = PACKAGE_DIR) -> str:
    """The digest that names a stored help text (the module docstring lists what goes into it)."""
    lines = [
        "tofdenoise-cli-help 1",
        verb,
        *args,
        f"columns {shutil.get_terminal_size().columns}",
        f"python {sys.version}",
        *(_stat_line(Path(entry)) for entry in sys.path if Path(entry).name in SITE_FOLDERS),
        *(_stat_line(path) for path in sorted(package_dir.rglob("*.py"))),
    ]
    return hashlib.sha256("\n".join(lines).encode("utf-8", "surrogateescape")).hexdigest()[:32]


def read_help(verb: str, args: Sequence[str]) -> str | None:
    """The stored help text of ``tofdenoise <verb> <args>``, or ``None`` (not a bare help, none stored, cache off)."""
    folder = cache_dir()
    if folder is None or not is_bare_help(args):
        return None
    try:
        return (folder / f"{verb}-{cache_key(verb, args)}.txt").read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None


def store_help(verb: str, args: Sequence[str], text: str) -> Path | None:
    """Keep ``text`` as the help of ``tofdenoise <verb> <args>`` (atomically; of the verb's texts the ``KEEP``
    newest stay, older code's are removed); the file, or ``None`` when it is not a bare help, the cache is off or
    the folder cannot be written."""
    from tofdenoise.atomic import atomic_write_text

    folder = cache_dir()
    if folder is None or not is_bare_help(args) or not text:
        return None
    path = folder / f"{verb}-{cache_key(verb, args)}.txt"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        written = atomic_write_text(path, text)
        stored = sorted(folder.glob(f"{verb}-*.txt"), key=lambda p: p.stat().st_mtime_ns, reverse=True)
        for old in stored[KEEP:]:  # texts of older code or other terminal widths
            old.unlink(missing_ok=True)
        return written
    except OSError:
        return None
