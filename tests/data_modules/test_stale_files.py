"""Cached maps of file-backed sources follow their files: a rewritten file, a re-paired list or a mask column added
recomputes what was made from the old content; a touch or a same-byte copy does not; the procedural source's keys
and cache files are what they were."""

from __future__ import annotations

import json
import os
import warnings

import cv2
import numpy as np
import pytest

from tofdenoise.data_modules import ToFDataModule
from tofdenoise.data_modules.cache import MapCache, SampleMaps
from tofdenoise.data_modules.file_stamps import file_stamps, stamps_state

H, W = 40, 48


def write_folder(root, n=6, seed=0):
    """``n`` samples: 16-bit depth PNGs (500-2000 mm), float amplitude .npy, list.txt pairing them."""
    rng = np.random.default_rng(seed)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    (root / "amp").mkdir(exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(root / "depth" / f"{i:03d}.png"), rng.uniform(500, 2000, (H, W)).astype(np.uint16))
        np.save(root / "amp" / f"{i:03d}.npy", rng.uniform(10, 1000, (H, W)).astype(np.float32))
    (root / "list.txt").write_text("".join(f"depth/{i:03d}.png amp/{i:03d}.npy\n" for i in range(n)))
    return root


def folder_dm(root, cache, **kwargs):
    settings = dict(crop_size=16, simulated_test=False, holes=False, seed=0)
    settings.update(kwargs)
    return ToFDataModule(source="folder", source_kwargs={"root": str(root)}, cache_dir=str(cache), **settings)


def prepared(dm):
    """prepare_data + setup, returning the warnings' messages."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dm.prepare_data()
        dm.setup()
    return [str(w.message) for w in caught]


def rewrite_keeping_mtime(path, write):
    """Rewrite ``path`` with ``write(path)`` and set its old mtime back (as ``cp -p`` / ``rsync -a`` do)."""
    st = os.stat(path)
    write(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(path).st_mtime_ns == st.st_mtime_ns


def test_stamps_fresh_touched_rewritten(tmp_path):
    """The stamp check: a stat alone while nothing moved; a touch hashes and keeps the content; a rewrite of the same
    size with the old mtime is a change (its ctime moved); a file set of another make is a change."""
    a, b = tmp_path / "a.npy", tmp_path / "b.npy"
    np.save(a, np.arange(12, dtype=np.float32))
    np.save(b, np.ones(12, np.float32))
    recorded = file_stamps([a, b])
    assert set(recorded[str(a)]) == {"size", "mtime_ns", "ctime_ns", "ino", "sha256"}
    assert stamps_state(recorded, [a, b]) == ("fresh", None)
    os.utime(a, ns=(0, 10**18))  # touched: same bytes
    state, stamps = stamps_state(recorded, [a, b])
    assert state == "restamped" and stamps[str(a)]["mtime_ns"] == 10**18
    assert stamps[str(a)]["sha256"] == recorded[str(a)]["sha256"] and stamps[str(b)] == recorded[str(b)]
    rewrite_keeping_mtime(b, lambda p: np.save(p, np.full(12, 2, np.float32)))
    assert os.path.getsize(b) == recorded[str(b)]["size"]
    assert stamps_state(stamps, [a, b]) == ("changed", None)
    assert stamps_state(recorded, [a]) == ("changed", None)  # another set of files
    assert stamps_state(None, [a]) == ("changed", None)  # nothing recorded


def test_rewritten_depth_file_recomputes_its_maps_once_with_one_warning(tmp_path):
    """depth/002.png rewritten with a constant 3000 mm: training got the old maps (median 1267 mm, 2 cache hits, no
    warning). Now the entry is recomputed, the index follows, and one warning names how many samples."""
    root = write_folder(tmp_path / "ds")
    cache = tmp_path / "cache"
    dm = folder_dm(root, cache)
    assert not [m for m in prepared(dm) if "computed again" in m]
    sid = dm.splits["train"][0]
    before = dm.prepared.provider.maps(sid)
    assert 500 <= np.median(before.depth_mm[before.mask]) <= 2000
    entry = json.loads(bytes(np.load(dm.cache.path(sid))["meta"]).decode())
    assert list(entry["files"]) == [str(root / f"{sid}.png"), str(root / f"amp/{sid[-3:]}.npy")]

    cv2.imwrite(str(root / f"{sid}.png"), np.full((H, W), 3000, np.uint16))
    dm2 = folder_dm(root, cache)
    messages = [m for m in prepared(dm2) if "computed again" in m]
    assert messages == [
        f"the folder source: 1 sample(s) computed again because their files changed since their maps were cached "
        f"(or the cache recorded no file stamps): {sid}"
    ]
    assert dm2.cache.folder == dm.cache.folder  # the same key: only that entry was recomputed
    maps = dm2.prepared.provider.maps(sid)
    assert np.median(maps.depth_mm[maps.mask]) == 3000.0
    item = dm2.train_dataloader().dataset[dm2.splits["train"].index(sid)]
    assert float(item["clean"][item["mask"] > 0].median()) == 3000.0
    index = json.loads((dm2.cache.folder / "index.json").read_text())["samples"]
    assert index[sid]["files"][str(root / f"{sid}.png")]["size"] == os.path.getsize(root / f"{sid}.png")
    # a third datamodule finds everything fresh: no warning, cache hits only
    dm3 = folder_dm(root, cache)
    assert not [m for m in prepared(dm3) if "computed again" in m]
    dm3.prepared.provider.maps(sid)
    assert dm3.cache.stats.stale == 0 and dm3.cache.stats.misses == 0


def test_rewrite_with_the_old_mtime_is_seen_and_a_touch_is_not_a_change(tmp_path):
    root = write_folder(tmp_path / "ds")
    cache = tmp_path / "cache"
    dm = folder_dm(root, cache)
    prepared(dm)
    sid = dm.splits["train"][1]
    amp = root / f"amp/{sid[-3:]}.npy"
    old_amp = np.load(amp)
    # touched (new mtime, same bytes): nothing recomputed, the stamps refreshed
    os.utime(root / f"{sid}.png")
    dm2 = folder_dm(root, cache)
    assert not [m for m in prepared(dm2) if "computed again" in m]
    # rewritten with the same size and the old mtime: the ctime moved and the SHA-256 differs
    rewrite_keeping_mtime(amp, lambda p: np.save(p, old_amp[::-1].copy()))
    dm3 = folder_dm(root, cache)
    assert [m for m in prepared(dm3) if "computed again" in m and m.endswith(f": {sid}")]
    maps = dm3.prepared.provider.maps(sid)
    np.testing.assert_array_equal(maps.amplitude[maps.mask], old_amp[::-1][maps.mask])


def test_a_sample_once_empty_is_used_after_its_file_is_fixed_without_the_cache(tmp_path):
    """With use_cache=False the index still decided: a sample skipped as empty stayed skipped after a fix."""
    root = write_folder(tmp_path / "ds", n=10)
    cv2.imwrite(str(root / "depth/004.png"), np.zeros((H, W), np.uint16))
    dm = folder_dm(root, tmp_path / "cache", use_cache=False)
    assert any("no valid pixel skipped: depth/004" in m for m in prepared(dm))
    cv2.imwrite(str(root / "depth/004.png"), np.full((H, W), 1500, np.uint16))
    dm2 = folder_dm(root, tmp_path / "cache", use_cache=False)
    messages = prepared(dm2)
    assert not any("no valid pixel" in m for m in messages)
    assert any("1 sample(s) computed again" in m for m in messages)
    assert sum("depth/004" in ids for ids in dm2.splits.values()) == 1 and dm2.skipped_samples == {}
    index = json.loads((dm2.cache.folder / "index.json").read_text())["samples"]
    assert index["depth/004"]["num_valid"] == H * W


def test_repaired_list_and_a_mask_column_give_new_maps(tmp_path):
    """list.txt re-pairing the amplitudes and adding a mask column: the old pairing and no mask were served (1920
    valid pixels where 960 were expected). The list's entries are part of the source description."""
    root = write_folder(tmp_path / "ds")
    (root / "list.txt").write_text("".join(f"depth/{i:03d}.png amp/{(i + 1) % 6:03d}.npy\n" for i in range(6)))
    cache = tmp_path / "cache"
    dm = folder_dm(root, cache)
    prepared(dm)
    (root / "masks").mkdir()
    mask = np.zeros((H, W), np.uint8)
    mask[:, W // 2 :] = 255
    for i in range(6):
        cv2.imwrite(str(root / "masks" / f"{i:03d}.png"), mask)
    (root / "list.txt").write_text(
        "# fixed\n" + "".join(f"depth/{i:03d}.png  amp/{i:03d}.npy masks/{i:03d}.png\n" for i in range(6))
    )
    dm2 = folder_dm(root, cache)
    prepared(dm2)
    assert dm2.cache.folder != dm.cache.folder
    assert dm2.splits == dm.splits  # the same ids: the same split, by the same rule
    maps = dm2.prepared.provider.maps("depth/000")
    assert maps.num_valid == H * W // 2 == 960
    np.testing.assert_array_equal(maps.amplitude[maps.mask], np.load(root / "amp/000.npy")[maps.mask])
    described = dm2.summary()["source_settings"]
    assert described["list_entries_sha256"] != dm.summary()["source_settings"]["list_entries_sha256"]
    # comments and spacing are not the list's content
    (root / "list.txt").write_text("".join(f"depth/{i:03d}.png amp/{i:03d}.npy masks/{i:03d}.png\n" for i in range(6)))
    assert folder_dm(root, cache).make_source().describe() == described


def test_variance_scale_and_simulated_captures_follow_the_files(tmp_path):
    """Records made from the maps: the fixed baseline's matched sigma and the simulator-noised test captures are
    made again when a file of theirs changes (they were keyed on the maps' key alone)."""
    root = write_folder(tmp_path / "ds", n=10)
    cache = tmp_path / "cache"
    dm = folder_dm(root, cache, noise="fixed", simulated_test=True)
    prepared(dm)
    scale = dm.summary()["variance_scale"]
    test_id = dm.splits["test"][0]
    sim = dm.datasets["simulated"]
    first = sim.capture(test_id)
    for sid in dm.splits["train"] + [test_id]:
        cv2.imwrite(str(root / f"{sid}.png"), np.full((H, W), 2600, np.uint16))
    dm2 = folder_dm(root, cache, noise="fixed", simulated_test=True)
    prepared(dm2)
    assert dm2.summary()["variance_scale"] != pytest.approx(scale, rel=1e-3)
    assert len(list(dm2.cache.folder.glob("variance_scale_fixed_*.json"))) == 2
    again = dm2.datasets["simulated"].capture(test_id)
    valid = again.mask
    assert abs(np.median(again.depth_mm[valid]) - 2600) < 50 < abs(np.median(first.depth_mm[first.mask]) - 2600)


def test_capture_whose_files_changed_after_prepare_is_recomputed_when_read(tmp_path):
    root = write_folder(tmp_path / "ds", n=10)
    dm = folder_dm(root, tmp_path / "cache", simulated_test=True)
    prepared(dm)
    test_id = dm.splits["test"][0]
    cv2.imwrite(str(root / f"{test_id}.png"), np.full((H, W), 2600, np.uint16))
    item = dm.datasets["simulated"][0]
    assert item["name"] == test_id
    assert abs(float(item["noisy"][item["mask"] > 0].median()) - 2600) < 50
    assert abs(float(item["clean"][item["mask"] > 0].median()) - 2600) < 1e-3


def test_flyingthings3d_entries_follow_their_mat_files(tmp_path, write_ft3d):
    import scipy.io

    tokens = write_ft3d(tmp_path / "ft3d", [f"t{i:03d}" for i in range(7)], [f"v{i:03d}" for i in range(3)])
    dm = ToFDataModule(
        source="flyingthings3d",
        source_kwargs={"root": str(tmp_path / "ft3d")},
        cache_dir=str(tmp_path / "cache"),
        crop_size=8,
        simulated_test=False,
    )
    prepared(dm)
    token = dm.splits["train"][0]
    gt = tokens[token][0]
    scipy.io.savemat(tmp_path / "ft3d" / "gt_depth_rgb" / f"{token}_gt_depth.mat", {"gt_depth": gt * 0 + 1000.0})
    messages = prepared(dm2 := ToFDataModule(**dm.hparams))
    assert any("flyingthings3d source: 1 sample(s) computed again" in m and token in m for m in messages)
    maps = dm2.prepared.provider.maps(token)
    assert dm2.cache.folder == dm.cache.folder
    assert maps.depth_mm[12, 16] == pytest.approx(2000.0, rel=1e-3)  # the image centre: z = r = 2 x 1000


def test_procedural_keys_and_cache_files_are_unchanged(tmp_path):
    """The procedural source has no files: its maps folder, index, records and entries are named and written as
    before (the committed results depend on them)."""
    for noise, record in (
        ("fixed", "variance_scale_fixed_9140cc800134.json"),
        ("blind", "blind_range_63d401a34e52.json"),
    ):
        dm = ToFDataModule(
            source_kwargs={"num_samples": 3, "height": 16, "width": 24},
            noise=noise,
            seed=2,
            crop_size=8,
            signal_route="physical",
            cache_dir=str(tmp_path / noise),
        )
        dm.prepare_data()
        folder = dm.prepared.cache.folder
        assert folder.relative_to(tmp_path / noise).as_posix() == "procedural-1ce3b4255ddb/maps-6d80bb75630bffb9"
        assert (folder / record).is_file()
        assert (folder.parent / "simulated-test" / "maps-d7d5ae0d1b451bac").is_dir()
        index = json.loads((folder / "index.json").read_text())
        assert index == {
            "samples": {
                "scene_000002": {"num_valid": 346, "shape": [16, 24]},
                "scene_000000": {"num_valid": 348, "shape": [16, 24]},
                "scene_000001": {"num_valid": 384, "shape": [16, 24]},
            }
        }
        meta = json.loads(bytes(np.load(dm.cache.path("scene_000000"))["meta"]).decode())
        assert sorted(meta) == ["format_version", "key", "sample_id", "shape"]


def test_an_entry_of_a_file_source_without_stamps_is_stale(tmp_path):
    """Entries written before stamps were kept (or by a source that had none) are recomputed, not trusted."""
    depth = tmp_path / "d.npy"
    np.save(depth, np.full((4, 5), 1000.0, np.float32))
    cache = MapCache(tmp_path / "c", {"source": "test"})
    ones = np.ones((4, 5), np.float32)
    old = SampleMaps(ones, ones, ones, np.ones((4, 5), bool), ones)
    cache.write("s", old)  # no stamps
    calls = []

    def compute():
        calls.append(1)
        return SampleMaps(ones * 2, ones, ones, np.ones((4, 5), bool), ones)

    maps, status = cache.get_or_compute("s", compute, [depth])
    assert status == "stale" and calls == [1] and maps.depth_mm[0, 0] == 2.0
    maps, status = cache.get_or_compute("s", compute, [depth])
    assert status == "hit" and calls == [1] and maps.depth_mm[0, 0] == 2.0
    assert cache.stats.stale == 1 and cache.stats.stale_ids == ["s"]


def test_a_root_given_relative_or_absolute_shares_the_entries(tmp_path, monkeypatch):
    root = write_folder(tmp_path / "ds")
    dm = folder_dm(root, tmp_path / "cache")
    prepared(dm)
    monkeypatch.chdir(tmp_path)
    relative = ToFDataModule(
        source="folder",
        source_kwargs={"root": "ds"},
        cache_dir=str(tmp_path / "cache"),
        crop_size=16,
        simulated_test=False,
        holes=False,
    )
    assert not [m for m in prepared(relative) if "computed again" in m]
    assert relative.cache.folder == dm.cache.folder and relative.cache.stats.misses == 0
