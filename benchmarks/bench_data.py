"""Data loader throughput with and without the sigma_D map cache, next to the DVSS training step (CPU).

Measured side by side in one run: 320x320 training crops from 640x480 procedural scenes, batch 4, 2 DataLoader
workers. "cached" reads the per-sample maps (depth, signal, sigma_D, mask, amplitude) from the on-disk cache;
"uncached" renders the scene and evaluates the WLS sigma_D map on every read. The DVSS row is one AdamW
training step (forward + backward) of the default DVSS backbone on a (4, 1, 320, 320) batch.

Usage: python benchmarks/bench_data.py [--quick]
"""

from __future__ import annotations

import argparse
import gc
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

warnings.filterwarnings("ignore", message=".*does not have many workers.*")


def loader_throughput(use_cache: bool, cache_dir: Path, num_samples: int, batches: int, workers: int) -> float:
    """Samples per second over `batches` batches after one warm-up batch (workers already running)."""
    from tofdenoise.data_modules import ToFDataModule

    dm = ToFDataModule(
        source_kwargs={"num_samples": num_samples},
        cache_dir=str(cache_dir),
        use_cache=use_cache,
        crop_size=320,
        batch_size=4,
        num_workers=workers,
        persistent_workers=True,
        seed=0,
    )
    dm.prepare_data()
    dm.setup("fit")
    loader = dm.train_dataloader()
    seen = 0
    iterator = iter(loader)
    next(iterator)  # warm-up: worker start-up is not part of the steady-state rate
    start = time.perf_counter()
    while seen < batches * 4:
        try:
            batch = next(iterator)
        except StopIteration:
            iterator = iter(loader)
            continue
        seen += batch["noisy"].shape[0]
    rate = seen / (time.perf_counter() - start)
    # stop the persistent workers now, so the next loader's forked workers do not inherit this iterator
    shutdown = getattr(loader._iterator, "_shutdown_workers", None) if loader._iterator is not None else None
    if shutdown is not None:
        shutdown()
    del iterator, loader
    gc.collect()
    return rate


def dvss_step_rate(steps: int, size: int, warmup: bool) -> tuple[float | None, str]:
    """Training samples per second of the DVSS backbone (batch 4, size x size, CPU), or why it is unavailable.

    A step on a crop smaller than 320x320 costs less than the 320x320 step, so its rate is an upper bound of
    the 320x320 training rate (the comparison with the loader stays conservative).
    """
    try:
        import yaml

        from tofdenoise.models import build_backbone
        from tofdenoise.paths import CONFIG_DIR
    except Exception as exc:  # the models package may be absent in a partial checkout
        return None, f"unavailable ({exc})"
    kwargs = {}
    config = CONFIG_DIR / "backbone" / "dvss.yaml"
    if config.is_file():
        kwargs = dict(yaml.safe_load(config.read_text()).get("kwargs") or {})
    try:
        model = build_backbone("dvss", **kwargs)
    except Exception as exc:
        return None, f"unavailable ({exc})"
    opt = torch.optim.AdamW(model.parameters(), lr=2e-4)
    x = torch.randn(4, int(kwargs.get("in_channels", 1)), size, size)
    y = torch.randn(4, 1, size, size)

    def step():
        opt.zero_grad(set_to_none=True)
        loss = (model(x) - y).abs().mean()
        loss.backward()
        opt.step()

    if warmup:
        step()
    start = time.perf_counter()
    for _ in range(steps):
        step()
    seconds = (time.perf_counter() - start) / steps
    return 4 / seconds, f"{seconds:.2f} s/step at {size}x{size}" + (
        "" if size >= 320 else " (upper bound of the 320x320 rate)"
    )


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer scenes and batches (smoke run)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--dvss-size",
        type=int,
        default=None,
        help="crop size of the DVSS step (default 64, --quick 32; 320 = the training crop, slow on CPU)",
    )
    args = parser.parse_args(argv)
    num_samples, batches, steps = (10, 6, 1) if args.quick else (24, 24, 2)
    dvss_size = args.dvss_size or (32 if args.quick else 64)
    workdir = Path(tempfile.mkdtemp(prefix="bench_data_"))
    try:
        cache_dir = workdir / "cache"
        t0 = time.perf_counter()
        from tofdenoise.data_modules import ToFDataModule

        # fills the cache
        ToFDataModule(source_kwargs={"num_samples": num_samples}, cache_dir=str(cache_dir)).prepare_data()
        fill = time.perf_counter() - t0
        print(
            f"procedural 640x480 scenes: {num_samples}; crops 320x320, batch 4, {args.workers} workers, "
            f"torch threads {torch.get_num_threads()}; cache fill (prepare_data) {fill:.1f} s",
            flush=True,
        )
        print(f"{'':34s}{'samples/s':>12s}{'ratio':>10s}", flush=True)
        # interleaved measurements (uncached, cached, uncached, cached) so load changes hit both alike
        rates = {True: [], False: []}
        for use_cache in (False, True) * (1 if args.quick else 2):
            rates[use_cache].append(loader_throughput(use_cache, cache_dir, num_samples, batches, args.workers))
        uncached, cached = max(rates[False]), max(rates[True])
        print(f"{'loader, uncached (render + WLS)':34s}{uncached:12.2f}{1.0:10.2f}", flush=True)
        print(f"{'loader, cached maps':34s}{cached:12.2f}{cached / uncached:10.2f}", flush=True)
        dvss_rate, dvss_note = dvss_step_rate(steps, dvss_size, warmup=not args.quick)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    if dvss_rate is None:
        print(f"{'DVSS training step (CPU)':34s}{'-':>12s}{'-':>10s}  {dvss_note}")
    else:
        print(f"{'DVSS training step (CPU)':34s}{dvss_rate:12.2f}{dvss_rate / uncached:10.2f}  {dvss_note}")
    ok = cached >= 2.0 * uncached
    print(f"cached / uncached = {cached / uncached:.2f} (target >= 2): {'OK' if ok else 'BELOW TARGET'}")
    if dvss_rate is not None:
        faster = cached > dvss_rate
        print(f"cached loader / DVSS step = {cached / dvss_rate:.1f}x (target > 1): {'OK' if faster else 'BELOW'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
