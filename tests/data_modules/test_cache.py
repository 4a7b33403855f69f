"""sigma_D map cache: hit / miss / invalidation / corruption recovery, with two DataLoader worker processes."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Dataset

from tofdenoise.data_modules.cache import CacheEntryError, MapCache
from tofdenoise.data_modules.datasets import MapProvider
from tofdenoise.data_modules.sources.procedural import ProceduralSource
from tofdenoise.physics.calibration import default_calibration


def make_provider(folder, calib=None, n=6):
    calib = calib or default_calibration()
    source = ProceduralSource(num_samples=n, height=32, width=48, seed=5, max_depth_mm=2000)
    cache = MapCache(folder, {"source": source.describe(), "calibration": calib.fingerprint()})
    return MapProvider(source, calib, cache), source.sample_ids()


class StatusDataset(Dataset):
    """Reads maps through the provider and reports how (hit / miss / corrupt) and in which process."""

    def __init__(self, provider, ids):
        self.provider, self.ids = provider, ids

    def __len__(self):
        return len(self.ids)

    def __getitem__(self, i):
        maps, status = self.provider.get(self.ids[i])
        return {"status": status, "pid": os.getpid(), "sigma": torch.from_numpy(maps.sigma_mm), "id": self.ids[i]}


def read_all(provider, ids, workers=2):
    loader = DataLoader(StatusDataset(provider, ids), batch_size=1, num_workers=workers)
    return [{k: (v[0] if isinstance(v, (list, torch.Tensor)) else v) for k, v in b.items()} for b in loader]


def test_hit_miss_and_values(tmp_path):
    provider, ids = make_provider(tmp_path)
    maps, status = provider.get(ids[0])
    assert status == "miss" and provider.cache.path(ids[0]).is_file()
    again, status = provider.get(ids[0])
    assert status == "hit"
    fresh = provider.compute(ids[0])
    for name in ("depth_mm", "signal_e", "sigma_mm", "mask", "amplitude"):
        np.testing.assert_array_equal(getattr(again, name), getattr(fresh, name))
    assert again.mask.dtype == bool and again.sigma_mm.dtype == np.float32


def test_two_workers_miss_then_hit(tmp_path):
    provider, ids = make_provider(tmp_path)
    first = read_all(provider, ids)
    assert [r["status"] for r in first] == ["miss"] * len(ids)
    assert len({int(r["pid"]) for r in first}) == 2 and os.getpid() not in {int(r["pid"]) for r in first}
    second = read_all(provider, ids)
    assert [r["status"] for r in second] == ["hit"] * len(ids)
    for a, b in zip(first, second):
        torch.testing.assert_close(a["sigma"], b["sigma"])


def test_concurrent_writers_of_the_same_entries(tmp_path):
    provider, ids = make_provider(tmp_path, n=4)
    doubled = [i for i in ids for _ in range(2)]  # both workers compute/write every entry at about the same time
    rows = read_all(provider, doubled)
    assert {r["status"] for r in rows} <= {"miss", "hit"}
    for sample_id in ids:  # every entry is complete and correct; no temporary files remain
        np.testing.assert_array_equal(provider.cache.read(sample_id).sigma_mm, provider.compute(sample_id).sigma_mm)
    assert not [p for p in provider.cache.folder.iterdir() if ".tmp" in p.name]


def test_truncated_and_corrupt_entries_are_recomputed(tmp_path):
    provider, ids = make_provider(tmp_path)
    read_all(provider, ids, workers=0)
    p0, p1, p2 = (provider.cache.path(i) for i in ids[:3])
    p0.write_bytes(p0.read_bytes()[: p0.stat().st_size // 2])  # truncated
    raw = bytearray(p1.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # flipped byte inside an array: zip CRC mismatch
    p1.write_bytes(bytes(raw))
    p2.write_bytes(b"")  # empty file
    for path in (p0, p1, p2):
        with pytest.raises(CacheEntryError):
            provider.cache.read(ids[[p0, p1, p2].index(path)])
    rows = read_all(provider, ids)
    assert [r["status"] for r in rows] == ["corrupt"] * 3 + ["hit"] * (len(ids) - 3)
    for row in rows:
        torch.testing.assert_close(row["sigma"], torch.from_numpy(provider.compute(row["id"]).sigma_mm))
    assert [r["status"] for r in read_all(provider, ids)] == ["hit"] * len(ids)  # rewritten


def test_changed_calibration_never_reuses_maps(tmp_path):
    calib = default_calibration()
    provider, ids = make_provider(tmp_path, calib)
    provider.get(ids[0])
    noisier = calib.replace(dark_std_e=calib.dark_std_e * 3.0)
    other, _ = make_provider(tmp_path, noisier)
    assert other.cache.folder != provider.cache.folder
    maps, status = other.get(ids[0])
    assert status == "miss"
    assert maps.sigma_mm[maps.mask].mean() > provider.maps(ids[0]).sigma_mm[maps.mask].mean()
    # an entry copied in from another key is detected (its stored key digest differs)
    shutil.copy(provider.cache.path(ids[1]) if provider.get(ids[1]) else None, other.cache.path(ids[1]))
    assert other.get(ids[1])[1] == "corrupt"


def test_disabled_cache_computes_every_time(tmp_path):
    provider, ids = make_provider(tmp_path)
    provider.cache.enabled = False
    assert provider.get(ids[0])[1] == "disabled"
    assert not provider.cache.path(ids[0]).exists()
