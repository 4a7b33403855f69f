"""Atomic file writes: the one implementation every cache, output and config writer uses.

A writer fills a temporary file in the destination folder (unique per process and thread), flushes it, gives it
the permissions of a normal new file (0666 minus the umask, not ``mkstemp``'s private 0600) and renames it over the
destination with ``os.replace``. Readers therefore see either the old file or the complete new one, never a
partial write; concurrent writers of the same path are safe (the last rename wins); a failed write leaves the old
file untouched and no temporary file behind, and raises :class:`WriteError`: an ``OSError`` whose message names the
destination and the cause (a full disk: "No space left on device"), for the commands' one-line errors.

An atomic write keeps each file whole, but a file rebuilt from others (a page from the records) can still lose an
update when two processes rebuild it at once: each reads, the slower one writes what it read before the other's
input existed. :func:`exclusive_lock` makes such a read-then-write one at a time (an ``fcntl.flock`` on a lock file
next to it; the kernel drops it when its holder ends in any way).

Several files that belong together (a frame's restored depth, its ``.npy``, its sigma_D map and preview) are
written all or nothing inside :func:`atomic_group`: every write of the block fills its temporary file, and only when
the whole block succeeded are they renamed into place, one after the other; a write that fails (a full disk) leaves
none of them, and the files they would have replaced stay as they were.

A unit of several writes and its bookkeeping (a frame's outputs and the count of frames done) is whole with respect
to Ctrl-C inside :func:`sigint_deferred`: a SIGINT that arrives there is raised as ``KeyboardInterrupt`` when the
unit ends, so a summary never counts fewer frames than are on disk.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import os
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy and OpenCV are imported by the writers that need them: light users import neither
    import numpy as np

__all__ = [
    "WriteError",
    "atomic_group",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_png",
    "current_umask",
    "exclusive_lock",
    "save_npy_atomic",
    "sigint_deferred",
]


class WriteError(OSError):
    """A write that failed (full disk, file too large, no permission): the message names the destination and the
    cause; the destination is untouched. ``errno`` is the cause's."""


def _write_error(path: Path, exc: OSError) -> WriteError:
    cause = exc.strerror or str(exc)
    full = exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) or "requested and" in str(exc)
    error = WriteError(f"could not write {path}: {cause}" + (" (disk full?)" if full else ""))
    error.errno = exc.errno
    return error


def current_umask() -> int:
    """The process umask, read without changing it where /proc allows (thread-safe), else set-and-restore."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: the open :func:`atomic_group` of each thread: (temporary file, destination) pairs still to rename
_group = threading.local()


@contextlib.contextmanager
def atomic_group() -> Iterator[None]:
    """All or nothing (module docstring): the atomic writes inside the block are renamed into place when it ends
    without an exception, and removed when it raises. Groups do not nest."""
    if getattr(_group, "pending", None) is not None:
        raise RuntimeError("atomic_group blocks do not nest")
    pending: list[tuple[Path, Path]] = []
    _group.pending = pending
    try:
        yield
    except BaseException:
        for tmp, _ in pending:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        _group.pending = None
    for k, (tmp, path) in enumerate(pending):
        try:
            os.replace(tmp, path)
        except OSError as exc:
            for rest, _ in pending[k:]:
                rest.unlink(missing_ok=True)
            raise _write_error(path, exc) from exc


def atomic_write(path: str | os.PathLike[str], write: Callable[[Path], object], suffix: str | None = None) -> Path:
    """Call ``write(tmp_path)`` to fill a temporary file next to ``path``, then rename it into place.

    ``suffix`` is the temporary file's extension (default: the destination's), for writers that choose the format
    by extension (``np.save``, ``cv2.imwrite``, ``Figure.savefig``). Returns ``Path(path)``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=f".tmp{suffix if suffix is not None else path.suffix}", dir=path.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        if not tmp.exists():
            raise OSError(f"{path}: the writer produced no file")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~current_umask())
        pending = getattr(_group, "pending", None)
        if pending is None:
            os.replace(tmp, path)
        else:  # renamed when the atomic_group ends
            pending.append((tmp, path))
    except WriteError:
        tmp.unlink(missing_ok=True)
        raise
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise _write_error(path, exc) from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda tmp: tmp.write_bytes(data))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def save_npy_atomic(path: str | os.PathLike[str], array: np.ndarray) -> Path:
    """Save ``array`` as a ``.npy`` file (no pickle) atomically. It is encoded in memory first: ``np.save`` to a
    file name writes through C stdio, which truncated the file without an error when the disk filled (a 256-byte
    ``.npy`` of a 1.6 kB array under a file-size limit, tests/reliability)."""
    import numpy as np

    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(array), allow_pickle=False)
    return atomic_write_bytes(path, buf.getvalue())


def atomic_write_png(path: str | os.PathLike[str], image: np.ndarray) -> Path:
    """Encode ``image`` as PNG with OpenCV (uint8 or uint16; 2-D, or 3-D in OpenCV's BGR order) and write it
    atomically."""
    import cv2
    import numpy as np

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise OSError(f"{path}: OpenCV could not encode a {image.dtype} {image.shape} image as PNG")
    return atomic_write_bytes(path, buf.tobytes())


@contextlib.contextmanager
def exclusive_lock(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Hold an exclusive lock for ``path`` (blocking until it is free): the lock file ``.<name>.lock`` next to it,
    which stays in place (removing a lock file others may be waiting on would let two holders in). POSIX only."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lock_path = path.parent / f".{path.name}.lock"
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield lock_path
    finally:
        os.close(fd)  # closing drops the flock


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Run the block without being cut by Ctrl-C: a SIGINT received inside it raises ``KeyboardInterrupt`` as the
    block ends (once, however many arrived), so that the block's writes and the record of them stay together. Off
    the main thread, or when SIGINT is not Python's default handler (someone else handles it), the block runs
    unchanged. An exception of the block itself wins over a deferred SIGINT."""
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt
