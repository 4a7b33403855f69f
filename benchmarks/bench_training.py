"""Training-step time per backbone: with the data loader in the loop vs a pre-loaded batch, side by side.

One training step = DepthRestorer input normalisation + backbone forward + loss (``full``) + backward + AdamW
step, batch 4 of 320 x 320 crops (the paper's setting) from the built-in procedural scenes. For every backbone
(sizes of configs/backbone/<name>.yaml) the script times the same number of steps

* "loader": the next batch comes from ``ToFDataModule.train_dataloader()`` (crop, flips, noise synthesis
  in the loop; ``--workers`` loader processes), and
* "compute": one batch fetched beforehand is reused,

and prints both plus their ratio (loader / compute; 1.00 = the data pipeline costs nothing).

    python benchmarks/bench_training.py            # batch 4, 320 x 320, 3 timed steps per backbone
    python benchmarks/bench_training.py --quick    # batch 4, 64 x 64, 2 steps, fast backbones only
    python benchmarks/bench_training.py --backbones unet dvss --crop 128 --steps 5
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
QUICK_BACKBONES = ["unet", "deeptof", "tofkpn", "restormer", "dvss"]


def backbone_config(name: str) -> dict:
    """configs/backbone/<name>.yaml as Hydra composes it (the dvss ablations inherit dvss.yaml)."""
    from omegaconf import OmegaConf

    from tofdenoise.config import compose_config

    return dict(OmegaConf.to_container(compose_config([f"backbone={name}"]).backbone, resolve=True))


def backbone_kwargs(name: str) -> dict:
    return dict(backbone_config(name)["kwargs"])


def make_data(crop: int, batch: int, workers: int, cache: str):
    from tofdenoise.data_modules import ToFDataModule

    height, width = max(480, crop), max(640, crop)
    dm = ToFDataModule(
        source="procedural",
        source_kwargs={"num_samples": 20, "height": height, "width": width},
        crop_size=crop,
        batch_size=batch,
        num_workers=workers,
        cache_dir=cache,
        seed=0,
    )
    dm.setup("fit")
    return dm


def time_steps(model, optimizer, batches, steps: int) -> list[float]:
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        batch = batches()
        loss = model.training_loss(batch, model.backbone)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        times.append(time.perf_counter() - t0)
    return times


def bench_backbone(name: str, dm, steps: int) -> tuple[float, float, int]:
    from tofdenoise.models import count_parameters
    from tofdenoise.training.module import DepthRestorer

    # the amplitude channel when the backbone's config asks for it (rcf), as configs/model/default.yaml does
    signal = bool(backbone_config(name).get("use_signal_channel", False))
    model = DepthRestorer(
        backbone=name, backbone_kwargs=backbone_kwargs(name), loss="full", conditioning={"use_signal_channel": signal}
    )
    model.train()
    optimizer = torch.optim.AdamW(model.backbone.parameters(), lr=2e-4)
    loader = dm.train_dataloader()

    def endless():
        while True:
            yield from loader

    stream = endless()
    fixed = next(stream)
    time_steps(model, optimizer, lambda: fixed, 1)  # warm-up (allocator, first-call costs)
    # interleave the two modes so that machine load drifts hit both alike
    with_loader, compute_only = [], []
    for _ in range(steps):
        with_loader += time_steps(model, optimizer, lambda: next(stream), 1)
        compute_only += time_steps(model, optimizer, lambda: fixed, 1)
    return statistics.median(with_loader), statistics.median(compute_only), count_parameters(model.backbone)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="64 x 64 crops, 2 steps (smoke run of the script)")
    ap.add_argument("--backbones", nargs="*", default=None, help="default: every registered backbone")
    ap.add_argument("--crop", type=int, default=None, help="crop size (default 320, --quick 64)")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--steps", type=int, default=None, help="timed steps per mode (default 3, --quick 2)")
    ap.add_argument("--workers", type=int, default=0, help="data loader worker processes")
    args = ap.parse_args(argv)

    from tofdenoise.models import available_backbones

    crop = args.crop or (64 if args.quick else 320)
    steps = args.steps or (2 if args.quick else 3)
    names = args.backbones or (QUICK_BACKBONES if args.quick else available_backbones())
    unknown = [n for n in names if n not in available_backbones()]
    if unknown:
        print(f"unknown backbone(s) {unknown}; valid names: {', '.join(available_backbones())}", file=sys.stderr)
        return 2
    torch.manual_seed(0)
    print(
        f"# training step, batch {args.batch}, crop {crop}x{crop}, loss full, AdamW; median of {steps} steps "
        f"per mode; torch threads {torch.get_num_threads()}, loader workers {args.workers}"
    )
    with tempfile.TemporaryDirectory() as cache:
        t0 = time.perf_counter()
        dm = make_data(crop, args.batch, args.workers, cache)
        print(f"# data set-up (20 procedural scenes, noise maps): {time.perf_counter() - t0:.1f} s")
        print("| backbone | params | step with loader (s) | step, batch pre-loaded (s) | loader / compute |")
        print("|---|---:|---:|---:|---:|")
        for name in names:
            loader_s, compute_s, params = bench_backbone(name, dm, steps)
            print(
                f"| {name} | {params / 1e6:.2f} M | {loader_s:.3f} | {compute_s:.3f} | {loader_s / compute_s:.2f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
