"""Whether a frame is restored whole or tile by tile: the network's activation memory against a memory budget.

A whole frame is faster than its tiles (tiles overlap and each one pays the network's borders: a 640 x 576 frame in
512-pixel tiles runs four tiles, 2.8x the pixels), so ``DepthRestorer.predict_tile_plan`` (LightningCLI
``predict``, ``tofdenoise denoise``, ``tofdenoise.denoise``) tiles only a frame whose activations do not fit the
memory budget (``tile_plan``), or when a tile side is forced (``--tile``).

- **Activations** (``activation_bytes_per_px``): measured once per network, by running it on a ``PROBE_PX`` x
  ``PROBE_PX`` input of zeros: on the CPU under a ``TorchDispatchMode`` that counts the bytes of every tensor the
  forward pass creates while it is alive (a storage is counted once, whatever its views; freed when its last tensor
  goes) and keeps the peak; on CUDA by the caching allocator's own peak (``torch.cuda.max_memory_allocated``).
  Divided by the probe's pixels, it scales with the frame's pixels: the backbones here (U-Net, DVSS's scans,
  Restormer's channel attention ...) hold memory linear in the pixel count, and a fixed part counted per pixel of
  a small probe only overestimates a larger frame (U-Net and DVSS: the same bytes per pixel at 64, 128 and
  576 x 640). ``SAFETY`` covers what the process holds beyond the tensors (the allocator, oneDNN's workspaces):
  the peak resident memory of a 576 x 640 forward pass on the CPU grew by 1.34x (U-Net) and 1.16x (DVSS) the
  counted peak.
- **Budget** (``memory_budget_bytes``): on CUDA, ``BUDGET_FRACTION_CUDA`` of the device's free memory; on the CPU,
  ``BUDGET_FRACTION_CPU`` of the memory available to the process (Linux ``MemAvailable``, bounded by the cgroup's
  limit in a container; unknown elsewhere, and then a frame is never tiled for memory).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

__all__ = [
    "BUDGET_FRACTION_CPU",
    "BUDGET_FRACTION_CUDA",
    "MIN_TILE_PX",
    "PROBE_PX",
    "SAFETY",
    "TilePlan",
    "activation_bytes_per_px",
    "memory_budget_bytes",
    "peak_tensor_bytes",
    "gib",
    "tile_plan",
]

PROBE_PX = 64
SAFETY = 1.5
BUDGET_FRACTION_CUDA = 0.8
BUDGET_FRACTION_CPU = 0.5
#: the smallest tile ``tile_plan`` shrinks to when even the checkpoint's tile does not fit
MIN_TILE_PX = 64


class _PeakBytes(TorchDispatchMode):
    """Counts the bytes of the tensors created under it while they are alive, and their peak."""

    def __init__(self) -> None:
        super().__init__()
        self.live = 0
        self.peak = 0
        self._refs: dict[int, list[int]] = {}  # storage pointer -> [tensors alive, bytes]

    def _release(self, key: int) -> None:
        entry = self._refs.get(key)
        if entry is None:
            return
        entry[0] -= 1
        if entry[0] == 0:
            self.live -= entry[1]
            del self._refs[key]

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for tensor in tree_leaves(out):
            if not isinstance(tensor, torch.Tensor):
                continue
            storage = tensor.untyped_storage()
            key, size = storage.data_ptr(), storage.nbytes()
            if not size:
                continue
            entry = self._refs.get(key)
            if entry is None:
                self._refs[key] = [1, size]
                self.live += size
                self.peak = max(self.peak, self.live)
            else:
                entry[0] += 1
            weakref.finalize(tensor, self._release, key)
        return out


@torch.no_grad()
def peak_tensor_bytes(fn: Any, *args: Any) -> int:
    """The peak bytes of the tensors ``fn(*args)`` creates (its inputs and parameters not counted)."""
    counter = _PeakBytes()
    with counter:
        result = fn(*args)
    del result
    return counter.peak


#: bytes per pixel measured per network, by (channels, device type, precision)
_MEASURED: weakref.WeakKeyDictionary[Any, dict[tuple, float]] = weakref.WeakKeyDictionary()


def activation_bytes_per_px(net: Any, channels: int, device: torch.device, precision: str, autocast: Any) -> float:
    """Bytes of activations per input pixel of ``net`` on (1, ``channels``, H, W) inputs, measured once per
    ``precision`` on a ``PROBE_PX`` square (module docstring); ``autocast``: the context the network runs under."""
    key = (channels, device.type, precision)
    cache = _MEASURED.setdefault(net, {})
    if key not in cache:
        probe = torch.zeros(1, channels, PROBE_PX, PROBE_PX, device=device)
        with autocast:
            peak = _cuda_peak_bytes(net, probe) if device.type == "cuda" else peak_tensor_bytes(net, probe)
        cache[key] = peak / (PROBE_PX * PROBE_PX)
    return cache[key]


@torch.no_grad()
def _cuda_peak_bytes(net: Any, probe: torch.Tensor) -> int:
    """On CUDA the caching allocator counts itself: its peak over the forward pass, above what was allocated."""
    torch.cuda.synchronize(probe.device)
    base = torch.cuda.memory_allocated(probe.device)
    torch.cuda.reset_peak_memory_stats(probe.device)
    result = net(probe)
    torch.cuda.synchronize(probe.device)
    peak = torch.cuda.max_memory_allocated(probe.device) - base
    del result
    return max(int(peak), 0)


def _meminfo_available_bytes() -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _cgroup_headroom_bytes() -> int | None:
    """What the cgroup (v2) still lets the process allocate: memory.max - memory.current (None: no limit)."""
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit == "max":
            return None
        return max(int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text().strip()), 0)
    except (OSError, ValueError):
        return None


def memory_budget_bytes(device: torch.device) -> float | None:
    """The activation memory a whole frame may take on ``device`` (module docstring); None when unknown."""
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return BUDGET_FRACTION_CUDA * free
    known = [b for b in (_meminfo_available_bytes(), _cgroup_headroom_bytes()) if b is not None]
    return BUDGET_FRACTION_CPU * min(known) if known else None


@dataclass(frozen=True)
class TilePlan:
    """How one frame runs: ``tile`` None = whole, else tiles of that side. ``forced``: ``--tile`` asked for it;
    ``need_bytes`` / ``budget_bytes``: the estimate and the budget it was judged on (None when not judged)."""

    tile: int | None
    forced: bool = False
    need_bytes: float | None = None
    budget_bytes: float | None = None

    @property
    def tiled(self) -> bool:
        return self.tile is not None


def tile_plan(
    shape: tuple[int, int],
    tile: int | None,
    default_tile: int | None,
    bytes_per_px: Any,
    budget_bytes: Any,
    frames: int = 1,
    min_tile: int = MIN_TILE_PX,
) -> TilePlan:
    """Whole frame or tiles for ``frames`` frames of ``shape`` (H, W) run together (a batch).

    ``tile``: a side forced by the caller (``--tile``): tiles whenever a side of the frame exceeds it. Else the frame
    runs whole when its estimated activations (``bytes_per_px()`` x pixels x ``SAFETY``) fit ``budget_bytes()``
    (both callables, asked only when needed; an unknown budget counts as fitting), and otherwise in tiles of
    ``default_tile`` (the checkpoint's ``tiling.predict_tile_px``; None: never tiled), halved down to
    ``MIN_TILE_PX`` while a tile does not fit either (never below ``min_tile``: the smallest tile the network's
    overlap and padding multiple allow, ``models.tiling.min_tile_px``)."""
    height, width = (int(v) for v in shape[-2:])
    if tile is not None:
        return TilePlan(int(tile) if max(height, width) > int(tile) else None, forced=True)
    if default_tile is None:
        return TilePlan(None)
    per_px = float(bytes_per_px()) * max(int(frames), 1)
    need = per_px * height * width * SAFETY
    budget = budget_bytes()
    if budget is None or need <= budget:
        return TilePlan(None, need_bytes=need, budget_bytes=budget)
    floor = max(MIN_TILE_PX, int(min_tile))
    side = max(int(default_tile), int(min_tile))
    while side > floor and per_px * side * side * SAFETY > budget:
        side = max(floor, side // 2)
    if max(height, width) <= side:  # a frame no larger than one tile runs whole anyway
        return TilePlan(None, need_bytes=need, budget_bytes=budget)
    return TilePlan(side, need_bytes=need, budget_bytes=budget)


def gib(n_bytes: float) -> str:
    """``n_bytes`` in GiB for the summary (MiB below 1 GiB, KiB below 1 MiB)."""
    if n_bytes < 2**20:
        return f"{n_bytes / 2**10:.0f} KiB"
    if n_bytes < 2**30:
        return f"{n_bytes / 2**20:.{1 if n_bytes < 10 * 2**20 else 0}f} MiB"
    return f"{n_bytes / 2**30:.{1 if n_bytes < 10 * 2**30 else 0}f} GiB"
