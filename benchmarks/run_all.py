"""Run the benchmark scripts of ORDER (benchmarks/bench_<name>.py) in one process each, in that order.
(bench_mamba_scan.py is not among them: it needs a checkout of mamba-ssm, ``--src``, and a CUDA machine.)

Each script prints its own side-by-side table with ratios measured in the same run.
Usage: python benchmarks/run_all.py [--quick] [name ...]   (e.g. `--quick physics models`);
options starting with `--` are passed on to every script. `make bench BENCH_ARGS=--quick` does the same.
"""

from __future__ import annotations

import platform
import subprocess
import sys
import time
from pathlib import Path

ORDER = [
    "startup",
    "physics",
    "metrics",
    "models",
    "scan_cpu",
    "onnx",
    "export_scan",
    "data",
    "captures",
    "training",
    "gpu",
    "gpu_scan",
]


def main(argv: list[str]) -> int:
    here = Path(__file__).resolve().parent
    options = [a for a in argv if a.startswith("--")]
    wanted = [a for a in argv if not a.startswith("--")] or ORDER
    scripts = [here / f"bench_{name}.py" for name in wanted]
    import torch

    print(f"# tofdenoise benchmarks  {time.strftime('%Y-%m-%d %H:%M:%S')}")
    print(
        f"# python {platform.python_version()}  torch {torch.__version__}  "
        f"threads {torch.get_num_threads()}  cpu {platform.processor() or platform.machine()}"
    )
    failed = []
    for script in scripts:
        if not script.exists():
            print(f"\n## {script.stem}: missing ({script})")
            failed.append(script.stem)
            continue
        print(f"\n## {script.stem}", flush=True)
        rc = subprocess.call([sys.executable, str(script), *options])
        if rc != 0:
            failed.append(script.stem)
    if failed:
        print(f"\nfailed: {', '.join(failed)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
