"""Seeded train/val/test splits (6:2:2 by default), stored as JSON so they can be inspected and reused."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Sequence

import numpy as np

from tofdenoise.atomic import atomic_write_text

SPLIT_NAMES = ("train", "val", "test")


def split_sizes(num_samples: int, ratios: Sequence[float] = (6, 2, 2)) -> tuple[int, int, int]:
    """Sizes for train/val/test: val and test are round(n * r / sum), train takes the rest.

    6,250 samples at 6:2:2 give 3,750 / 1,250 / 1,250 (the paper's split).
    """
    if len(ratios) != 3 or any(r < 0 for r in ratios) or sum(ratios) <= 0:
        raise ValueError(f"data.split_ratios must be three non-negative numbers (train, val, test), got {list(ratios)}")
    total = float(sum(ratios))
    n_val = int(round(num_samples * ratios[1] / total))
    n_test = int(round(num_samples * ratios[2] / total))
    if ratios[1] > 0 and num_samples >= 3:
        n_val = max(n_val, 1)
    if ratios[2] > 0 and num_samples >= 3:
        n_test = max(n_test, 1)
    n_train = num_samples - n_val - n_test
    if n_train < 0 or (ratios[0] > 0 and n_train < 1):
        raise ValueError(f"{num_samples} samples are too few for split ratios {list(ratios)}")
    return n_train, n_val, n_test


def make_split(sample_ids: Sequence[str], seed: int, ratios: Sequence[float] = (6, 2, 2)) -> dict[str, list[str]]:
    """Random split by a permutation drawn from ``numpy.random.default_rng(seed)``; each part keeps list order."""
    ids = list(sample_ids)
    if len(set(ids)) != len(ids):
        raise ValueError("sample ids must be unique to be split")
    n_train, n_val, _ = split_sizes(len(ids), ratios)
    order = np.random.default_rng(int(seed)).permutation(len(ids))
    parts = {"train": order[:n_train], "val": order[n_train:n_train + n_val], "test": order[n_train + n_val:]}
    return {name: [ids[i] for i in sorted(part.tolist())] for name, part in parts.items()}


def ids_digest(sample_ids: Sequence[str]) -> str:
    return hashlib.sha256("\n".join(sample_ids).encode("utf-8")).hexdigest()


def save_split(path: str | Path, split: dict[str, list[str]], *, seed: int, ratios: Sequence[float],
               source: dict) -> Path:
    payload = {"seed": int(seed), "ratios": [float(r) for r in ratios], "source": source,
               "sizes": {k: len(split[k]) for k in SPLIT_NAMES}, **{k: split[k] for k in SPLIT_NAMES}}
    return atomic_write_text(path, json.dumps(payload, indent=1) + "\n")


def load_split(path: str | Path) -> dict:
    path = Path(path)
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"split file {path} is unreadable: {exc}") from exc
    for name in SPLIT_NAMES:
        if not isinstance(payload.get(name), list):
            raise ValueError(f"split file {path} has no list {name!r}")
    return payload


def load_or_make_split(path: str | Path, sample_ids: Sequence[str], seed: int, ratios: Sequence[float],
                       source: dict) -> dict[str, list[str]]:
    """Reuse the split stored at ``path`` when it was made from the same ids, seed and ratios; else make one."""
    path = Path(path)
    ids = list(sample_ids)
    if path.is_file():
        try:
            stored = load_split(path)
        except ValueError:
            stored = None
        if (stored is not None and stored.get("seed") == int(seed)
                and stored.get("ratios") == [float(r) for r in ratios]
                and sorted(stored["train"] + stored["val"] + stored["test"]) == sorted(ids)):
            return {name: list(stored[name]) for name in SPLIT_NAMES}
    split = make_split(ids, seed, ratios)
    save_split(path, split, seed=seed, ratios=ratios, source=source)
    return split
