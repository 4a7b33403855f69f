"""Torch datasets: synthetic pairs (clean maps + noise drawn by a physics noise model) and real capture sets.

Batch items (after default collation) are float32 tensors (B, 1, H, W) in mm: ``noisy``, ``clean``, ``sigma``
(the hetero sigma_D map whatever the training noise is), ``mask`` (1 valid / 0 invalid: the pixels the loss and
the metrics score), ``amplitude``; plus ``index`` (position in the split) and ``name`` (sample id). Invalid
pixels are 0 in ``clean`` and ``noisy``. The network input (``noisy``, ``amplitude``) is 0 exactly at the
input's own invalid pixels: for synthetic pairs these are the ``mask == 0`` pixels; for a capture set
``mask`` is the common valid region of input and reference, and the input keeps its valid pixels outside it.
Synthetic pairs may carry holes (``tofdenoise.data_modules.holes``): pixels invalid in the simulated input,
0 in every map and in ``mask``.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from tofdenoise.data_modules.cache import MapCache, SampleMaps
from tofdenoise.data_modules.holes import apply_holes
from tofdenoise.data_modules.maps import compute_sample_maps
from tofdenoise.data_modules.transforms import random_crop_flip
from tofdenoise.physics.photometry import field_cosine


def stable_seed(*parts: Any) -> int:
    """A 63-bit seed from any plain values (sha256 of their repr): stable across runs and processes."""
    digest = hashlib.sha256(repr(tuple(parts)).encode("utf-8")).digest()
    return int.from_bytes(digest[:8], "little") & 0x7FFF_FFFF_FFFF_FFFF


@dataclass
class MapProvider:
    """Maps of one sample id: from the cache when enabled (computed and stored on a miss), else computed."""

    source: Any
    calib: Any
    cache: MapCache
    lower_percentile: float | None = None
    upper_percentile: float | None = None
    signal_route: str = "linear"

    def compute(self, sample_id: str) -> SampleMaps:
        raw = self.source.load(sample_id)
        cos_field = None
        if self.signal_route == "physical":
            cos_field = field_cosine(*raw.depth_mm.shape, self.source.hfov_deg)
        return compute_sample_maps(
            raw, self.calib, self.lower_percentile, self.upper_percentile, self.signal_route, cos_field
        )

    def files(self, sample_id: str) -> list | None:
        """The files the sample is read from (the source's ``files``; None for a source without files): their
        stamps key its cache entry."""
        files = getattr(self.source, "files", None)
        return None if files is None else list(files(sample_id))

    def get(self, sample_id: str) -> tuple[SampleMaps, str]:
        return self.cache.get_or_compute(sample_id, lambda: self.compute(sample_id), self.files(sample_id))

    def get_stamped(self, sample_id: str) -> tuple[SampleMaps, str, dict | None]:
        """``get`` and the stamps of the files the maps were computed from (``MapCache.get_or_compute_stamped``)."""
        return self.cache.get_or_compute_stamped(sample_id, lambda: self.compute(sample_id), self.files(sample_id))

    def maps(self, sample_id: str) -> SampleMaps:
        return self.get(sample_id)[0]


def _as_tensor(array: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))[None]


class SyntheticPairs(Dataset):
    """Clean maps + synthesised noisy depth.

    train=True: random crop + flips (all maps together), noise drawn fresh on every read from a generator
    owned by the reading process and seeded from (seed, torch.initial_seed()); DataLoader gives each worker a
    different ``torch.initial_seed()`` per epoch, so workers never repeat each other's streams.
    train=False: full resolution, noise from ``torch.Generator().manual_seed(stable_seed(seed, split, id))``:
    the same noisy input for a sample in every epoch and every run.
    holes (a ``HoleModel``): invalid input regions drawn after the noise, from the training generator (train) or
    from ``manual_seed(stable_seed(seed, split, id, "holes"))`` (eval: the same holes in every epoch and run,
    and the noise is the same as without holes).
    """

    def __init__(
        self,
        provider: MapProvider,
        sample_ids: list[str],
        split: str,
        noise_model: Any,
        seed: int,
        train: bool,
        crop: tuple[int, int] | None = None,
        flips: bool = True,
        holes: Any = None,
    ):
        self.provider = provider
        self.sample_ids = list(sample_ids)
        self.split = split
        self.noise_model = noise_model
        self.seed = int(seed)
        self.train = bool(train)
        self.crop = crop
        self.flips = flips
        self.holes = holes
        self._generator: torch.Generator | None = None
        self._generator_base: int | None = None

    def __len__(self) -> int:
        return len(self.sample_ids)

    def train_generator(self) -> torch.Generator:
        base = torch.initial_seed()
        if self._generator is None or self._generator_base != base:
            self._generator = torch.Generator().manual_seed(stable_seed(self.seed, "train", base))
            self._generator_base = base
        return self._generator

    def eval_generator(self, sample_id: str) -> torch.Generator:
        return torch.Generator().manual_seed(stable_seed(self.seed, self.split, sample_id))

    def __getitem__(self, index: int) -> dict[str, Any]:
        sample_id = self.sample_ids[index]
        maps = self.provider.maps(sample_id)
        tensors = {
            "clean": _as_tensor(maps.depth_mm),
            "sigma": _as_tensor(maps.sigma_mm),
            "mask": _as_tensor(maps.mask),
            "amplitude": _as_tensor(maps.amplitude),
        }
        if self.holes is not None:
            tensors["signal"] = _as_tensor(maps.signal_e)
        if self.train:
            generator = self.train_generator()
            tensors = random_crop_flip(tensors, self.crop, generator, hflip=self.flips, vflip=self.flips)
        else:
            generator = self.eval_generator(sample_id)
        valid = tensors["mask"] > 0.5
        noisy = self.noise_model.sample(tensors["clean"], tensors["sigma"], valid=valid, generator=generator)
        noisy = torch.where(valid, noisy.to(torch.float32), torch.zeros((), dtype=torch.float32))
        tensors = {"noisy": noisy, **tensors}
        if self.holes is not None:
            signal = tensors.pop("signal")
            hole_generator = (
                generator
                if self.train
                else torch.Generator().manual_seed(stable_seed(self.seed, self.split, sample_id, "holes"))
            )
            holes = self.holes.sample(tensors["clean"], signal, valid, self.provider.calib, hole_generator)
            tensors = apply_holes(tensors, holes)
        return {**tensors, "index": index, "name": sample_id}


class RealCaptures(Dataset):
    """A real (or simulated) capture set: noisy = standard-exposure depth, clean = multi-frame reference."""

    def __init__(self, scenes: list[Any], load: Callable[[Any], dict[str, np.ndarray]]):
        self.scenes = list(scenes)
        self._load = load

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, index: int) -> dict[str, Any]:
        maps = self._load(self.scenes[index])
        item = {key: _as_tensor(maps[key]) for key in ("noisy", "clean", "sigma", "mask", "amplitude")}
        return {**item, "index": index, "name": str(maps["name"])}
