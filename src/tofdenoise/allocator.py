"""The process's C allocator: keep freed memory for the next frame or step instead of returning it to the system.

glibc's ``malloc`` serves a block above its mmap threshold (dynamic, at most 32 MiB by default) with a fresh
``mmap`` and gives it back with ``munmap`` when it is freed. A tensor of a full frame is far above that: DVSS at
480 x 640 allocates tensors of 39-315 MB per block, so every one of them is mapped anew and every page of it faults
on its first write, in every frame. :func:`keep_freed_memory` raises the threshold to
:data:`MMAP_THRESHOLD_BYTES` and the trim threshold to :data:`TRIM_THRESHOLD_BYTES`, so that freed blocks stay in
the heap and the next allocation of the same size reuses pages already mapped (the same settings as the
``MALLOC_*_`` environment variables of glibc's manual, which it also exports, so that the processes a command starts
-- a ``reproduce`` job's training, data-loader workers -- inherit them).

Measured on the 2-core CPU machine (docs/benchmarks.md, "Inference on the CPU"): a DVSS frame 1.5x faster, a
U-Net frame 1.3x, a training step about 1.1x; the price is a resident set that stays at its high-water mark.
``tofdenoise`` applies it once for every verb; ``TOFDENOISE_MALLOC=default`` (:data:`ENV`) leaves the allocator
as it is. A library user calls :func:`keep_freed_memory` once at start-up. Anywhere but glibc (macOS, Windows,
musl) it does nothing and says so by returning False.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import resource
import sys

__all__ = [
    "ENV",
    "MMAP_THRESHOLD_BYTES",
    "TRIM_THRESHOLD_BYTES",
    "TOP_PAD_BYTES",
    "keep_freed_memory",
    "malloc_environment",
    "peak_rss_bytes",
]

#: ``TOFDENOISE_MALLOC=default`` leaves the C allocator untouched; unset or ``keep``: :func:`keep_freed_memory`
ENV = "TOFDENOISE_MALLOC"
#: blocks below this are carved from the heap (kept when freed), not mapped per allocation
MMAP_THRESHOLD_BYTES = 1 << 30
#: free memory at the top of the heap is returned to the system only above this (mallopt takes a C int)
TRIM_THRESHOLD_BYTES = (1 << 31) - 1
#: extra heap grown per request, so that a growing heap is not extended one block at a time
TOP_PAD_BYTES = 256 << 20

# mallopt parameters (glibc's <malloc.h>)
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3

_applied = False


def malloc_environment() -> dict[str, str]:
    """The same settings as glibc's environment variables (read when a process starts)."""
    return {
        "MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD_BYTES),
        "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD_BYTES),
        "MALLOC_TOP_PAD_": str(TOP_PAD_BYTES),
    }


def _glibc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 - only glibc has it (musl does not)
    except (OSError, AttributeError):
        return None
    return libc


def keep_freed_memory(environ: dict[str, str] | None = None) -> bool:
    """Apply the settings above to this process (``mallopt``) and export them to the processes it starts (into
    ``environ``, default ``os.environ``). Returns True when they are in effect; False where the C library is not
    glibc or ``TOFDENOISE_MALLOC=default``. Calling it again changes nothing."""
    global _applied
    env = os.environ if environ is None else environ
    choice = env.get(ENV, "keep").strip().lower()
    if choice == "default":
        return False
    if choice != "keep":
        raise ValueError(f"{ENV}={env[ENV]!r}: expected 'keep' (the default) or 'default'")
    if _applied:
        return True
    libc = _glibc()
    if libc is None:
        return False
    settings = (
        (_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
        (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
        (_M_TOP_PAD, TOP_PAD_BYTES),
    )
    if not all(libc.mallopt(param, value) == 1 for param, value in settings):
        return False
    for key, value in malloc_environment().items():
        env.setdefault(key, value)  # a user's own MALLOC_* setting wins in the processes started
    _applied = True
    return True


def peak_rss_bytes() -> int:
    """The process's peak resident memory in bytes: Linux's ``VmHWM`` (the high-water mark of the memory the process
    runs in, which starts afresh when a program is executed), else ``getrusage``'s ``ru_maxrss``. Linux carries
    ``ru_maxrss`` over an ``exec``: a subprocess started by a large process reports at least its parent's size at
    the fork (a benchmark row after a 1.7 GB training step read 1.7 GB for a 0.4 GB network)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # kB
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak) if sys.platform == "darwin" else int(peak) * 1024  # macOS: bytes; Linux, BSD: KiB
