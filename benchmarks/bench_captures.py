"""Simulated capture sets: scenes one at a time against ``--workers`` scenes at a time (spawned processes).

Measured side by side in one run, on the same settings: the stand-in camera (cam75), 100 high-exposure frames per
scene, 3 x 3 mixed-pixel samples, at the CPU profile's size (128 x 160) and the GPU profiles' (480 x 640). Each
timing writes a fresh set in a temporary folder. The two sets of a size must be byte-identical: the script fails
otherwise.

Usage: python benchmarks/bench_captures.py [--quick] [--workers N]   (default N: the CPU cores)
"""

from __future__ import annotations

import argparse
import filecmp
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from tofdenoise.data_modules.capture_simulation import simulate_capture_set


def _files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def _same(a: Path, b: Path) -> bool:
    files = _files(a)
    return files == _files(b) and all(filecmp.cmp(a / f, b / f, shallow=False) for f in files)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer scenes and frames (smoke run)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args(argv)
    scenes, frames = (2, 10) if args.quick else (4, 100)
    sizes = [(128, 160), (480, 640)]
    print(f"{scenes} scenes, {frames} frames, mixed pixels 3, camera cam75; {args.workers} workers", flush=True)
    print(f"{'':22s}{'1 worker s':>12s}{f'{args.workers} workers s':>14s}{'speed-up':>10s}", flush=True)
    workdir = Path(tempfile.mkdtemp(prefix="bench_captures_"))
    identical = True
    try:
        for height, width in sizes:
            settings = dict(scenes=scenes, frames=frames, height=height, width=width, seed=1000, mixed_pixels=3)
            seconds = {}
            for workers in (1, args.workers):
                out = workdir / f"{height}x{width}-{workers}"
                started = time.perf_counter()
                simulate_capture_set(out, calib="cam75", workers=workers, **settings)
                seconds[workers] = time.perf_counter() - started
            same = _same(workdir / f"{height}x{width}-1", workdir / f"{height}x{width}-{args.workers}")
            identical &= same
            one, many = seconds[1], seconds[args.workers]
            print(
                f"{f'{height} x {width}':22s}{one:12.1f}{many:14.1f}{one / many:10.2f}"
                f"{'' if same else '  FILES DIFFER'}",
                flush=True,
            )
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    print(f"byte-identical sets: {'yes' if identical else 'NO'}")
    return 0 if identical else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
