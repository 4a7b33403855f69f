"""CPU training with a fixed seed and thread count is bit-identical run to run (issue 39): the same tiny run twice,
the first on a fresh data cache and the second on the cache the first wrote, gives the same weights, the same
optimiser state, the same logged losses and the same test metrics, exactly (docs/training.md, "Reproducibility").
Each run names the commit that made it in run_info.json."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
import torch

from tofdenoise.cli.train import run
from tofdenoise.config import compose_config
from tofdenoise.records import code_commit

#: intra-op threads of both runs (the reductions of a convolution split by thread: the count is part of the recipe)
THREADS = 2


@pytest.fixture
def fixed_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(THREADS)
    yield
    torch.set_num_threads(before)


def _train(run_dir: Path, cache: Path, tiny, backbone: str) -> dict:
    cfg = compose_config(
        tiny(run_dir, cache, backbone, num_samples=12) + ["logger=csv", "trainer.max_epochs=2", "seed=3"]
    )
    run(cfg)
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")
    with open(run_dir / "csv" / "metrics.csv") as fh:
        losses = [{k: v for k, v in row.items() if k.startswith("train/")} for row in csv.DictReader(fh)]
    return {
        "state_dict": ckpt["state_dict"],
        "optimizer": ckpt["optimizer_states"],
        "losses": losses,
        "metrics": json.loads((run_dir / "metrics.json").read_text()),
        "per_image": (run_dir / "per_image" / "synthetic.csv").read_text(),
        "run_info": json.loads((run_dir / "run_info.json").read_text()),
    }


def _flat(state, prefix=""):
    """Every tensor of a nested optimiser state, keyed by its path."""
    if isinstance(state, torch.Tensor):
        yield prefix, state
    elif isinstance(state, dict):
        for k, v in state.items():
            yield from _flat(v, f"{prefix}/{k}")
    elif isinstance(state, (list, tuple)):
        for i, v in enumerate(state):
            yield from _flat(v, f"{prefix}/{i}")


@pytest.mark.parametrize("backbone", ["unet", pytest.param("dvss", marks=pytest.mark.slow)])
def test_cpu_training_is_bit_identical_run_to_run(backbone, tmp_path, tiny, fixed_threads):
    cache = tmp_path / "cache"  # the first run fills it, the second reads it
    first = _train(tmp_path / "first", cache, tiny, backbone)
    second = _train(tmp_path / "second", cache, tiny, backbone)

    assert first["state_dict"].keys() == second["state_dict"].keys()
    differ = [k for k, v in first["state_dict"].items() if not torch.equal(v, second["state_dict"][k])]
    assert not differ, f"weights differ run to run: {differ}"
    a, b = dict(_flat(first["optimizer"])), dict(_flat(second["optimizer"]))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert first["losses"] == second["losses"] and len(first["losses"]) > 0
    for key in ("synthetic", "best_val_mae_mm", "raw_val_mae_mm", "trained_steps"):
        assert first["metrics"][key] == second["metrics"][key], key
    assert first["per_image"] == second["per_image"]
    # the runs trained: identical because seeded, not because nothing moved
    assert first["metrics"]["trained_steps"] > 0


def test_run_info_names_the_commit_that_made_it(tmp_path, tiny, fixed_threads):
    """run_info.json carries the commit of the checkout the package runs from (with its dirty flag)."""
    cfg = compose_config(tiny(tmp_path, tmp_path / "cache") + ["+trainer.fast_dev_run=true", "logger=csv"])
    run(cfg)
    info = json.loads((tmp_path / "run_info.json").read_text())
    expected = code_commit()
    assert {k: info.get(k) for k in expected} == expected
    if expected["commit"] is not None:  # the tests run from a git checkout
        assert len(info["commit"]) == 40 and isinstance(info["commit_dirty"], bool)
