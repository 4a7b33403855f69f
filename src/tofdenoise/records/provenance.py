"""Which code made a record: the git commit of the checkout the running ``tofdenoise`` package was imported from.

Every ``run_info.json`` written at training time carries ``commit`` (:func:`code_commit`): the 40-hex commit of the
checkout, ``commit_dirty`` (``true`` when tracked files differ from that commit: an uncommitted edit, a changed
config; the records and the results page that ``tofdenoise reproduce`` itself writes into the checkout,
``OUTPUT_PATHS``, do not count, so the runs after a table's first recorded one are not marked dirty by it) and
``commit_describe`` (``git describe --always``, with ``-dirty`` appended when ``commit_dirty``). An
installed package outside a checkout (a wheel in site-packages) records ``commit: null`` and its ``version``
instead. Records written before these fields existed read as before (:func:`record_commit` gives ``None``).
"""

from __future__ import annotations

import subprocess
from collections.abc import Mapping
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

__all__ = ["code_commit", "is_ancestor", "record_commit"]

#: the folder holding the ``tofdenoise`` package (``src/`` in a checkout)
_PACKAGE_DIR = Path(__file__).resolve().parents[1]
#: paths of a checkout (from its top) that hold outputs, not code: the committed records and the page built from them
OUTPUT_PATHS = ("docs/results", "docs/results.md")


def _run_git(folder: Path, *args: str) -> subprocess.CompletedProcess | None:
    """``git -C folder args`` run to its end, or None when git is missing or does not answer."""
    try:
        return subprocess.run(
            ["git", "-C", str(folder), *args], capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None


def _git(folder: Path, *args: str) -> str | None:
    """``git -C folder args`` stripped, or None when git is missing, the folder is no checkout, or git fails."""
    done = _run_git(folder, *args)
    return done.stdout.strip() if done is not None and done.returncode == 0 else None


def is_ancestor(older: str, commit: str, folder: Path = _PACKAGE_DIR) -> bool | None:
    """Is ``older`` an ancestor of (or equal to) ``commit`` in the checkout holding ``folder`` (default: this
    package's)? None when git cannot tell (no git, no checkout, a commit it does not have)."""
    done = _run_git(folder, "merge-base", "--is-ancestor", older, commit)
    return None if done is None else {0: True, 1: False}.get(done.returncode)


def _version() -> str | None:
    try:
        return metadata.version("tofdenoise")
    except metadata.PackageNotFoundError:
        return None


@lru_cache(maxsize=8)
def _commit_of(folder: Path) -> tuple[tuple[str, Any], ...]:
    commit = _git(folder, "rev-parse", "--verify", "HEAD")
    if not commit:
        return (("commit", None), ("commit_dirty", None), ("version", _version()))
    # refresh the index's stat data first, so a file touched but not changed does not count as dirty
    _git(folder, "update-index", "-q", "--refresh")
    outputs = [f":(top,exclude){path}" for path in OUTPUT_PATHS]
    # diff-index --quiet exits 1 (None here) when a tracked file outside the outputs differs from HEAD
    dirty = _git(folder, "diff-index", "--quiet", "HEAD", "--", ":(top)", *outputs) is None
    describe = _git(folder, "describe", "--always", "--abbrev=12")
    return (
        ("commit", commit),
        ("commit_dirty", dirty),
        ("commit_describe", f"{describe}-dirty" if describe and dirty else describe),
    )


def code_commit(folder: str | Path | None = None) -> dict[str, Any]:
    """The commit of the code that runs: ``{"commit", "commit_dirty", "commit_describe"}`` of the git checkout
    holding ``folder`` (default: the imported ``tofdenoise`` package); outside a checkout ``{"commit": None,
    "commit_dirty": None, "version": <installed version>}``. Read once per process and folder (a training run
    records the code it started with)."""
    return dict(_commit_of(Path(folder).resolve() if folder is not None else _PACKAGE_DIR))


def record_commit(run_info: Mapping[str, Any] | None) -> str | None:
    """The commit a ``run_info.json`` names, or None for a record written before commits were recorded (or made
    outside a checkout)."""
    if not run_info:
        return None
    commit = run_info.get("commit")
    return str(commit) if commit else None
