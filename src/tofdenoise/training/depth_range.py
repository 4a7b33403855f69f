"""The depths a network was trained on, kept in its checkpoint, and a frame's depths against them.

During a fit, ``DepthRestorer`` counts the valid clean (target) depths of every training batch into a histogram of
``BINS`` log-spaced bins from ``LOW_MM`` to ``HIGH_MM`` (bins at 2.3 % steps; depths outside go to the end bins),
on the batch's device and without a synchronisation, plus the exact nearest and farthest depth. The checkpoint keeps
the record under ``DEPTH_RANGE_KEY`` as plain values (it loads with ``weights_only=True``); a resumed fit goes on
counting. The training range is the ``QUANTILES`` (0.5 % and 99.5 %) of the counted depths, so that a few far
outliers of a real dataset do not widen it; for the built-in scenes it is their configured depth range (300 mm to
80 % of the unambiguous range). Under DDP the record is that of the process that writes the checkpoint (rank 0:
a random share of the same training set).

``outside_fraction`` is the share of a frame's valid depths outside a range; ``tofdenoise denoise`` says so for a
frame whose valid depths lie mostly (more than half) outside the checkpoint's range. A checkpoint written before
this record existed has none: its range is unknown (``TrainingDepthRange.range_mm`` is None).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "BINS",
    "DEPTH_RANGE_KEY",
    "HIGH_MM",
    "LOW_MM",
    "QUANTILES",
    "TrainingDepthRange",
    "outside_fraction",
]

#: key of the record inside a checkpoint
DEPTH_RANGE_KEY = "tofdenoise_training_depth_mm"
#: histogram: log-spaced bins from LOW_MM to HIGH_MM
LOW_MM, HIGH_MM, BINS = 10.0, 100_000.0, 400
#: the quantiles of the counted depths that bound the training range
QUANTILES = (0.005, 0.995)


def _edges_mm() -> np.ndarray:
    return np.geomspace(LOW_MM, HIGH_MM, BINS + 1)


class TrainingDepthRange:
    """The valid target depths of the training batches seen so far (module docstring)."""

    def __init__(self) -> None:
        self._counts: Tensor | None = None  # int64 (BINS,), on the device of the batches
        self._edges: Tensor | None = None  # inner edges, float32, same device
        self._min: Tensor | None = None
        self._max: Tensor | None = None
        self._loaded: dict[str, Any] | None = None

    @torch.no_grad()
    def update(self, clean_mm: Tensor, mask: Tensor) -> None:
        """Count the valid (``mask > 0``, finite, > 0) depths of one training batch."""
        depth = clean_mm.detach().float().reshape(-1)
        valid = (mask.detach().reshape(-1) > 0) & torch.isfinite(depth) & (depth > 0)
        if self._counts is None or self._counts.device != depth.device:
            self._start(depth.device)
        assert self._counts is not None and self._edges is not None
        index = torch.bucketize(depth, self._edges).clamp_(0, BINS - 1)
        self._counts.scatter_add_(0, index, valid.long())
        big = torch.tensor(math.inf, device=depth.device)
        self._min = torch.minimum(self._min, torch.where(valid, depth, big).min())
        self._max = torch.maximum(self._max, torch.where(valid, depth, -big).max())

    def _start(self, device: torch.device) -> None:
        counts = torch.zeros(BINS, dtype=torch.int64, device=device)
        low, high = math.inf, -math.inf
        if self._counts is not None:  # moved to another device
            counts += self._counts.to(device)
            low, high = float(self._min), float(self._max)
        elif self._loaded is not None:  # a resumed fit goes on counting
            counts += torch.tensor(self._loaded["counts"], dtype=torch.int64, device=device)
            low, high = float(self._loaded["min_mm"]), float(self._loaded["max_mm"])
        self._counts = counts
        self._edges = torch.tensor(_edges_mm()[1:-1], dtype=torch.float32, device=device)
        self._min = torch.tensor(low, device=device)
        self._max = torch.tensor(high, device=device)

    def record(self) -> dict[str, Any] | None:
        """The plain-values record (None: no depth counted)."""
        if self._counts is None:
            return None if self._loaded is None else dict(self._loaded)
        counts = [int(c) for c in self._counts.cpu().tolist()]
        if not sum(counts):
            return None
        low, high = _quantiles_mm(np.asarray(counts), QUANTILES)
        return {
            "low_mm": low,
            "high_mm": high,
            "quantiles": list(QUANTILES),
            "min_mm": float(self._min),
            "max_mm": float(self._max),
            "pixels": int(sum(counts)),
            "bins": {"low_mm": LOW_MM, "high_mm": HIGH_MM, "count": BINS},
            "counts": counts,
        }

    def save(self, checkpoint: dict[str, Any]) -> None:
        record = self.record()
        if record is not None:
            checkpoint[DEPTH_RANGE_KEY] = record

    def load(self, checkpoint: dict[str, Any]) -> None:
        """The record of a checkpoint (none: a checkpoint written before it existed, the range unknown)."""
        record = checkpoint.get(DEPTH_RANGE_KEY)
        ok = isinstance(record, dict) and isinstance(record.get("counts"), list) and len(record["counts"]) == BINS
        self._loaded = dict(record) if ok else None
        self._counts = self._edges = self._min = self._max = None

    @property
    def range_mm(self) -> tuple[float, float] | None:
        """(nearest, farthest) training depth [mm] (the ``QUANTILES`` of the counted depths), None when unknown."""
        record = self.record()
        return None if record is None else (float(record["low_mm"]), float(record["high_mm"]))


def _quantiles_mm(counts: np.ndarray, quantiles: tuple[float, float]) -> tuple[float, float]:
    """Depths [mm] at ``quantiles`` of a histogram, log-interpolated within the bin (the end bins, which also hold
    the depths beyond LOW_MM / HIGH_MM, at their inner edge)."""
    edges = _edges_mm()
    cumulative = np.cumsum(counts) / counts.sum()
    out = []
    for q in quantiles:
        i = int(np.searchsorted(cumulative, q, side="left"))
        i = min(i, BINS - 1)
        before = cumulative[i - 1] if i > 0 else 0.0
        share = (q - before) / max(cumulative[i] - before, 1e-12)
        lo, hi = np.log(edges[i]), np.log(edges[i + 1])
        out.append(float(np.exp(lo + min(max(share, 0.0), 1.0) * (hi - lo))))
    return out[0], out[1]


def outside_fraction(depth_mm: np.ndarray, valid: np.ndarray, range_mm: tuple[float, float]) -> float:
    """The share of the valid depths of a frame outside ``range_mm`` (0 for a frame without a valid pixel)."""
    values = np.asarray(depth_mm)[np.asarray(valid, dtype=bool)]
    if not values.size:
        return 0.0
    low, high = range_mm
    return float(np.count_nonzero((values < low) | (values > high)) / values.size)
