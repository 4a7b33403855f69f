"""Eager vs ``torch.compile`` training step (forward + backward) of a backbone, and the first compile's cost.

The network (sizes of configs/backbone/<name>.yaml unless ``--width``) is compiled as ``model.compile=true`` does
(``torch.compile`` of the backbone, inductor); the first compiled step's time is the compile (forward and
backward graphs; it depends on the inductor cache: an empty ``TORCHINDUCTOR_CACHE_DIR`` gives the first-time cost).
Then eager and compiled steps are timed interleaved (the median of ``--steps`` each), so that a shared machine's
load hits both alike.

    python benchmarks/bench_compile.py                         # dvss, batch 2 x 1 x 64 x 64, 8 steps
    python benchmarks/bench_compile.py --backbone unet --size 128
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from tofdenoise.models.registry import build_backbone


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--backbone", default="dvss")
    parser.add_argument("--size", type=int, default=64, help="square crop side (pixels)")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--steps", type=int, default=8, help="timed steps of each kind")
    parser.add_argument("--width", type=int, default=None, help="the backbone's width (default: its config's)")
    args = parser.parse_args()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    torch.manual_seed(0)
    kwargs = {} if args.width is None else {"width": args.width}
    net = build_backbone(args.backbone, in_channels=1, **kwargs).to(device)
    x = torch.randn(args.batch, 1, args.size, args.size, device=device)

    def step(fn) -> float:
        net.zero_grad(set_to_none=True)
        if device == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn(x).square().mean().backward()
        if device == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - start

    compiled = torch.compile(net)
    first = step(compiled)
    step(net)
    step(compiled)
    eager, comp = [], []
    for _ in range(args.steps):
        eager.append(step(net))
        comp.append(step(compiled))
    print(
        f"{args.backbone}, batch {args.batch} x 1 x {args.size} x {args.size}, {device}, "
        f"{torch.get_num_threads()} threads: eager step {statistics.median(eager) * 1e3:.0f} ms, compiled step "
        f"{statistics.median(comp) * 1e3:.0f} ms (medians of {args.steps}); first compiled step {first:.1f} s"
    )


if __name__ == "__main__":
    main()
