"""``tofdenoise reproduce --time-budget`` and the long-schedule study: what a GPU allocation of fixed minutes runs."""

from __future__ import annotations

import json

import pytest

from tofdenoise.cli.reproduce import main
from tofdenoise.experiments.reproduce import ESTIMATE_MARGIN, parse_run_minutes, recorded_seconds, run_estimate
from tofdenoise.experiments.runner import RunSpec
from tofdenoise.experiments.tables import SCHEDULE_EPOCHS, TABLE_PROFILES, table_specs
from tofdenoise.paths import REPO_ROOT
from tofdenoise.reporting.results_page import results_markdown


def _record(dest, name: str, wall_s: float) -> None:
    folder = dest / name
    folder.mkdir(parents=True)
    minutes, seconds = divmod(int(wall_s), 60)
    hours, minutes = divmod(minutes, 60)
    info = {
        "started": "2026-11-26T10:00:00+0000",
        "finished": f"2026-11-26T{10 + hours:02d}:{minutes:02d}:{seconds:02d}+0000",
    }
    (folder / "run_info.json").write_text(json.dumps(info))


def test_a_run_is_estimated_from_the_median_recorded_run_of_its_backbone_loss_and_variant(tmp_path):
    _record(tmp_path, "dvss-fixed-l1-s0", 100)
    _record(tmp_path, "dvss-range-l1-s1", 200)
    _record(tmp_path, "dvss-range-l1-s2", 3000)  # timed on a shared machine: the median ignores it
    _record(tmp_path, "dvss-hetero-full-s0", 900)  # another loss
    _record(tmp_path, "unet-fixed-l1-s0", 10)
    _record(tmp_path, "dvss-fixed-l1-e100-s0", 1000)  # another variant: 10x the epochs
    (tmp_path / "broken-x-l1-s0").mkdir()
    (tmp_path / "broken-x-l1-s0" / "run_info.json").write_text("{")  # unreadable: not an estimate
    assert recorded_seconds(tmp_path, RunSpec("dvss-hetero-l1-s2", ())) == pytest.approx(200 * ESTIMATE_MARGIN)
    assert recorded_seconds(tmp_path, RunSpec("dvss-hetero-l1-e100-s1", ())) == pytest.approx(1000 * ESTIMATE_MARGIN)
    assert recorded_seconds(tmp_path, RunSpec("unet-range-l1-s1", ())) == pytest.approx(10 * ESTIMATE_MARGIN)
    assert recorded_seconds(tmp_path, RunSpec("restormer-range-l1-s0", ())) is None
    assert recorded_seconds(tmp_path, RunSpec("broken-y-l1-s0", ())) is None
    # once the family has a record of the current protocol (a simulator-noised split), only those count
    (tmp_path / "dvss-fixed-l1-s0" / "metrics.json").write_text(json.dumps({"synthetic": {}, "simulated": {}}))
    assert recorded_seconds(tmp_path, RunSpec("dvss-hetero-l1-s2", ())) == pytest.approx(100 * ESTIMATE_MARGIN)


def test_given_run_minutes_replace_the_records_estimate(tmp_path):
    """--run-minutes: a run name first, then its backbone, then the records (whose walls may come from a shared
    machine or code since made faster)."""
    _record(tmp_path, "dvss-fixed-l1-s0", 440)
    given = parse_run_minutes(["dvss=5", "dvss-blind-l1-s0=2.5"])
    assert given == {"dvss": 5.0, "dvss-blind-l1-s0": 2.5}
    assert run_estimate(tmp_path, RunSpec("dvss-range-l1-s1", ()), given) == pytest.approx(300.0)
    assert run_estimate(tmp_path, RunSpec("dvss-blind-l1-s0", ()), given) == pytest.approx(150.0)
    assert run_estimate(tmp_path, RunSpec("dvss-range-l1-s1", ()), {}) == pytest.approx(440 * ESTIMATE_MARGIN)
    assert run_estimate(tmp_path, RunSpec("unet-range-l1-s1", ()), given) is None
    for bad in ("dvss", "dvss=", "=5", "dvss=0", "dvss=-1", "dvss=five", "dvss=inf", "dvss=nan"):
        with pytest.raises(ValueError, match=f"--run-minutes expects NAME=MINUTES .*got {bad!r}"):
            parse_run_minutes([bad])


@pytest.mark.parametrize(
    "argv",
    [
        ["--table", "3", "--run-minutes", "dvss=5"],  # without a time budget
        ["--table", "3", "--time-budget", "5", "--run-minutes", "dvss=x"],
    ],
)
def test_run_minutes_usage_errors(tmp_path, capsys, argv):
    assert main([*argv, "--out", str(tmp_path / "runs"), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--run-minutes" in err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "argv",
    [
        ["--figure", "7", "--time-budget", "5"],  # a figure needs its runs' checkpoints
        ["--table", "3", "--time-budget", "0"],
        ["--table", "3", "--time-budget", "5", "--executor", "slurm", "--slurm-partition", "gpu"],
    ],
)
def test_time_budget_usage_errors(tmp_path, capsys, argv):
    assert main([*argv, "--out", str(tmp_path / "runs"), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--time-budget" in err
    assert not (tmp_path / "runs").exists()


def test_schedule_study_trains_dvss_three_noises_ten_times_longer():
    specs = table_specs("schedule", [0, 1], ("experiment=paper_short",))
    assert [s.name for s in specs] == [
        f"dvss-{noise}-l1-e{SCHEDULE_EPOCHS}-s{seed}" for seed in (0, 1) for noise in ("fixed", "range", "hetero")
    ]
    for spec in specs:  # the study's epochs come after the profile's, so they win
        assert spec.overrides[-1] == f"trainer.max_epochs={SCHEDULE_EPOCHS}"
        assert spec.overrides.index("experiment=paper_short") < len(spec.overrides) - 1
        # 20 validations, compiled steps: after the profile's eager setting and its validation every 2 epochs
        first = spec.overrides.index("experiment=paper_short")
        assert spec.overrides.index("trainer.check_val_every_n_epoch=5") > first
        assert spec.overrides.index("model.compile=true") > first
    assert SCHEDULE_EPOCHS == 10 * 10  # gpu-short trains 10 epochs (configs/experiment/paper_short.yaml)


def test_schedule_study_is_on_the_gpu_short_page_only(tmp_path):
    for profile in ("cpu", "gpu-short"):
        (tmp_path / profile).mkdir()
        folder = tmp_path / profile / "dvss-hetero-l1-s0"
        folder.mkdir()
        for name in ("metrics.json", "run_info.json"):  # a committed record of the CPU profile
            (folder / name).write_bytes((REPO_ROOT / "docs/results/cpu/dvss-hetero-l1-s0" / name).read_bytes())
    page = results_markdown(tmp_path)
    assert TABLE_PROFILES["schedule"] == ("gpu-short",)
    cpu, gpu_short = page.split("# Profile `gpu-short`")
    assert "does the gain last" not in cpu
    assert "does the gain last" in gpu_short and "dvss-hetero-l1-e100-s0" in gpu_short  # listed as missing


def test_the_papers_recipe_is_priced_at_each_gpu_runs_measured_rate(tmp_path):
    from tofdenoise.reporting.results_page import PAPER_RECIPE_STEPS, recipe_hours

    assert PAPER_RECIPE_STEPS == 281_100  # 300 epochs x 937 full batches of 4 of 3,750 training crops (drop_last)
    # 450 steps in 81 s: 0.18 s per step -> 281,100 steps = 14.055 h
    assert recipe_hours(81.0, 450) == pytest.approx(0.18 * 281_100 / 3600)
    assert recipe_hours(None, 450) is None and recipe_hours(81.0, 0) is None and recipe_hours(81.0, None) is None
    results = tmp_path / "results"
    src = REPO_ROOT / "docs/results/gpu-short"
    for run in ("dvss-fixed-l1-s0",):
        (results / "gpu-short" / run).mkdir(parents=True)
        for name in ("metrics.json", "run_info.json"):
            (results / "gpu-short" / run / name).write_bytes((src / run / name).read_bytes())
    info = json.loads((src / "dvss-fixed-l1-s0/run_info.json").read_text())
    steps = json.loads((src / "dvss-fixed-l1-s0/metrics.json").read_text())["trained_steps"]
    page = results_markdown(results)
    row = next(line for line in page.splitlines() if line.startswith("| dvss-fixed-l1-s0 |"))
    assert row.endswith(f" {recipe_hours(info['train_seconds'], steps):.1f} |")
    cpu_runs = page.split("# Profile `gpu-short`")[0].split("## Runs")[1]
    assert "paper's recipe (h)" not in cpu_runs  # a CPU run's rate prices nothing of the paper's recipe
