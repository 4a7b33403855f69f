"""How fast ``tofdenoise`` answers: help texts, refused arguments, and the first frame of ``denoise``.

    python benchmarks/bench_startup.py [--quick] [--repeats 7] [--no-denoise]

Every command runs in a fresh interpreter, as a user's shell starts it (``python -m tofdenoise.cli.main ...``: what
the ``tofdenoise`` console script calls); the table gives the median and the fastest wall time of ``--repeats`` runs,
and the median total import time (the sum of the cumulative times of the top-level imports, ``python -X importtime``),
which depends far less on what else the machine runs than the wall time does. ``python -c pass`` is the
interpreter's own start, the floor of every row. ``fit --help`` runs twice: built by LightningCLI (the help cache
off, as on a first call) and read from the help cache (``tofdenoise.cli.help_cache``, kept in the scratch folder).

``denoise`` on a 640 x 576 frame (the Azure Kinect's NFOV unbinned mode; a smooth synthetic scene, untrained default
U-Net of ``tofdenoise train``'s recipe): the command's wall time, and from its summary the first frame (one-time
set-up included) and the mean of the frames after it. ``--quick``: 3 repeats, 2 frames; ``--no-denoise`` skips it.
Set ``PYTHONPATH`` to a checkout's ``src`` to measure that checkout.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = [sys.executable, "-m", "tofdenoise.cli.main"]

#: the row of ``fit --help`` built by LightningCLI (the help cache off, as on a first call)
FIT_HELP_BUILT = "tofdenoise fit --help (LightningCLI, built)"

#: (label, arguments): the help texts and refusals; paths are relative to a scratch folder holding frames/ and a.ckpt
COMMANDS: list[tuple[str, list[str]]] = [
    ("tofdenoise --help", ["--help"]),
    ("tofdenoise train --help", ["train", "--help"]),
    ("tofdenoise classic --help", ["classic", "--help"]),
    ("tofdenoise denoise --help", ["denoise", "--help"]),
    ("tofdenoise export --help", ["export", "--help"]),
    ("tofdenoise evaluate --help", ["evaluate", "--help"]),
    ("tofdenoise report --help", ["report", "--help"]),
    ("tofdenoise grid --help", ["grid", "--help"]),
    ("tofdenoise reproduce --help", ["reproduce", "--help"]),
    ("tofdenoise sensor --help", ["sensor", "--help"]),
    ("denoise missing.npy --ckpt nope.ckpt (refused)", ["denoise", "missing.npy", "--ckpt", "nope.ckpt", "--out", "o"]),
    (
        "denoise frames --ckpt a.ckpt --bogus (refused)",
        ["denoise", "frames", "--ckpt", "a.ckpt", "--out", "o", "--bogus"],
    ),
    ("export nope.ckpt --onnx m.onnx (refused)", ["export", "nope.ckpt", "--onnx", "m.onnx"]),
    ("train backbone=nope (refused by Hydra)", ["train", "backbone=nope"]),
    (FIT_HELP_BUILT, ["fit", "--help"]),
    ("tofdenoise fit --help (LightningCLI, stored)", ["fit", "--help"]),
]

#: the environment of a row beyond the bench's own (help cache in the scratch folder): the built row turns it off
ROW_ENV: dict[str, dict[str, str]] = {FIT_HELP_BUILT: {"TOFDENOISE_CACHE_DIR": ""}}


def _wall_s(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> float:
    started = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    return time.perf_counter() - started


def _import_ms(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> float:
    """Total import time [ms] of the command: the cumulative microseconds of its top-level imports."""
    proc = subprocess.run(
        [cmd[0], "-X", "importtime", *cmd[1:]], cwd=cwd, env=env, capture_output=True, text=True, check=False
    )
    total_us = 0
    for line in proc.stderr.splitlines():
        match = re.match(r"import time:\s+\d+ \|\s+(\d+) \| (\S.*)$", line)  # no indent: a top-level import
        if match:
            total_us += int(match.group(1))
    return total_us / 1000


def _frames(folder: Path, count: int, height: int = 576, width: int = 640) -> None:
    """``count`` 16-bit depth PNGs [mm] of a tilted plane with a box and sensor-like noise, 2 % holes."""
    import numpy as np

    from tofdenoise.data_modules.io import write_depth_png16

    rng = np.random.default_rng(0)
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    for i in range(count):
        depth = 900.0 + 0.6 * rows + 0.3 * cols
        depth[150:350, 200:420] -= 250.0
        depth += rng.normal(0.0, 4.0, depth.shape)
        depth[rng.random(depth.shape) < 0.02] = 0.0
        write_depth_png16(folder / f"frame_{i:03d}.png", depth)


def _checkpoint(path: Path) -> Path:
    """An untrained U-Net checkpoint of the default recipe (``configs/backbone/unet.yaml``'s width and stages)."""
    import lightning
    import torch

    from tofdenoise.config import compose_config
    from tofdenoise.training.learned_guard import LEARNED_RECORD_KEY
    from tofdenoise.training.module import DepthRestorer

    cfg = compose_config([])
    torch.manual_seed(0)
    model = DepthRestorer(backbone="unet", backbone_kwargs=dict(cfg.model.backbone_kwargs))
    torch.save(
        {
            "state_dict": model.state_dict(),
            "hyper_parameters": dict(model.hparams),
            "pytorch-lightning_version": lightning.__version__,
            LEARNED_RECORD_KEY: {"trained_steps": 0, "best_val_mae_mm": None, "raw_val_mae_mm": None},
        },
        path,
    )
    return path


def _denoise(scratch: Path, repeats: int, frames: int) -> None:
    folder = scratch / "kinect"
    folder.mkdir()
    _frames(folder, frames)
    ckpt = _checkpoint(scratch / "unet.ckpt")
    walls, firsts, rests = [], [], []
    for i in range(repeats):
        cmd = [*CLI, "denoise", str(folder), "--ckpt", str(ckpt), "--out", str(scratch / f"out{i}"), "--quiet"]
        started = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        walls.append(time.perf_counter() - started)
        summary = next((line for line in proc.stderr.splitlines() if "frame(s) done" in line), proc.stderr[-300:])
        timing = re.search(r"([\d.]+) s/frame after the first \(([\d.]+) s", summary)
        if proc.returncode != 0 or timing is None:
            print(f"denoise failed (exit {proc.returncode}): {summary}")
            return
        rests.append(float(timing.group(1)))
        firsts.append(float(timing.group(2)))
    print(
        f"\ndenoise, {frames} frames of 640 x 576 (16-bit PNG), untrained default U-Net, CPU, {repeats} runs (median)"
    )
    print(f"{'command wall time (imports, model, all frames)':<50} {statistics.median(walls):8.2f} s")
    print(f"{'first frame (one-time set-up included)':<50} {statistics.median(firsts):8.2f} s")
    print(f"{'each frame after the first':<50} {statistics.median(rests):8.2f} s")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="3 repeats, 2 denoise frames")
    p.add_argument("--repeats", type=int, default=None, help="runs per command (default 7; --quick: 3)")
    p.add_argument("--no-denoise", action="store_true", help="skip the denoise rows")
    args = p.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 7)
    with tempfile.TemporaryDirectory(prefix="tofdenoise-startup-") as tmp:
        scratch = Path(tmp)
        (scratch / "frames").mkdir()
        (scratch / "a.ckpt").write_bytes(b"never read: the command is refused first")
        print(f"{'command':<50} {'median s':>9} {'min s':>7} {'imports ms':>11}   ({repeats} runs each)")
        for label, args_ in [("python -c pass (the interpreter)", None), *COMMANDS]:
            cmd = [sys.executable, "-c", "pass"] if args_ is None else [*CLI, *args_]
            env = {**os.environ, "TOFDENOISE_CACHE_DIR": str(scratch / "cache"), **ROW_ENV.get(label, {})}
            _wall_s(cmd, scratch, env)  # warm the file cache (and store a Lightning verb's help)
            walls = [_wall_s(cmd, scratch, env) for _ in range(repeats)]
            imports = statistics.median(_import_ms(cmd, scratch, env) for _ in range(max(1, repeats // 2)))
            print(f"{label:<50} {statistics.median(walls):9.3f} {min(walls):7.3f} {imports:11.0f}", flush=True)
        if not args.no_denoise:
            _denoise(scratch, max(1, repeats // 3) if not args.quick else 1, 2 if args.quick else 4)
    return 0


if __name__ == "__main__":
    sys.exit(main())
