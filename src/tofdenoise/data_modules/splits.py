"""Seeded train/val/test splits (6:2:2 by default), stored as JSON so they can be inspected and reused."""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Sequence
from pathlib import Path

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
    parts = {"train": order[:n_train], "val": order[n_train : n_train + n_val], "test": order[n_train + n_val :]}
    return {name: [ids[i] for i in sorted(part.tolist())] for name, part in parts.items()}


def ids_digest(sample_ids: Sequence[str]) -> str:
    return hashlib.sha256("\n".join(sample_ids).encode("utf-8")).hexdigest()


def save_split(
    path: str | Path, split: dict[str, list[str]], *, seed: int, ratios: Sequence[float], source: dict
) -> Path:
    payload = {
        "seed": int(seed),
        "ratios": [float(r) for r in ratios],
        "source": source,
        "sizes": {k: len(split[k]) for k in SPLIT_NAMES},
        **{k: split[k] for k in SPLIT_NAMES},
    }
    return atomic_write_text(path, json.dumps(payload, indent=1) + "\n")


def load_split(path: str | Path) -> dict:
    """Read a split file; errors name the file and say what is wrong (not JSON, a part missing, bad ids)."""
    path = Path(path)
    try:
        payload = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"split file {path} is unreadable: {exc}") from exc
    if not isinstance(payload, dict):
        raise ValueError(f"split file {path}: expected a JSON object with lists 'train', 'val', 'test'")
    seen: dict[str, str] = {}
    for name in SPLIT_NAMES:
        part = payload.get(name)
        if not isinstance(part, list):
            raise ValueError(f"split file {path} has no list {name!r}")
        for sample_id in part:
            if not isinstance(sample_id, str):
                raise ValueError(f"split file {path}: {name!r} holds {sample_id!r}; sample ids are strings")
            if sample_id in seen:
                raise ValueError(f"split file {path}: sample {sample_id!r} is in both {seen[sample_id]!r} and {name!r}")
            seen[sample_id] = name
    return payload


def load_or_make_split(
    path: str | Path, sample_ids: Sequence[str], seed: int, ratios: Sequence[float], source: dict
) -> dict[str, list[str]]:
    """Reuse the split stored at ``path`` when it was made from the same ids, seed and ratios; else make one.

    A stored file that does not parse (e.g. after a hand edit) is an error naming the file, never silently
    replaced; one made from other ids, seed or ratios is replaced by a new split with a warning.
    """
    path = Path(path)
    ids = list(sample_ids)
    if path.is_file():
        try:
            stored = load_split(path)
        except ValueError as exc:
            raise ValueError(
                f"{exc}. Fix the file (docs/data.md, 'Cache'), or delete it to make a new seeded split"
            ) from None
        if (
            stored.get("seed") == int(seed)
            and stored.get("ratios") == [float(r) for r in ratios]
            and sorted(stored["train"] + stored["val"] + stored["test"]) == sorted(ids)
        ):
            return {name: list(stored[name]) for name in SPLIT_NAMES}
        stored_ids = set(stored["train"] + stored["val"] + stored["test"])
        warnings.warn(
            f"split file {path} was made for other samples, seed or ratios (seed {stored.get('seed')}, "
            f"ratios {stored.get('ratios')}, {len(stored_ids)} ids of which "
            f"{len(stored_ids - set(ids))} unknown, {len(set(ids) - stored_ids)} missing): replaced by "
            f"a new split",
            stacklevel=2,
        )
    split = make_split(ids, seed, ratios)
    save_split(path, split, seed=seed, ratios=ratios, source=source)
    return split
