"""Metric cost, side by side in one run: the exact masked per-image metrics vs torchmetrics' (unmasked) SSIM.

Usage: python benchmarks/bench_metrics.py [--quick]
"""

from __future__ import annotations

import argparse
import time

import torch
from torchmetrics.functional.image import structural_similarity_index_measure as tm_ssim

from tofdenoise.training.metrics import D_MAX_MM, depth_metrics_per_image


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="one repeat on a 2 x 240 x 320 batch")
    args = parser.parse_args()
    batch, height, width, repeats = (2, 240, 320, 1) if args.quick else (4, 480, 640, 5)
    gen = torch.Generator().manual_seed(0)
    ref = 500 + 1500 * torch.rand(batch, 1, height, width, generator=gen)
    pred = ref + 10 * torch.randn(ref.shape, generator=gen)
    mask = (torch.rand(ref.shape, generator=gen) > 0.1).float()

    ours = _time(lambda: depth_metrics_per_image(pred, ref, mask), repeats)
    tm64 = _time(lambda: tm_ssim(pred.double(), ref.double(), data_range=D_MAX_MM, reduction="none"), repeats)
    tm32 = _time(lambda: tm_ssim(pred, ref, data_range=D_MAX_MM, reduction="none"), repeats)
    print(
        f"batch {batch}x1x{height}x{width}, 10% of pixels masked, torch {torch.__version__}, "
        f"threads {torch.get_num_threads()}, {repeats} repeats"
    )
    print("| computation | ms per batch | ratio |\n|---|---:|---:|")
    print(f"| depth_metrics_per_image (4 metrics, masked SSIM, float64) | {ours * 1e3:.1f} | 1.00 |")
    print(f"| torchmetrics SSIM alone, float64, no mask | {tm64 * 1e3:.1f} | {tm64 / ours:.2f} |")
    print(f"| torchmetrics SSIM alone, float32, no mask | {tm32 * 1e3:.1f} | {tm32 / ours:.2f} |")


if __name__ == "__main__":
    main()
