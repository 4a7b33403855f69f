"""What keeping the map cache fresh costs a file-backed source (docs/data.md, "Per-sample maps and the cache").

A folder source of N small samples (40 x 48: a 16-bit depth PNG and a float32 amplitude .npy each, 2N files) is
prepared once (maps computed, files hashed, stamps recorded); then, each timed best of three:

- ``check, nothing changed``: the stamp check of the index (``stamps_state`` of every sample: one ``stat`` a file);
- ``prepare + setup, nothing changed``: the datamodule's whole preparation on the filled cache;
- ``read N entries``: ``MapProvider.get`` of every sample from the cache, with the stamp check (stat of the files)
  and without it (as a source without files reads);
- ``check after touching every file``: their stat stamps moved, so every file is hashed once (SHA-256) and found
  unchanged;
- ``hash N files``: SHA-256 of the 2N files, the part of a cold fill that stamps add.

Usage: python benchmarks/bench_cache_stamps.py [--quick] [--samples N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from tofdenoise.data_modules import ToFDataModule  # noqa: E402
from tofdenoise.data_modules.file_stamps import _DIGESTS, file_sha256, stamps_state  # noqa: E402

H, W = 40, 48


def write_folder(root: Path, n: int) -> None:
    rng = np.random.default_rng(0)
    (root / "depth").mkdir(parents=True)
    (root / "amp").mkdir()
    for i in range(n):
        cv2.imwrite(str(root / "depth" / f"{i:05d}.png"), rng.uniform(500, 2000, (H, W)).astype(np.uint16))
        np.save(root / "amp" / f"{i:05d}.npy", rng.uniform(10, 1000, (H, W)).astype(np.float32))
    (root / "list.txt").write_text("".join(f"depth/{i:05d}.png amp/{i:05d}.npy\n" for i in range(n)))


def best(fn, repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--quick", action="store_true", help="100 samples")
    args = parser.parse_args(argv)
    n = 100 if args.quick else args.samples
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        root, cache = Path(tmp) / "ds", Path(tmp) / "cache"
        write_folder(root, n)
        settings = dict(source="folder", source_kwargs={"root": str(root)}, cache_dir=str(cache))
        settings.update(crop_size=16, simulated_test=False, holes=False)
        start = time.perf_counter()
        dm = ToFDataModule(**settings)
        dm.prepare_data()
        dm.setup()
        fill = time.perf_counter() - start
        provider = dm.prepared.provider
        ids = provider.source.sample_ids()
        files = [provider.files(i) for i in ids]
        paths = [p for trio in files for p in trio]
        index = json.loads((dm.cache.folder / "index.json").read_text())["samples"]
        recorded = [index[i]["files"] for i in ids]

        def check():
            assert all(stamps_state(r, f)[0] == "fresh" for r, f in zip(recorded, files, strict=True))

        def prepare():
            fresh = ToFDataModule(**settings)
            fresh.prepare_data()
            fresh.setup()

        def read(with_files: bool):
            cache = provider.cache
            for i in ids:
                cache.get_or_compute(i, lambda: None, provider.files(i) if with_files else None)

        rows = [
            (f"fill: prepare + setup of {n} samples (maps computed, files hashed)", fill),
            (f"check, nothing changed ({len(paths)} files: one stat each)", best(check)),
            ("prepare + setup, nothing changed", best(prepare)),
            (f"read {n} entries, stamp check (stat)", best(lambda: read(True))),
            (f"read {n} entries, no stamp check", best(lambda: read(False))),
            (f"hash {len(paths)} files (SHA-256)", best(lambda: [file_sha256(p) for p in paths])),
        ]
        for p in paths:
            os.utime(p)
        _DIGESTS.clear()  # as in a new process: nothing hashed yet
        start = time.perf_counter()
        assert all(stamps_state(r, f)[0] == "restamped" for r, f in zip(recorded, files, strict=True))
        rows.append(
            (f"check after touching every file ({len(paths)} hashed, same content)", time.perf_counter() - start)
        )
        size = sum(os.path.getsize(p) for p in paths)
    print(f"{n} samples of {H} x {W}, {len(paths)} files, {size / 1e6:.1f} MB")
    print(f"{'':<72} {'s':>8} {'ms / 1000 files':>16}")
    for label, seconds in rows:
        print(f"{label:<72} {seconds:8.3f} {1000 * seconds / len(paths) * 1000:16.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
