"""A grid's data prepared once before its runs (experiments.grid_data): one preparation per distinct data node,
and a run on the prepared cache gives the records of a run that prepared its own."""

from __future__ import annotations

import json

from tofdenoise.experiments.grid_data import prepare_grid_data
from tofdenoise.experiments.runner import RunSpec, run_all

from .test_executors import RECORDS, TINY


def _spec(name: str, cache, *extra: str) -> RunSpec:
    return RunSpec(name, (*TINY, "trainer.max_epochs=1", f"++data.cache_dir={cache}", *extra))


def test_each_distinct_data_node_is_prepared_once_and_a_run_on_it_equals_a_cold_one(tmp_path):
    warm, cold = tmp_path / "warm-cache", tmp_path / "cold-cache"
    specs = [
        _spec("unet-range-s0", warm, "noise=range", "seed=0"),
        _spec("unet-range-s0-again", warm, "noise=range", "seed=0", "model.optim.lr=1e-3"),  # same data
        _spec("unet-hetero-s0", warm, "noise=hetero", "seed=0"),
        RunSpec("bilateral", ("method=bilateral",), entry="classical"),  # no training data to prepare
    ]
    lines: list[str] = []
    assert prepare_grid_data(specs, workers=2, log=lines.append) == ["unet-range-s0", "unet-hetero-s0"]
    assert len(lines) == 2 and all("prepared ahead" in line for line in lines)
    scales = [json.loads(p.read_text())["scale"] for p in warm.rglob("variance_scale_range_*.json")]
    assert len(scales) == 1 and scales[0] > 0  # the range baseline's variance match is stored ahead of its run
    # the run on the prepared cache and the same run on a cache it prepares itself: the same records
    run_all([specs[0]], tmp_path / "runs-warm", echo=False)
    run_all([_spec("unet-range-s0", cold, "noise=range", "seed=0")], tmp_path / "runs-cold", echo=False)
    for name in RECORDS:
        warm_bytes = (tmp_path / "runs-warm" / "unet-range-s0" / name).read_bytes()
        assert warm_bytes == (tmp_path / "runs-cold" / "unet-range-s0" / name).read_bytes(), name


def test_a_spec_that_does_not_compose_is_left_to_its_run(tmp_path):
    lines: list[str] = []
    bad = RunSpec("bad", (*TINY, "noise=nope"))
    assert prepare_grid_data([bad], workers=1, log=lines.append) == []
    assert len(lines) == 1 and "bad: data not prepared ahead" in lines[0]
