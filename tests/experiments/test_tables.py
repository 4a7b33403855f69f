"""The paper's tables as run grids, the orderings they claim, and the results page built from run records."""

from __future__ import annotations

import json
import math
import shutil
import statistics
from pathlib import Path

import pytest

from tofdenoise.experiments.runner import RunSpec
from tofdenoise.experiments.tables import (
    CLAIMS,
    TABLE_PROFILES,
    TABLES,
    claim_holds,
    claim_steps,
    pooled_steps,
    table_specs,
)
from tofdenoise.paths import REPO_ROOT
from tofdenoise.records import RecordError, learned_verdict
from tofdenoise.reporting.results_page import load_records, results_markdown, run_minutes, seeds_present


def test_specs_are_one_per_distinct_run_and_shared_across_tables():
    specs1 = table_specs("1", [0, 1])
    names1 = [s.name for s in specs1]
    # raw needs no run of its own; the classical filter has one run for all seeds (nothing in it depends on the seed)
    assert len(names1) == len(set(names1)) == 2 * 5 + 1
    assert "dvss-hetero-l1-s1" in names1 and "bilateral" in names1 and "bilateral-s1" not in names1
    # the DVSS + hetero + L1 run is a row of every table, under the same folder name
    for table in ("2", "3"):
        assert "dvss-hetero-l1-s0" in {s.name for s in table_specs(table, [0])}
    # Table 3: the paper's 7 runs and the blind Gaussian per backbone
    assert len(table_specs("2", [0])) == 6 and len(table_specs("3", [0])) == 10
    blind = [s for s in table_specs("3", [0]) if "noise=blind" in s.overrides]
    assert sorted(s.name for s in blind) == ["dvss-blind-l1-s0", "restormer-blind-l1-s0", "unet-blind-l1-s0"]


def test_spec_overrides_and_entries():
    specs = {
        s.name: s
        for s in table_specs(
            "3", [2], common=("experiment=reproduce_cpu",), per_backbone={"unet": ("backbone.kwargs.width=8",)}
        )
    }
    s = specs["unet-range-l1-s2"]
    assert s.entry == "train"
    assert s.overrides[:4] == ("backbone=unet", "noise=range", "loss=l1", "seed=2")
    assert "experiment=reproduce_cpu" in s.overrides and s.overrides[-1] == "backbone.kwargs.width=8"
    bil = {x.name: x for x in table_specs("1", [1, 2])}["bilateral"]
    assert bil.entry == "classical" and bil.overrides == ("seed=1",)
    with pytest.raises(ValueError, match="unknown entry 'nope'"):
        RunSpec("x", (), entry="nope")
    with pytest.raises(ValueError, match="unknown table '4'"):
        table_specs("4", [0])


def test_claims_name_rows_of_their_table():
    for claim in CLAIMS:
        keys = {r.key for r in TABLES[claim.table]}
        assert set(claim.chain) <= keys, claim
        assert len(claim.chain) >= 2


def _metrics(mae: float, real_mae: float | None = None, raw_mae: float = 7.0, earlier: bool = False) -> dict:
    """A run's ``metrics.json``: the current protocol (a simulator-noised split beside the synthetic one) unless
    ``earlier``."""
    entry = {
        "psnr_db": 40.0,
        "mae_mm": mae,
        "mse_mm2": mae * 10,
        "ssim": 0.99,
        "raw": {"psnr_db": 35.0, "mae_mm": raw_mae, "mse_mm2": 70.0, "ssim": 0.9},
    }
    out = {"synthetic": entry, **learned_verdict(10, mae, raw_mae)}
    if not earlier:
        out["simulated"] = {**entry, "mae_mm": mae + 3.0}
    if real_mae is not None:
        out["real"] = {**entry, "mae_mm": real_mae, "raw": {**entry["raw"], "mae_mm": raw_mae + 1}}
    return out


DVSS_NOISE_CLAIM = next(c for c in CLAIMS if c.text.startswith("DVSS: hetero < range < fixed (synthetic"))


def _dvss_noise_runs(maes_by_seed: dict[int, tuple[float, ...]]) -> dict[str, dict]:
    """Records of the DVSS noise rows: {seed: (hetero, range, fixed) synthetic MAE}, a shorter tuple = runs
    missing."""
    return {
        f"dvss-{noise}-l1-s{seed}": _metrics(mae)
        for seed, maes in maes_by_seed.items()
        for noise, mae in zip(("hetero", "range", "fixed"), maes)
    }


def test_claim_holds_per_seed():
    claim = DVSS_NOISE_CLAIM
    table = _dvss_noise_runs({0: (2.0, 2.5, 3.0), 1: (2.6, 2.5, 3.0)})
    assert claim_holds(claim, 0, table.get) is True
    assert claim_holds(claim, 1, table.get) is False
    assert claim_holds(claim, 2, table.get) is None  # not run
    # the raw row of Table 1 reads the noisy input of the DVSS L1 run of the same seed
    real = next(c for c in CLAIMS if c.metric == "real_mae_mm" and c.table == "1")
    runs = {
        "dvss-hetero-full-s0": _metrics(2.0, 3.0),
        "tofkpn-hetero-l1-s0": _metrics(3.0, 4.0),
        "rcf-hetero-l1-s0": _metrics(3.1, 4.5),
        "deeptof-hetero-l1-s0": _metrics(4.0, 5.0),
        "dvss-hetero-l1-s0": _metrics(2.2, 3.5, raw_mae=6.0),
    }  # raw real MAE = 7.0
    assert claim_holds(real, 0, runs.get) is True
    runs["dvss-hetero-l1-s0"] = _metrics(2.2, 3.5, raw_mae=3.5)  # raw real MAE 4.5 < DeepToF's 5.0
    assert claim_holds(real, 0, runs.get) is False


def test_claim_steps_are_paired_by_seed_over_complete_seeds():
    """Hand-computed: each step is the mean over the seeds in which every row ran of the per-seed difference
    between consecutive rows, with the standard deviation of that difference (not of either row)."""
    claim = DVSS_NOISE_CLAIM
    # seed 2 has only its hetero run: it is left out of every step
    table = _dvss_noise_runs({0: (2.0, 2.5, 3.0), 1: (2.6, 2.5, 2.4), 2: (9.0,)})
    steps = claim_steps(claim, [0, 1, 2], table.get)
    # seed 0: range - hetero = 0.5, fixed - range = 0.5; seed 1: -0.1, -0.1
    assert [m for m, _ in steps] == pytest.approx([0.2, 0.2])
    assert [sd for _, sd in steps] == pytest.approx([statistics.stdev([0.5, -0.1])] * 2)
    # rows that move together across seeds: a small step with a small paired spread, although each row's own
    # seed std (0.71) is far larger than the step
    table = _dvss_noise_runs({0: (2.0, 2.1, 2.2), 1: (3.0, 3.1, 3.2)})
    steps = claim_steps(claim, [0, 1], table.get)
    assert [m for m, _ in steps] == pytest.approx([0.1, 0.1])
    assert [sd for _, sd in steps] == pytest.approx([0.0, 0.0], abs=1e-12)
    steps = claim_steps(claim, [0], table.get)
    assert steps == [(pytest.approx(0.1), None), (pytest.approx(0.1), None)]
    assert claim_steps(claim, [2], table.get) == []


def test_the_data_seed_study_is_table_3_on_data_seed_1():
    """``--study dataseed``: Table III's rows with ``++data.seed=1`` in their own folders (``-d1-``), the same
    orderings on them, shown on the CPU profile's page only."""
    specs = table_specs("dataseed", [0])
    assert [s.name for s in specs] == [s.name.replace("-l1-", "-l1-d1-") for s in table_specs("3", [0])]
    assert all("++data.seed=1" in s.overrides for s in specs)
    assert all("++data.seed=1" not in s.overrides for s in table_specs("3", [0]))
    assert [c.text for c in CLAIMS if c.table == "dataseed"] == [c.text for c in CLAIMS if c.table == "3"]
    assert TABLE_PROFILES["dataseed"] == ("cpu",)


def test_pooled_steps_pool_every_data_seed_and_training_seed_pair():
    """Hand-computed: the step over (data seed, training seed) pairs is the mean and std of all six paired
    differences; the ordering holds in a pair when every step is positive."""
    first = DVSS_NOISE_CLAIM
    second = next(c for c in CLAIMS if c.table == "dataseed" and c.text == first.text)
    runs = _dvss_noise_runs({0: (2.0, 2.5, 3.0), 1: (2.6, 2.5, 2.4), 2: (2.0, 2.2, 2.3)})
    d1 = _dvss_noise_runs({0: (3.0, 3.1, 3.5), 1: (3.0, 2.9, 3.1), 2: (3.0, 3.4)})  # seed 2: no fixed run
    runs.update({name.replace("-l1-", "-l1-d1-"): m for name, m in d1.items()})
    steps, pairs, holds = pooled_steps([first, second], [0, 1, 2], runs.get)
    first_steps = [0.5, -0.1, 0.2, 0.1, -0.1]  # range - hetero: data seed 0 (3 seeds), then data seed 1 (2)
    second_steps = [0.5, -0.1, 0.1, 0.4, 0.2]  # fixed - range
    assert pairs == 5
    assert [m for m, _ in steps] == pytest.approx([statistics.fmean(first_steps), statistics.fmean(second_steps)])
    assert [sd for _, sd in steps] == pytest.approx([statistics.stdev(first_steps), statistics.stdev(second_steps)])
    assert holds == 3  # (0, 0), (0, 2), (1, 0)
    assert pooled_steps([first], [0, 1, 2], runs.get)[1:] == (3, 2)
    assert pooled_steps([second], [5], runs.get) == ([], 0, 0)


def _write_run(
    root: Path, name: str, metrics: dict, started="2026-11-22T10:00:00+0000", finished="2026-11-22T10:12:30+0000"
) -> None:
    d = root / name
    d.mkdir(parents=True)
    (d / "metrics.json").write_text(json.dumps(metrics))
    (d / "run_info.json").write_text(json.dumps({"started": started, "finished": finished}))


def test_results_page_mean_std_over_seeds(tmp_path):
    cpu = tmp_path / "cpu"
    maes = {0: 2.0, 1: 2.4, 2: 2.9}
    for seed, mae in maes.items():
        _write_run(cpu, f"dvss-hetero-l1-s{seed}", _metrics(mae, mae + 1))
        _write_run(cpu, f"dvss-range-l1-s{seed}", _metrics(mae + 0.5))
    # a run folder without run_info.json is not a record (an interrupted copy)
    (cpu / "dvss-fixed-l1-s0").mkdir()
    (cpu / "dvss-fixed-l1-s0" / "metrics.json").write_text(json.dumps(_metrics(9.0)))
    records = load_records(cpu)
    assert sorted(records) == [f"dvss-{n}-l1-s{s}" for n in ("hetero", "range") for s in (0, 1, 2)]
    assert seeds_present(records) == [0, 1, 2]
    page = results_markdown(tmp_path)
    mean, std = statistics.fmean(maes.values()), statistics.stdev(maes.values())
    assert f"| DVSS, hetero (proposed) | 40.37 / 40.00 ± 0.00 (n=3) | 2.78 / {mean:.2f} ± {std:.2f} (n=3) |" in page
    assert "| DVSS, fixed Gaussian | 39.40 / - | 3.42 / - |" in page
    # hetero < range holds in all three seeds; the fixed run is missing, so the 3-chain is "not run"
    assert "| hetero < range for U-Net (synthetic MAE) | - | not run | - |" in page
    assert "| DVSS: hetero < range < fixed (synthetic MAE) | - | not run | - |" in page
    assert "| dvss-hetero-l1-s0 | current | yes | 10 | 2.00 | 7.00 | 12.5 | - | - | - |" in page
    # the runs table: a tuned classical filter is "classical", a run that stayed near the raw input is flagged
    _write_run(cpu, "bilateral", {**_metrics(2.5), "learned": False, "trained_steps": 0, "method_kind": "classical"})
    _write_run(cpu, "unet-range-l1-s0", {**_metrics(6.9), "learned": False})
    page = results_markdown(tmp_path)
    assert "| bilateral | current | classical | 0 | 2.50 | 7.00 | 12.5 | - | - | - |" in page
    # one run for every seed, and the raw input is the same in every seed: one value each, not a mean over n
    assert "| Joint bilateral (classical, not in the paper) | - / 40.00 (seed-independent) |" in page
    assert "| Raw iToF (the noisy input) | - / 35.00 (seed-independent) |" in page
    assert "| unet-range-l1-s0 | current | NOT LEARNED | 10 | 6.90 | 7.00 | 12.5 | - | - | - |" in page
    # a resumed run's span includes the stop: marked, and no minutes claimed
    # (its training minutes, images/s and memory come from TrainingCost, summed over the attempts)
    info = json.loads((cpu / "unet-range-l1-s0" / "run_info.json").read_text())
    info.update(resumed="2026-11-22T11:00:00+0000", train_seconds=90.0, train_images_per_second=19.2)
    info.update(peak_gpu_memory_gib=7.94, peak_rss_gib=1.62)
    (cpu / "unet-range-l1-s0" / "run_info.json").write_text(json.dumps(info))
    assert math.isnan(run_minutes(info))
    row = "| unet-range-l1-s0 (resumed) | current | NOT LEARNED | 10 | 6.90 | 7.00 | - | 1.5 | 19.2 | 7.9 / 1.6 |"
    assert row in results_markdown(tmp_path)
    # one seed of both U-Net rows: the step has no spread yet
    _write_run(cpu, "unet-hetero-l1-s0", _metrics(3.0))
    page = results_markdown(tmp_path)
    unet_claim = "| hetero < range for U-Net (synthetic MAE) | 0: yes | holds in every seed run so far |"
    assert f"{unet_claim} +3.900 mm (one seed) |" in page
    # with the fixed runs the 3-chain holds in every seed. Paired by seed: hetero -> range is +0.5 mm in every
    # seed (spread 0, although each row's own seed std is 0.45 mm); range -> fixed is +0.5 / +0.6 / +0.7 mm
    shutil.rmtree(cpu / "dvss-fixed-l1-s0")
    for seed, mae in maes.items():
        _write_run(cpu, f"dvss-fixed-l1-s{seed}", _metrics(mae + 1.0 + 0.1 * seed))
    page = results_markdown(tmp_path)
    assert (
        "| DVSS: hetero < range < fixed (synthetic MAE) | 0: yes, 1: yes, 2: yes | holds in every seed | "
        "+0.500 ± 0.000, +0.600 ± 0.100 mm (n=3) |"
    ) in page
    assert "# Profile `gpu`" not in page  # no GPU records


def test_a_seed_independent_row_shows_one_value_unless_its_seeds_disagree():
    from tofdenoise.reporting.results_page import _row_cell

    raw = TABLES["1"][0]
    dvss = next(r for r in TABLES["1"] if r.key == "dvss_l1")
    assert raw.seed_independent and not dvss.seed_independent
    assert _row_cell(raw, [4.5, 4.5, math.nan], 2) == "4.50 (seed-independent)"
    # inputs that did change with the seed are not hidden behind one value
    assert _row_cell(raw, [4.0, 5.0], 2) == f"4.50 ± {statistics.stdev([4.0, 5.0]):.2f} (n=2)"
    assert _row_cell(dvss, [4.5, 4.5], 2) == "4.50 ± 0.00 (n=2)"


def test_run_minutes():
    assert run_minutes({"started": "2026-11-22T10:00:00+0000", "finished": "2026-11-22T11:30:00+0000"}) == 90.0
    assert math.isnan(run_minutes({"started": "2026-11-22T10:00:00+0000"}))


def test_records_of_two_protocols_are_never_compared(tmp_path):
    """Records without a simulator-noised split are the earlier protocol: a row of only those is marked, a row with
    current records shows only those (its earlier ones listed as not shown), and an ordering whose runs in a seed
    are of two protocols is no evidence in that seed."""
    cpu = tmp_path / "cpu"
    # seed 0: hetero and range current, fixed earlier; seed 1: all current; seed 2: range earlier only
    for name, metrics in {
        "dvss-hetero-l1-s0": _metrics(2.0),
        "dvss-range-l1-s0": _metrics(2.4),
        "dvss-fixed-l1-s0": _metrics(2.9, earlier=True),
        "dvss-hetero-l1-s1": _metrics(2.1),
        "dvss-range-l1-s1": _metrics(2.3),
        "dvss-fixed-l1-s1": _metrics(2.6),
        "dvss-range-l1-s2": _metrics(9.0, earlier=True),
        "unet-hetero-l1-s0": _metrics(3.0, earlier=True),
        "unet-range-l1-s0": _metrics(3.5, earlier=True),
    }.items():
        _write_run(cpu, name, metrics)
    page = results_markdown(tmp_path)
    table3 = page.split("## Table III")[1].split("## Beyond the paper")[0]
    # range: seeds 0 and 1 current; its earlier seed-2 record is not averaged in
    assert "| DVSS, range-aware Gaussian | 39.89 / 40.00 ± 0.00 (n=2) | 3.08 / 2.35 ± 0.07 (n=2) |" in table3
    assert "Not shown: earlier-protocol records of rows that have current ones: dvss-fixed-l1-s0, " in table3
    assert "dvss-range-l1-s2." in table3
    # the U-Net rows have earlier records only: marked, and compared with each other
    assert "| U-Net, range-aware Gaussian † |" in table3 and "| U-Net, hetero (proposed) † |" in table3
    assert "| hetero < range for U-Net (synthetic MAE) | 0: yes | holds in every seed run so far | +0.500 mm" in table3
    # DVSS's chain: seed 0's fixed record is earlier (not shown), so only seed 1 is evidence
    assert "| DVSS: hetero < range < fixed (synthetic MAE) | 1: yes | holds in every seed run so far |" in table3
    runs = page.split("## Runs")[1]
    assert "| dvss-fixed-l1-s0 | earlier |" in runs and "| dvss-fixed-l1-s1 | current |" in runs


def test_a_chain_of_two_protocols_in_a_seed_gives_no_verdict(tmp_path):
    cpu = tmp_path / "cpu"
    _write_run(cpu, "unet-hetero-l1-s0", _metrics(3.0))
    _write_run(cpu, "unet-range-l1-s0", _metrics(3.5, earlier=True))
    table3 = results_markdown(tmp_path).split("## Table III")[1].split("## Beyond the paper")[0]
    line = next(x for x in table3.splitlines() if x.startswith("| hetero < range for U-Net (synthetic MAE)"))
    assert line.startswith(
        "| hetero < range for U-Net (synthetic MAE) | 0: two protocols | not compared (two protocols)"
    )
    assert "| U-Net, range-aware Gaussian † |" in table3 and "| U-Net, hetero (proposed) |" in table3


def test_a_baseline_matched_on_whole_maps_is_of_the_earlier_protocol(tmp_path):
    """A Gaussian baseline whose variance was matched on whole maps (its noise_record without ``weights:
    crop_coverage``) trained on more variance than hetero: the earlier protocol, never compared with a current
    hetero record; matched as the crops cover the maps it is current. Hetero and blind records have no match."""
    from tofdenoise.records import matched_on_whole_maps

    def info(noise: str, weights: str | None) -> dict:
        record = {"noise": noise, "scale": 1.8, "pixels": "after_holes"}
        if weights:
            record["weights"] = weights
        return {"started": "2026-11-22T10:00:00+0000", "prepared_data": {"noise": noise, "noise_record": record}}

    assert matched_on_whole_maps(info("range", None)) and matched_on_whole_maps(info("fixed", None))
    assert not matched_on_whole_maps(info("range", "crop_coverage"))
    assert not matched_on_whole_maps({"prepared_data": {"noise": "hetero", "noise_record": None}})
    assert not matched_on_whole_maps(info("blind", None)) and not matched_on_whole_maps(None)
    cpu = tmp_path / "cpu"
    for seed, weights in ((0, None), (1, "crop_coverage")):
        _write_run(cpu, f"unet-hetero-l1-s{seed}", _metrics(3.0))
        _write_run(cpu, f"unet-range-l1-s{seed}", _metrics(3.5))
        (cpu / f"unet-range-l1-s{seed}" / "run_info.json").write_text(json.dumps(info("range", weights)))
    page = results_markdown(tmp_path)
    table3 = page.split("## Table III")[1].split("## Beyond the paper")[0]
    line = next(x for x in table3.splitlines() if x.startswith("| hetero < range for U-Net (synthetic MAE)"))
    assert line.startswith("| hetero < range for U-Net (synthetic MAE) | 1: yes | holds in every seed run so far |")
    assert "Not shown: earlier-protocol records of rows that have current ones: unet-range-l1-s0." in table3
    runs = page.split("## Runs")[1]
    assert "| unet-range-l1-s0 | earlier |" in runs and "| unet-range-l1-s1 | current |" in runs


def test_committed_results_page_matches_the_records():
    """docs/results.md is exactly what `tofdenoise reproduce --page-only` prints from docs/results/."""
    page = REPO_ROOT / "docs" / "results.md"
    assert page.read_text() == results_markdown(REPO_ROOT / "docs" / "results"), (
        "docs/results.md is stale: run `tofdenoise reproduce --page-only`"
    )


def test_committed_study_figures_are_drawn_from_the_committed_records(tmp_path):
    """Each committed study figure (docs/results/<profile>/dynrange/gains.png) is byte for byte what `tofdenoise
    reproduce --page-only` draws from the committed records (the figure carries no timestamp, and the plotting
    library's version is pinned), and none is missing: a record replaced by hand fails here until the figure is
    redrawn."""
    import shutil

    from tofdenoise.experiments.reproduce import write_study_figures

    committed = REPO_ROOT / "docs" / "results"
    copy = tmp_path / "results"
    shutil.copytree(committed, copy, ignore=shutil.ignore_patterns("*.png"))
    write_study_figures(copy)
    drawn = sorted(p.relative_to(copy).as_posix() for p in copy.rglob("*.png"))
    kept = sorted(
        p.relative_to(committed).as_posix()
        for p in committed.rglob("*.png")
        if p.parent.name in ("dynrange", "schedule")
    )
    assert drawn == kept, "docs/results: study figures missing or left over: run `tofdenoise reproduce --page-only`"
    for name in drawn:
        assert (copy / name).read_bytes() == (committed / name).read_bytes(), (
            f"docs/results/{name} is not drawn from the committed records: run `tofdenoise reproduce --page-only`"
        )


def _write_per_image(run_dir: Path, set_name: str, maes: dict[str, float], raw: float = 7.0) -> None:
    from tofdenoise.records import write_per_image_csv

    rows = [
        {"index": i, "name": n, "valid_px": 100, "psnr_db": 40.0, "mae_mm": m, "mse_mm2": 10 * m, "ssim": 0.99}
        for i, (n, m) in enumerate(maes.items())
    ]
    raws = [{**r, "mae_mm": raw} for r in rows]
    write_per_image_csv(run_dir / "per_image" / f"{set_name}.csv", rows, raws)


def _truth_json(maes: dict[str, float], raw: float = 9.0) -> dict:
    def entry(m):
        return {"psnr_db": 40.0, "mae_mm": m, "mse_mm2": 10 * m, "ssim": 0.99}

    mean = statistics.fmean(maes.values())
    return {
        "truth": {"mean": entry(mean), "images": {n: entry(m) for n, m in maes.items()}},
        "input": {"truth": {"mean": entry(raw), "images": {n: entry(raw) for n in maes}}},
    }


def test_results_page_bootstraps_each_step_over_the_test_images_and_scenes(tmp_path):
    """Hand-computed: hetero -> range is +0.5 mm on both images in both seeds (a zero-width interval, holds on
    every image); range -> fixed is +1.0 mm on one image and -0.2 mm on the other in both seeds: resampling two
    images, the interval runs from -0.2 to +1.0 and the step holds on half of them."""
    cpu = tmp_path / "cpu"
    for seed in (0, 1):
        hetero = {"img_a": 2.0 + seed, "img_b": 3.0}
        rng = {k: v + 0.5 for k, v in hetero.items()}
        fixed = {"img_a": rng["img_a"] + 1.0, "img_b": rng["img_b"] - 0.2}
        for noise, maes in (("hetero", hetero), ("range", rng), ("fixed", fixed)):
            name = f"dvss-{noise}-l1-s{seed}"
            _write_run(cpu, name, _metrics(statistics.fmean(maes.values())))
            _write_per_image(cpu / name, "synthetic", maes)
    page = results_markdown(tmp_path)
    assert "95 % interval of each step over the test images / scenes" in page
    assert (
        "| +0.500 ± 0.000, +0.400 ± 0.000 mm (n=2) | [+0.500, +0.500], [-0.200, +1.000] mm | 100 %, 50 % of 2 images |"
    ) in page
    # a run without its per-image record: no interval (the seed-paired step stays)
    (cpu / "dvss-fixed-l1-s1" / "per_image" / "synthetic.csv").unlink()
    assert "| +0.500 ± 0.000, +0.400 ± 0.000 mm (n=2) | - | - |" in results_markdown(tmp_path)
    # the real set against its truth: per scene, from real_vs_truth.json (U-Net hetero beats range on one of
    # three scenes by 0.9 mm, loses the other two by 0.3 mm: mean +0.1 mm)
    for seed in (0, 1):
        for noise, maes in (
            ("hetero", {"s0": 4.0, "s1": 5.3, "s2": 6.3}),
            ("range", {"s0": 4.9, "s1": 5.0, "s2": 6.0}),
        ):
            name = f"unet-{noise}-l1-s{seed}"
            _write_run(cpu, name, _metrics(3.0))
            (cpu / name / "real_vs_truth.json").write_text(json.dumps(_truth_json(maes)))
    page = results_markdown(tmp_path)
    line = next(x for x in page.splitlines() if x.startswith("| hetero < range for U-Net (real vs truth MAE)"))
    assert line.endswith("| +0.100 ± 0.000 mm (n=2) | [-0.300, +0.900] mm | 33 % of 3 scenes |"), line
    # a per-image record that cannot be read is an error naming it, not a step without interval
    (cpu / "dvss-hetero-l1-s0" / "per_image" / "synthetic.csv").write_text("index,name,mae_mm\n0,img_a,oops\n")
    with pytest.raises(RecordError, match="dvss-hetero-l1-s0/per_image/synthetic.csv"):
        results_markdown(tmp_path)


def test_the_runs_table_names_each_records_machine(tmp_path):
    """Issue 39: the page's Runs table says what each run trained on (minutes and bit-for-bit reruns depend on it);
    a record made before machines were recorded shows -."""
    from tofdenoise.reporting.results_page import machine_label

    cpu = tmp_path / "cpu"
    _write_run(cpu, "dvss-hetero-l1-s0", _metrics(2.0))
    _write_run(cpu, "dvss-range-l1-s0", _metrics(2.4))
    info_path = cpu / "dvss-hetero-l1-s0" / "run_info.json"
    info = json.loads(info_path.read_text())
    info["machine"] = {"cpu": "AMD EPYC", "cpu_id": "AuthenticAMD 25/17", "torch_threads": 2, "gpu": None}
    info_path.write_text(json.dumps(info))
    runs = results_markdown(tmp_path).split("## Runs")[1]
    assert "| AMD EPYC (AuthenticAMD 25/17), 2 thr |" in next(x for x in runs.splitlines() if "dvss-hetero" in x)
    assert next(x for x in runs.splitlines() if "dvss-range" in x).endswith("| - |")
    assert machine_label({"machine": {"cpu": "AMD EPYC", "gpu": "NVIDIA H200", "torch_threads": 16}}) == (
        "NVIDIA H200, 16 thr"
    )
    shared = {"cpu": "AMD EPYC", "gpu": "NVIDIA H200", "torch_threads": 16, "runs_at_once": 3}
    assert machine_label({"machine": shared}) == "NVIDIA H200, 16 thr, up to 3 runs at once"
    assert machine_label({"machine": {**shared, "runs_at_once": 1}}) == "NVIDIA H200, 16 thr"
