"""Which content a file had: its size and SHA-256, hashed again only when its stat stamp moves.

A *stamp* records a file's ``size``, ``mtime_ns``, ``ctime_ns``, ``ino`` and ``sha256``. A file still has the
content a stamp recorded when its size, mtime, ctime and inode are the same (one ``stat``: nothing is read), or,
when any of them moved, when its size and SHA-256 are (a ``touch``, a copy of the same bytes or a restore from a
backup keeps the content; a rewrite keeps the mtime under ``cp -p`` / ``rsync -a`` but moves the ctime, which no
user tool sets back). A process hashes a file once for as long as its stat stamp stays the same (``_DIGESTS``).

Used by the capture sets' reference cache (``real_captures``: each ``hiexp/`` frame's size and SHA-256 in
``reference.json``) and by the map cache of file-backed sources (``cache.MapCache``: each entry and each
``index.json`` entry records the stamps of the files its maps were computed from).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

#: the stat fields a stamp compares before it hashes (their change alone does not make a file changed)
STAT_FIELDS = ("size", "mtime_ns", "ctime_ns", "ino")


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


#: SHA-256 of the files this process has hashed, by path, while their (size, mtime, ctime, inode) stay the same
_DIGESTS: dict[str, tuple[tuple[int, int, int, int], str]] = {}


def _stat_key(st: os.stat_result) -> tuple[int, int, int, int]:
    return (st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)


def _hashed(path: Path, st: os.stat_result) -> str:
    """The SHA-256 of ``path`` whose stat is ``st``, from ``_DIGESTS`` while its stat key is the same."""
    key = _stat_key(st)
    known = _DIGESTS.get(str(path))
    if known is not None and known[0] == key:
        return known[1]
    digest = file_sha256(path)
    if len(_DIGESTS) > 1_000_000:
        _DIGESTS.clear()
    _DIGESTS[str(path)] = (key, digest)
    return digest


def size_and_digest(path: str | os.PathLike[str]) -> tuple[int, str]:
    """(size, SHA-256) of a file, hashed again only when its size, mtime, ctime or inode moved."""
    path = Path(path)
    st = path.stat()
    return st.st_size, _hashed(path, st)


def file_stamp(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The stamp of one file (``STAT_FIELDS`` and ``sha256``); stat first, so a write after it shows as a change."""
    path = Path(path)
    st = path.stat()
    return dict(zip(STAT_FIELDS, _stat_key(st), strict=True), sha256=_hashed(path, st))


def _name(path: str | os.PathLike[str]) -> str:
    """A file's name in a stamps record: its absolute path (a root given as a relative or an absolute path names the
    same files)."""
    return os.path.abspath(path)


def file_stamps(paths: Iterable[str | os.PathLike[str]]) -> dict[str, dict[str, Any]]:
    """``{absolute path: file_stamp(path)}`` of the files, in their order."""
    return {_name(p): file_stamp(p) for p in paths}


def stamps_state(
    recorded: Mapping[str, Any] | None, paths: Iterable[str | os.PathLike[str]]
) -> tuple[str, dict[str, dict[str, Any]] | None]:
    """Whether ``paths`` still have the content ``recorded`` (a ``file_stamps`` result) holds.

    Returns ("fresh", None): the same files, none of whose stat stamp moved (only ``stat`` calls); ("restamped",
    new stamps): the same files and contents, some stat stamps moved (those files were hashed); ("changed", None):
    another set of files (a list re-paired, a mask added), a file gone, or another size or SHA-256, or no
    ``recorded`` at all (made before stamps were kept).
    """
    names = [_name(p) for p in paths]
    if not isinstance(recorded, Mapping) or sorted(recorded) != sorted(names):
        return "changed", None
    current: dict[str, dict[str, Any]] = {}
    moved = False
    for name in names:
        stamp = recorded[name]
        try:
            st = os.stat(name)
        except OSError:
            return "changed", None
        if not isinstance(stamp, Mapping) or st.st_size != stamp.get("size"):
            return "changed", None
        key = _stat_key(st)
        if key == tuple(stamp.get(field) for field in STAT_FIELDS):
            current[name] = stamp  # type: ignore[assignment]
            continue
        digest = _hashed(Path(name), st)
        if digest != stamp.get("sha256"):
            return "changed", None
        moved = True
        current[name] = dict(zip(STAT_FIELDS, key, strict=True), sha256=digest)
    return ("restamped", {k: dict(v) for k, v in current.items()}) if moved else ("fresh", None)


def content_digest(stamps: Mapping[str, Mapping[str, Any]]) -> dict[str, list]:
    """The part of stamps that is content, by file: ``{path: [size, sha256]}`` (what a derived record keys on)."""
    return {name: [stamp["size"], stamp["sha256"]] for name, stamp in sorted(stamps.items())}
