"""`tofdenoise reproduce`: the plan of a table, figure or study, the records it commits, and the page it rebuilds
(the command: ``tofdenoise.cli.reproduce``; the workflow: ``tofdenoise.experiments.reproduce``)."""

from __future__ import annotations

import csv
import json
import shutil
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest

from tofdenoise.cli.reproduce import main
from tofdenoise.experiments.reproduce import copy_records, profile_overrides
from tofdenoise.experiments.targets import KINDS, Target, target_of_key
from tofdenoise.records import code_commit, host_machine, learned_verdict, write_metrics_json


def _write_metrics(path: Path, results: dict) -> None:
    """A complete metrics.json (with the learned guard's run-level fields, which the page requires since 2623e28) of
    the current protocol: a simulator-noised set beside the synthetic one, as every run at this commit scores."""
    entry = results["synthetic"]
    results = {"simulated": entry, **results}
    write_metrics_json(path, results, run=learned_verdict(1000, entry["mae_mm"], entry["raw"]["mae_mm"]))


def test_dry_run_lists_the_realset_and_every_run(tmp_path, capsys):
    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    assert (
        main(
            [
                "--table",
                "2",
                "--seeds",
                "0",
                "1",
                "--out",
                str(out),
                "--results",
                str(results),
                "--page",
                str(page),
                "--dry-run",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert f"would build the stand-in real set (second camera): {out / 'realset'}, 200 scenes of 128 x 160" in printed
    planned = [line for line in printed.splitlines() if ": would run" in line]
    assert len(planned) == 2 * 6
    first = planned[0]
    for token in (
        "backbone=dvss_no_local",
        "noise=hetero",
        "loss=l1",
        "seed=0",
        "experiment=reproduce_cpu",
        f"++data.sensor={out / 'realset' / 'calibration.yaml'}",
        f"++data.real_dir={out / 'realset' / 'captures'}",
        f"paths.run_dir={out / 'dvss_no_local-hetero-l1-s0'}",
    ):
        assert token in first
    assert not page.exists() and not results.exists()  # a dry run writes nothing


def test_dry_run_of_a_qualitative_figure_lists_its_runs(tmp_path, capsys):
    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    argv = ["--figure", "8", "--seeds", "2", "1", "--out", str(out), "--results", str(results), "--page", str(page)]
    assert main([*argv, "--dry-run"]) == 0
    printed = capsys.readouterr().out
    planned = [line.split(":")[0].split()[-1] for line in printed.splitlines() if ": would run" in line]
    assert planned == ["deeptof-hetero-l1-s2", "tofkpn-hetero-l1-s2", "rcf-hetero-l1-s2", "dvss-hetero-full-s2"]
    assert "would render fig8 from deeptof-hetero-l1-s2, " in printed
    assert not page.exists() and not results.exists()  # a dry run writes nothing


def test_profiles_and_bad_arguments(tmp_path, capsys):
    assert profile_overrides("gpu", Path("/r"), ["data.source_kwargs.root=/d"]) == [
        "experiment=paper",
        "logger=csv",
        "++data.sensor=/r/calibration.yaml",
        "++data.real_dir=/r/captures",
        "data.source_kwargs.root=/d",
    ]
    # a usage error exits 2, as argparse's own do (it was 1)
    assert main(["--results", str(tmp_path), "--page", str(tmp_path / "p.md")]) == 2
    assert "error: give --table 1|2|3, --figure 6|7|8 or --study dynrange|schedule" in capsys.readouterr().err
    # one target at a time, each kind with its own names (a figure is no table)
    for argv in (["--table", "3", "--study", "dynrange"], ["--table", "fig6"], ["--figure", "3"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
    assert main(["--page-only", "--page", str(tmp_path / "p.txt")]) == 2
    assert f"--page {tmp_path / 'p.txt'}: expected a .md file" in capsys.readouterr().err


def test_records_of_finished_runs_only_and_the_page(tmp_path):
    runs, dest = tmp_path / "runs", tmp_path / "results" / "cpu"
    done, unfinished = runs / "dvss-hetero-l1-s0", runs / "dvss-range-l1-s0"
    for d in (done, unfinished):
        (d / "csv").mkdir(parents=True)
        (d / "csv" / "metrics.csv").write_text("step,train/loss\n0,1.0\n")
        (d / "checkpoints").mkdir()
        (d / "checkpoints" / "best.ckpt").write_bytes(b"x" * 100)
    metrics = {
        "synthetic": {
            "psnr_db": 40.0,
            "mae_mm": 2.5,
            "mse_mm2": 9.0,
            "ssim": 0.99,
            "raw": {"psnr_db": 30.0, "mae_mm": 7.0, "mse_mm2": 90.0, "ssim": 0.9},
        },
        **learned_verdict(100, 2.5, 7.0),
    }
    _write_metrics(done / "metrics.json", metrics)
    (done / "run_info.json").write_text(json.dumps({"finished": "2026-11-22T10:00:00+0000"}))
    (unfinished / "run_info.json").write_text(json.dumps({"started": "2026-11-22T10:00:00+0000"}))
    assert copy_records([done, unfinished], dest) == ["dvss-hetero-l1-s0"]
    assert sorted(p.relative_to(dest).as_posix() for p in dest.rglob("*") if p.is_file()) == [
        "dvss-hetero-l1-s0/csv/metrics.csv",
        "dvss-hetero-l1-s0/metrics.json",
        "dvss-hetero-l1-s0/run_info.json",
    ]
    page = tmp_path / "results.md"
    assert main(["--page-only", "--results", str(tmp_path / "results"), "--page", str(page)]) == 0
    assert "| DVSS, hetero (proposed) | 40.37 / 40.00 (n=1) | 2.78 / 2.50 (n=1) |" in page.read_text()


@pytest.mark.parametrize("earlier_start", ["2026-11-25T08:00:00+0000", None])
def test_a_run_copied_over_a_record_leaves_none_of_the_records_files_it_lacks(tmp_path, earlier_start):
    """A run trained again replaces its committed record whole: where the record is of another start (or says none)
    the record files the new run folder lacks (here the earlier run's score against the truth and its
    simulator-noised per-image rows) are removed, the others are the new run's; files that are not record files stay.
    The same run copied again keeps them."""
    run, dest = tmp_path / "runs" / "unet-hetero-l1-s0", tmp_path / "results"
    (run / "csv").mkdir(parents=True)
    info = {"started": "2026-11-28T09:00:00+0000", "finished": "2026-11-28T10:00:00+0000"}
    (run / "run_info.json").write_text(json.dumps(info))
    (run / "metrics.json").write_text('{"new": 1}')
    old = dest / run.name
    (old / "per_image").mkdir(parents=True)
    for name in ("real_vs_truth.json", "per_image/simulated.csv", "metrics.json", "notes.txt"):
        (old / name).write_text("earlier run")
    (old / "run_info.json").write_text(json.dumps({"started": earlier_start} if earlier_start else {}))
    assert copy_records([run], dest) == [run.name]
    assert sorted(p.relative_to(old).as_posix() for p in old.rglob("*") if p.is_file()) == [
        "metrics.json",
        "notes.txt",
        "run_info.json",
    ]
    assert (old / "metrics.json").read_text() == '{"new": 1}'
    (old / "real_vs_truth.json").write_text('{"scored": "later, into the record"}')
    assert copy_records([run], dest) == [run.name]
    assert (old / "real_vs_truth.json").is_file()


def test_per_scene_records_are_committed_compact_with_the_same_numbers(tmp_path):
    """real_vs_truth.json and regions.json (one value per scene and metric) go into the results in
    write_scene_record's compact form, whichever form the run folder holds, with every number as it was; a per-scene
    file that is not strict JSON is copied byte for byte."""
    run, dest = tmp_path / "runs" / "unet-hetero-l1-s0", tmp_path / "results"
    (run / "csv").mkdir(parents=True)
    (run / "run_info.json").write_text(json.dumps({"finished": "2026-11-28T10:00:00+0000"}))
    restored = {"psnr_db": 40.0, "mae_mm": 2.5, "mse_mm2": 9.0, "ssim": 0.99}
    raw = {"psnr_db": 30.0, "mae_mm": 7.0, "mse_mm2": 90.0, "ssim": 0.9}
    _write_metrics(run / "metrics.json", {"synthetic": {**restored, "raw": raw}, **learned_verdict(100, 2.5, 7.0)})
    scenes = {
        f"scene_{i:04d}": {"mae_mm": 1.0 / (i + 3), "psnr_db": 40.0 + i / 7, "valid_px": 300000 + i} for i in range(5)
    }
    truth = {"scenes": 5, "truth": {"mean": {"mae_mm": 0.123456789012345678}, "images": scenes}}
    (run / "real_vs_truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    (run / "regions.json").write_text('{"sets": NaN}')
    assert copy_records([run], dest) == [run.name]
    written = (dest / run.name / "real_vs_truth.json").read_text()
    assert json.loads(written) == truth and written.endswith("}\n")
    assert "  " not in written and ": " not in written  # no indentation, no spaces
    assert len(written) < 0.8 * len(json.dumps(truth, indent=2))
    assert (dest / run.name / "regions.json").read_text() == '{"sets": NaN}'


def test_each_finished_run_is_recorded_at_once(tmp_path, monkeypatch):
    """A table interrupted after its first run keeps that run's records and an updated page."""
    import tofdenoise.cli.reproduce as reproduce
    import tofdenoise.experiments.reproduce as workflow
    from tofdenoise.experiments.runner import RunOutcome

    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    metrics = {
        "synthetic": {
            "psnr_db": 41.0,
            "mae_mm": 2.0,
            "mse_mm2": 8.0,
            "ssim": 0.99,
            "raw": {"psnr_db": 30.0, "mae_mm": 7.0, "mse_mm2": 90.0, "ssim": 0.9},
        },
        **learned_verdict(100, 2.5, 7.0),
    }

    def fake_run_all(specs, out_dir, dry_run=False, after_each=None, executor=None, budget=None):
        first = out_dir / specs[0].name
        first.mkdir(parents=True)
        _write_metrics(first / "metrics.json", metrics)
        (first / "run_info.json").write_text(json.dumps({"finished": "2026-11-22T10:00:00+0000"}))
        after_each(RunOutcome(specs[0], first, "done"))
        assert (results / "cpu" / specs[0].name / "metrics.json").is_file()  # recorded before the next run
        assert "| DVSS, fixed Gaussian | 39.40 / 41.00 (n=1) | 3.42 / 2.00 (n=1) |" in page.read_text()
        raise KeyboardInterrupt  # the run of the command ends here

    monkeypatch.setattr(workflow, "ensure_realset", lambda *a, **k: None)
    monkeypatch.setattr(workflow, "run_all", fake_run_all)
    with pytest.raises(KeyboardInterrupt):
        reproduce.main(
            ["--table", "3", "--seeds", "0", "--out", str(out), "--results", str(results), "--page", str(page)]
        )
    assert sorted(p.name for p in (results / "cpu").iterdir()) == ["dvss-fixed-l1-s0"]


def test_a_figure_that_fails_its_check_is_not_written_and_fails_the_command(tmp_path, monkeypatch, capsys):
    import tofdenoise.cli.reproduce as reproduce
    import tofdenoise.experiments.reproduce as workflow
    from tofdenoise.experiments.figures import FigureMismatch
    from tofdenoise.experiments.runner import RunOutcome

    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"

    def refuse(*args, **kwargs):
        raise FigureMismatch("runs/x/per_image/real.csv: scene 'scene_0000': the figure's input has MAE 1.0 mm")

    monkeypatch.setattr(workflow, "ensure_realset", lambda *a, **k: None)
    monkeypatch.setattr(
        workflow,
        "run_all",
        lambda specs, out_dir, dry_run=False, after_each=None, executor=None: [
            RunOutcome(s, out_dir / s.name, "skipped") for s in specs
        ],
    )
    monkeypatch.setattr(workflow, "build_figure", refuse)
    argv = ["--figure", "8", "--seeds", "0", "--out", str(out), "--results", str(results), "--page", str(page)]
    assert reproduce.main(argv) == 1
    assert "fig8 not rendered: runs/x/per_image/real.csv: scene 'scene_0000'" in capsys.readouterr().out
    assert not (results / "cpu" / "fig8").exists() and not (out / "fig8").exists()
    assert "Not run yet (`make reproduce FIGURE=8`)" in page.read_text()


def test_figure_of_a_trained_run_matches_its_test_and_a_changed_checkpoint_is_refused(tmp_path, data_cache, tiny):
    """End to end on a tiny run (about 15 s): the figure's per-scene MAE is the run's recorded per-image MAE;
    a checkpoint that is not the one the test scored is an error naming the record."""
    from tofdenoise.cli.train import run
    from tofdenoise.config import compose_config
    from tofdenoise.experiments.figures import FigureMismatch, FigureSpec, build_figure, figure_specs

    out = tmp_path / "runs"
    common = [o for o in tiny(out, data_cache) if not o.startswith(("paths.run_dir", "backbone="))]
    spec = FigureSpec("figt", "Fig. T", "synthetic", (("U-Net", "3", "unet_hetero"),), 2, "Input", "GT")
    specs = figure_specs(spec, 0, [*common, "trainer.max_epochs=1", "logger=csv"])
    run(compose_config([*specs[0].overrides, f"paths.run_dir={out / specs[0].name}"]))
    image, record = build_figure(spec, 0, specs, out)
    assert record["runs"] == {"U-Net": "unet-hetero-l1-s0"} and len(record["scenes"]) == 2
    assert image.dtype == np.uint8
    assert record["provenance"]["commit"] == code_commit()["commit"]
    assert record["provenance"]["machine"] == host_machine()
    recorded = {}
    with (out / "unet-hetero-l1-s0" / "per_image" / "synthetic.csv").open() as f:
        for row in csv.DictReader(f):
            recorded[row["name"]] = float(row["mae_mm"])
    for scene in record["scenes"]:
        assert scene["mae_mm"]["U-Net"] == pytest.approx(recorded[scene["name"]], abs=1e-3)

    ckpt = out / "unet-hetero-l1-s0" / "checkpoints" / "best.ckpt"
    import torch

    content = torch.load(ckpt, map_location="cpu", weights_only=False)
    for key, value in content["state_dict"].items():  # every bias, whichever copy (EMA or not) restores
        if key.endswith("bias"):
            value += 0.5
    torch.save(content, ckpt)
    with pytest.raises(FigureMismatch, match="U-Net's prediction has MAE"):
        build_figure(spec, 0, specs, out)


#: a GPU profile's run scaled down to the CPU: fp32, one epoch validated, tiny crops and batches
CPU_SCALE_DOWN = [
    "trainer.accelerator=cpu",
    "trainer.precision=32-true",
    "trainer.max_epochs=1",
    "trainer.check_val_every_n_epoch=1",
    "trainer.enable_progress_bar=false",
    "data.crop_size=16",
    "data.batch_size=2",
    "data.num_workers=0",
]


def test_skip_recorded_runs_only_what_has_no_committed_record(tmp_path, monkeypatch, capsys):
    """``--skip-recorded`` (going on from committed records on a fresh machine) leaves out the runs whose
    metrics.json and run_info.json are committed; a run with metrics.json only is run again; without the option
    every run of the target runs. A figure needs its runs' checkpoints: the option is refused there (exit 2)."""
    import tofdenoise.experiments.reproduce as workflow

    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    committed = {"dvss-fixed-l1-s0": ("metrics.json", "run_info.json"), "dvss-range-l1-s0": ("metrics.json",)}
    for name, files in committed.items():
        for file in files:
            (results / "cpu" / name).mkdir(parents=True, exist_ok=True)
            (results / "cpu" / name / file).write_text("{}")
    asked = []

    def fake_run_all(specs, out_dir, dry_run=False, after_each=None, executor=None, budget=None):
        asked.append([s.name for s in specs])
        return []

    monkeypatch.setattr(workflow, "ensure_realset", lambda *a, **k: None)
    monkeypatch.setattr(workflow, "run_all", fake_run_all)
    monkeypatch.setattr(workflow, "write_page", lambda *a, **k: "")
    argv = ["--table", "3", "--seeds", "0", "--out", str(out), "--results", str(results), "--page", str(page)]
    assert main([*argv, "--skip-recorded"]) == 0
    assert main(argv) == 0
    assert "dvss-fixed-l1-s0" not in asked[0] and "dvss-range-l1-s0" in asked[0] and len(asked[0]) == 9
    assert len(asked[1]) == 10 and "dvss-fixed-l1-s0" in asked[1]
    assert "--skip-recorded: 1 run(s) committed" in capsys.readouterr().out
    # a mistyped --results commits nothing: every run trains, and the log says why
    typo = ["--results", str(tmp_path / "resluts"), "--page", str(page)]
    assert main([*argv[:4], "--out", str(out), *typo, "--skip-recorded"]) == 0
    assert len(asked[2]) == 10
    assert f"{tmp_path / 'resluts' / 'cpu'}: no such folder, so no run is committed there" in capsys.readouterr().out
    assert main(["--figure", "7", "--skip-recorded", "--out", str(out), "--results", str(results)]) == 2
    assert "--skip-recorded applies to --table and --study" in capsys.readouterr().err


def test_a_figure_says_which_committed_records_its_training_replaces(tmp_path, capsys):
    """A figure needs its runs' checkpoints, which records do not keep: a run with a committed record but no finished
    run folder is trained again, and that replaces its record (and moves the tables that show it). The dry run and
    the real one say so, naming where the record came from; a run whose folder is finished, or with no record, is
    not named."""
    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    records = {
        "dvss-range-l1-s0": {"commit": "84d82cdc29d5054bbd4593bfb650f4552b844b93"},
        "rcf-hetero-l1-s0": {
            "commit": "85660e173b9216db",
            "machine": {"cpu": "AMD EPYC", "cpu_id": "AuthenticAMD 25/17"},
        },
        "deeptof-hetero-l1-s0": {"commit": "85660e173b9216db"},
    }
    for name, info in records.items():
        (results / "cpu" / name).mkdir(parents=True)
        (results / "cpu" / name / "run_info.json").write_text(json.dumps(info))
    finished = out / "deeptof-hetero-l1-s0"  # its checkpoint is here: nothing is retrained, nothing replaced
    finished.mkdir(parents=True)
    (finished / "run_info.json").write_text(json.dumps({"finished": "2026-11-28T14:00:00+0000"}))
    (finished / "metrics.json").write_text("{}")
    argv = ["--figure", "7", "--out", str(out), "--results", str(results), "--page", str(page), "--dry-run"]
    assert main(argv) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "replaces its committed record" in line]
    assert len(lines) == 2
    assert lines[0].startswith("[reproduce] dvss-range-l1-s0: no finished run folder")
    assert "(made at 84d82cdc29d5 on an unrecorded machine)" in lines[0]
    assert lines[1].startswith("[reproduce] rcf-hetero-l1-s0:")
    assert "(made at 85660e173b92 on AMD EPYC (AuthenticAMD 25/17))" in lines[1]
    assert not (results / "cpu" / "fig7").exists()  # a dry run writes nothing


def test_record_provenance_reads_what_a_record_says(tmp_path):
    """``record_provenance``: commit and CPU from run_info.json, "unrecorded" for a missing part, None without a
    readable run_info.json (no record, a broken one, a JSON list)."""
    from tofdenoise.experiments.reproduce import record_provenance

    assert record_provenance(tmp_path / "none") is None
    (tmp_path / "run_info.json").write_text("{")
    assert record_provenance(tmp_path) is None
    (tmp_path / "run_info.json").write_text("[]")
    assert record_provenance(tmp_path) is None
    (tmp_path / "run_info.json").write_text("{}")
    assert record_provenance(tmp_path) == "made at an unrecorded commit on an unrecorded machine"
    (tmp_path / "run_info.json").write_text(json.dumps({"commit": "abc", "machine": {"cpu": "AMD EPYC"}}))
    assert record_provenance(tmp_path) == "made at abc on AMD EPYC"


def _table3_seed0_training_nothing(monkeypatch, tmp_path) -> tuple[list[list[str]], list[str]]:
    """Table 3 seed 0's command line on ``tmp_path``'s runs / results / page, with no stand-in set, no training (the
    names of the runs each call would train are appended to the list returned) and no page."""
    import tofdenoise.experiments.reproduce as workflow

    asked: list[list[str]] = []
    monkeypatch.setattr(workflow, "ensure_realset", lambda *a, **k: None)
    monkeypatch.setattr(workflow, "run_all", lambda specs, *a, **k: asked.append([s.name for s in specs]) or [])
    monkeypatch.setattr(workflow, "write_page", lambda *a, **k: "")
    paths = {"--out": "runs", "--results": "results", "--page": "results.md"}
    return asked, ["--table", "3", "--seeds", "0", *[a for k, v in paths.items() for a in (k, str(tmp_path / v))]]


def test_rerun_earlier_trains_again_the_runs_recorded_under_the_earlier_protocol(tmp_path, monkeypatch, capsys):
    """``--skip-recorded --rerun-earlier``: a committed record without the simulator-noised split (the earlier test
    protocol) or with an unreadable metrics.json runs again; a current-protocol record is still skipped; the option
    alone is refused."""
    results = tmp_path / "results"
    committed = {
        "dvss-fixed-l1-s0": {"synthetic": {}, "simulated": {}},  # current
        "dvss-range-l1-s0": {"synthetic": {}},  # earlier
        "dvss-hetero-l1-s0": None,  # unreadable
    }
    for name, metrics in committed.items():
        (results / "cpu" / name).mkdir(parents=True)
        (results / "cpu" / name / "metrics.json").write_text("{" if metrics is None else json.dumps(metrics))
        (results / "cpu" / name / "run_info.json").write_text("{}")
    asked, argv = _table3_seed0_training_nothing(monkeypatch, tmp_path)
    assert main([*argv, "--skip-recorded", "--rerun-earlier"]) == 0
    (names,) = asked
    assert len(names) == 9 and "dvss-fixed-l1-s0" not in names
    assert "dvss-range-l1-s0" in names and "dvss-hetero-l1-s0" in names
    out_text = capsys.readouterr().out
    assert "--rerun-earlier: 2 record(s) of the earlier protocol run again: dvss-range-l1-s0, dvss-hetero-l1-s0" in (
        out_text
    )
    assert main([*argv, "--rerun-earlier"]) == 2
    assert "--rerun-earlier applies with --skip-recorded" in capsys.readouterr().err


def test_rerun_without_truth_trains_again_the_runs_whose_record_lacks_its_truth_score(tmp_path, monkeypatch, capsys):
    """``--skip-recorded --rerun-without-truth``: a committed record without real_vs_truth.json (its checkpoint stayed
    on another machine) runs again, one with it is still skipped, and the option alone is refused; without the
    option both are skipped."""
    results = tmp_path / "results"
    for name, truth in (("dvss-fixed-l1-s0", True), ("dvss-range-l1-s0", False)):
        (results / "cpu" / name).mkdir(parents=True)
        (results / "cpu" / name / "metrics.json").write_text(json.dumps({"synthetic": {}, "simulated": {}}))
        (results / "cpu" / name / "run_info.json").write_text("{}")
        if truth:
            (results / "cpu" / name / "real_vs_truth.json").write_text("{}")
    asked, argv = _table3_seed0_training_nothing(monkeypatch, tmp_path)
    assert main([*argv, "--skip-recorded", "--rerun-without-truth"]) == 0
    assert main([*argv, "--skip-recorded"]) == 0
    with_option, without = asked
    assert len(with_option) == 9 and "dvss-range-l1-s0" in with_option and "dvss-fixed-l1-s0" not in with_option
    assert len(without) == 8 and "dvss-range-l1-s0" not in without
    out_text = capsys.readouterr().out
    assert "--rerun-without-truth: 1 record(s) without real_vs_truth.json run again: dvss-range-l1-s0" in out_text
    assert main([*argv, "--rerun-without-truth"]) == 2
    assert "--rerun-without-truth applies with --skip-recorded" in capsys.readouterr().err


def test_prepare_only_prepares_the_runs_still_to_train_and_trains_nothing(tmp_path, monkeypatch, capsys):
    """``--prepare-only`` (a GPU machine's CPUs, beside other work): the stand-in set is built, the data of every run
    of the target that is neither committed nor finished in its folder is prepared, nothing trains and no page is
    written; it applies to tables and studies only."""
    import tofdenoise.experiments.reproduce as workflow

    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    for file in ("metrics.json", "run_info.json"):
        (results / "cpu" / "dvss-fixed-l1-s0").mkdir(parents=True, exist_ok=True)
        (results / "cpu" / "dvss-fixed-l1-s0" / file).write_text("{}")
    calls = {"realset": 0, "prepared": [], "trained": 0, "page": 0}

    def fake_prepare(specs, workers=None, log=print):
        calls["prepared"].append([s.name for s in specs])
        return [s.name for s in specs[:2]]

    monkeypatch.setattr(workflow, "ensure_realset", lambda *a, **k: calls.__setitem__("realset", 1))
    monkeypatch.setattr(workflow, "prepare_grid_data", fake_prepare)
    monkeypatch.setattr(workflow, "run_all", lambda *a, **k: calls.__setitem__("trained", 1) or [])
    monkeypatch.setattr(workflow, "write_page", lambda *a, **k: calls.__setitem__("page", 1) or "")
    monkeypatch.setattr(workflow, "run_finished", lambda folder: folder.name == "unet-range-l1-s0")
    argv = ["--table", "3", "--seeds", "0", "--out", str(out), "--results", str(results), "--page", str(page)]
    assert main([*argv, "--skip-recorded", "--prepare-only"]) == 0
    assert calls["realset"] == 1 and calls["trained"] == 0 and calls["page"] == 0
    (prepared,) = calls["prepared"]
    assert len(prepared) == 8 and "dvss-fixed-l1-s0" not in prepared and "unet-range-l1-s0" not in prepared
    assert "--prepare-only: data of 2 distinct config(s) prepared; nothing trained" in capsys.readouterr().out
    assert main(["--figure", "7", "--prepare-only", "--out", str(out), "--results", str(results)]) == 2
    assert "--prepare-only applies to --table and --study" in capsys.readouterr().err
    assert main(["--page-only", "--prepare-only", "--results", str(results), "--page", str(page)]) == 2


def test_a_finished_runs_record_gains_its_score_against_the_stand_ins_truth(tmp_path, monkeypatch, data_cache, tiny):
    """``reproduce`` scores each finished learned run against the simulated capture set's truth as it commits it:
    the committed ``real_vs_truth.json`` gives the run's own real-set numbers against the references (to 1e-9) and
    fills the page's "real vs truth" column; a repeated run does not score it again, and a capture set without
    truth (a real camera's) or a run without a checkpoint (the classical filter) gets no such file."""
    import tofdenoise.experiments.reproduce as workflow
    from tofdenoise.cli.sensor import main as sensor_main
    from tofdenoise.cli.train import run
    from tofdenoise.config import compose_config
    from tofdenoise.experiments.runner import RunOutcome

    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    realset = out / "realset"
    args = ["realset", "--out", str(realset), "--scenes", "2", "--frames", "4", "--height", "32", "--width", "48"]
    assert sensor_main(args) == 0
    run_dir = out / "dvss-fixed-l1-s0"
    overrides = [f"++data.sensor={realset / 'calibration.yaml'}", f"++data.real_dir={realset / 'captures'}"]
    run(compose_config([*tiny(run_dir, data_cache), *overrides, "trainer.max_epochs=1", "logger=csv"]))
    bilateral = out / "bilateral-s0"  # a finished run without a checkpoint
    bilateral.mkdir()
    for name in ("metrics.json", "run_info.json"):
        shutil.copy(run_dir / name, bilateral / name)

    def fake_run_all(specs, out_dir, dry_run=False, after_each=None, executor=None, budget=None):
        for folder in (run_dir, bilateral):
            after_each(RunOutcome(specs[0], folder, "skipped"))
        return []

    monkeypatch.setattr(workflow, "ensure_realset", lambda *a, **k: None)
    monkeypatch.setattr(workflow, "run_all", fake_run_all)
    argv = ["--table", "3", "--seeds", "0", "--out", str(out), "--results", str(results), "--page", str(page)]
    assert main(argv) == 0
    record = results / "cpu" / run_dir.name / "real_vs_truth.json"
    truth = json.loads(record.read_text())
    recorded = json.loads((run_dir / "metrics.json").read_text())["real"]
    for key in ("psnr_db", "mae_mm", "mse_mm2", "ssim"):
        assert truth["reference"]["mean"][key] == pytest.approx(recorded[key], rel=1e-9, abs=1e-9)
    assert truth["scenes"] == 2 and truth["truth"]["num_images"] == 2 and truth["truth"]["mean"]["mae_mm"] > 0
    assert truth["checkpoint"] == str(run_dir / "checkpoints" / "best.ckpt")
    assert not (results / "cpu" / bilateral.name / "real_vs_truth.json").exists()
    row = next(line for line in page.read_text().splitlines() if line.startswith("| DVSS, fixed Gaussian |"))
    assert f"{truth['truth']['mean']['mae_mm']:.2f} (n=1)" in row
    # and its own test sets scored again by region (regions.json), whole images as its record
    regions = json.loads((results / "cpu" / run_dir.name / "regions.json").read_text())
    all_sets = json.loads((run_dir / "metrics.json").read_text())
    assert sorted(regions["sets"]) == ["simulated", "synthetic"]
    for name, scored in regions["sets"].items():
        assert scored["inputs_as_recorded"] is True
        assert scored["restored"]["mean"]["mae_mm"] == pytest.approx(all_sets[name]["mae_mm"], rel=1e-9)
        assert scored["restored"]["regions"]["edge_jump_mm"] == 50.0
    assert not (results / "cpu" / bilateral.name / "regions.json").exists()

    # a second run: the records are newer than the checkpoint, so they are kept as they are
    stamp = (run_dir / "real_vs_truth.json").stat().st_mtime_ns
    regions_stamp = (run_dir / "regions.json").stat().st_mtime_ns
    assert main(argv) == 0
    assert (run_dir / "real_vs_truth.json").stat().st_mtime_ns == stamp
    assert (run_dir / "regions.json").stat().st_mtime_ns == regions_stamp
    # the set grew (24 -> 200 scenes in the CPU profile): the kept record scored fewer scenes, so it is scored again
    assert sensor_main([*args[:4], "3", *args[5:]]) == 0
    assert main(argv) == 0
    assert json.loads(record.read_text())["scenes"] == 3 and json.loads(record.read_text())["truth"]["num_images"] == 3
    # a capture set without truth: no record for a run that has none yet
    (run_dir / "real_vs_truth.json").unlink()
    record.unlink()
    for truth_map in (realset / "captures").glob("*/ground_truth_depth_mm.npy"):
        truth_map.unlink()
    assert main(argv) == 0
    assert not (run_dir / "real_vs_truth.json").exists() and not record.exists()


def _train_table3_row(tmp_path: Path, profile: str, realset: Path, scaled_down: list[str], name: str):
    """Train and test Table III's run ``name`` with ``profile``'s overrides and ``scaled_down`` ones; both test sets
    must be scored (two images each, finite). Returns the run folder and its run_info.json."""
    from tofdenoise.cli.train import run
    from tofdenoise.config import compose_config
    from tofdenoise.experiments.tables import table_specs

    spec = {s.name: s for s in table_specs("3", [0], profile_overrides(profile, realset, scaled_down))}[name]
    run_dir = tmp_path / spec.name
    run(compose_config([*spec.overrides, f"paths.run_dir={run_dir}"]))
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["synthetic"]["images"] == 2 and metrics["real"]["images"] == 2
    for test_set in ("synthetic", "real"):
        assert np.isfinite(metrics[test_set]["mae_mm"]) and metrics[test_set]["raw"]["mae_mm"] > 0
    return run_dir, json.loads((run_dir / "run_info.json").read_text())


def test_gpu_profile_run_scaled_down_trains_and_tests_on_cpu(tmp_path, data_cache, tiny, write_ft3d):
    """The GPU profile's first execution must not be on the GPU machine: a Table III run with the profile's
    overrides (``experiment=paper``: ToF-FlyingThings3D, the row's backbone, noise and loss, the second camera's
    calibration and capture set) trains and tests end to end, scaled down (fixture dataset, CPU, one epoch, tiny
    DVSS). About 15 s."""
    from tofdenoise.cli.sensor import main as sensor_main

    ft3d, realset = tmp_path / "ft3d", tmp_path / "realset"
    write_ft3d(ft3d, [f"t{i:03d}" for i in range(8)], [f"v{i:03d}" for i in range(2)])
    assert (
        sensor_main(
            ["realset", "--out", str(realset), "--scenes", "2", "--frames", "4", "--height", "24", "--width", "32"]
        )
        == 0
    )
    tiny_dvss = [o for o in tiny(tmp_path, data_cache, backbone="dvss") if o.startswith("backbone.kwargs")]
    scaled_down = [
        f"data.source_kwargs.root={ft3d}",
        f"++data.cache_dir={data_cache}",
        *CPU_SCALE_DOWN,
        *tiny_dvss,
    ]
    run_dir, info = _train_table3_row(tmp_path, "gpu", realset, scaled_down, "dvss-range-l1-s0")
    assert info["data"] == "flyingthings3d" and info["noise"] == "range" and info["loss"] == "l1"
    config = (run_dir / "config.yaml").read_text()
    assert "lr: 0.0002" in config and "max_epochs: 1" in config and str(realset / "calibration.yaml") in config


def test_gpu_short_profile_run_scaled_down_trains_and_tests_on_cpu(tmp_path, data_cache, tiny):
    """The ``gpu-short`` profile (the paper's recipe per step on the procedural world, for a few GPU minutes)
    first runs here, not on the GPU machine: its overrides compose (experiment=paper's optimiser, crops and bf16
    trainer, the procedural source at 480 x 640, 10 epochs), and a Table III run with them, scaled down (CPU, one
    epoch, tiny scenes and DVSS), trains and tests end to end on both test sets."""
    from tofdenoise.cli.sensor import main as sensor_main
    from tofdenoise.config import compose_config
    from tofdenoise.experiments.tables import table_specs

    realset = tmp_path / "realset"
    specs = {s.name: s for s in table_specs("3", [0], profile_overrides("gpu-short", realset, []))}
    cfg = compose_config(specs["dvss-fixed-l1-s0"].overrides)
    assert cfg.data.source == "procedural" and cfg.data.crop_size == 320 and cfg.data.batch_size == 4
    assert dict(cfg.data.source_kwargs) == {"num_samples": 300, "height": 480, "width": 640}
    assert cfg.trainer.precision == "bf16-mixed" and cfg.trainer.max_epochs == 10
    assert cfg.model.optim.lr == 2e-4 and cfg.model.optim.lr_min == 1e-6 and cfg.model.optim.warmup_steps == 0
    assert (cfg.backbone.name, cfg.noise.name, cfg.loss.name) == ("dvss", "fixed", "l1")

    args = ["realset", "--out", str(realset), "--scenes", "2", "--frames", "4", "--height", "24", "--width", "32"]
    assert sensor_main(args) == 0
    tiny_dvss = [o for o in tiny(tmp_path, data_cache, backbone="dvss") if o.startswith("backbone.kwargs")]
    scaled_down = [
        "data.source_kwargs.num_samples=10",
        "data.source_kwargs.height=24",
        "data.source_kwargs.width=32",
        f"++data.cache_dir={data_cache}",
        *CPU_SCALE_DOWN,
        *tiny_dvss,
    ]
    _, info = _train_table3_row(tmp_path, "gpu-short", realset, scaled_down, "dvss-hetero-l1-s0")
    assert info["data"] == "procedural" and info["noise"] == "hetero" and info["loss"] == "l1"
    assert info["train_images_per_second"] > 0 and info["peak_rss_gib"] > 0  # what a GPU run records


def _results_with_three_seeds(root: Path) -> Path:
    """results/cpu with DVSS hetero and range, L1, seeds 0-2, and a hand-written discussion."""
    results = root / "results"
    for seed in range(3):
        for noise, mae in (("hetero", 2.0), ("range", 2.5)):
            d = results / "cpu" / f"dvss-{noise}-l1-s{seed}"
            d.mkdir(parents=True)
            entry = {"psnr_db": 40.0, "mae_mm": mae + 0.1 * seed, "mse_mm2": 9.0, "ssim": 0.99}
            entry["raw"] = {"psnr_db": 30.0, "mae_mm": 7.0, "mse_mm2": 90.0, "ssim": 0.9}
            _write_metrics(d / "metrics.json", {"synthetic": entry})
            (d / "run_info.json").write_text(json.dumps({"started": "2026-11-22T10:00:00+0000"}))
    (results / "discussion.md").write_text("## Discussion\n\nWritten by hand.\n")
    return results


def _truncate(path: Path) -> None:
    path.write_text(path.read_text()[:40])


def _null_mae(path: Path) -> None:
    data = json.loads(path.read_text())
    data["synthetic"]["mae_mm"] = None
    path.write_text(json.dumps(data))


@pytest.mark.parametrize(
    "file, damage, why",
    [
        ("metrics.json", _truncate, "cannot be read"),
        ("run_info.json", lambda p: p.write_text("{broken"), "cannot be read"),
        ("run_info.json", lambda p: p.write_text("[1, 2]"), "not a JSON object"),
        ("metrics.json", _null_mae, "'synthetic.mae_mm' is null"),
    ],
)
def test_a_record_that_cannot_be_read_is_an_error_naming_the_file(tmp_path, capsys, file, damage, why):
    """issue 23 case 5: a truncated metrics.json, a broken run_info.json or a null metric made the run leave the
    page silently (n=3 -> 2, orderings changed), exit 0."""
    results = _results_with_three_seeds(tmp_path)
    page = tmp_path / "results.md"
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 0
    assert "| DVSS, hetero (proposed) | 40.37 / 40.00 ± 0.00 (n=3) |" in page.read_text()
    before = page.read_bytes()
    broken = results / "cpu" / "dvss-range-l1-s1" / file
    damage(broken)
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) != 0
    err = capsys.readouterr().err
    assert f"tofdenoise reproduce: error: {broken}" in err and why in err
    assert page.read_bytes() == before  # the page is not rewritten without the run


def _truth_record(path: Path, mae_mm: float, raw_mae_mm: float) -> None:
    """A run's real_vs_truth.json as tofdenoise evaluate --ckpt writes it (only what the page reads)."""
    mean = {"psnr_db": 30.0, "mae_mm": mae_mm, "mse_mm2": 50.0, "ssim": 0.9}
    raw = {**mean, "mae_mm": raw_mae_mm}
    path.write_text(json.dumps({"truth": {"mean": mean}, "input": {"truth": {"mean": raw}}}))


def test_truth_columns_read_each_runs_real_vs_truth_record(tmp_path, capsys):
    """Table III's "real vs truth MAE" column and its ordering come from each run's real_vs_truth.json (the real-set
    predictions against the stand-in's rendered truth): mean over the seeds that have one; a run without it is '-',
    and a record without the truth scores is an error naming it."""
    results = _results_with_three_seeds(tmp_path)
    for seed in range(3):
        _truth_record(results / "cpu" / f"dvss-hetero-l1-s{seed}" / "real_vs_truth.json", 5.0 + 0.1 * seed, 12.0)
        if seed < 2:
            _truth_record(results / "cpu" / f"dvss-range-l1-s{seed}" / "real_vs_truth.json", 5.3, 12.0)
    page = tmp_path / "results.md"
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 0
    text = page.read_text()
    header = next(line for line in text.splitlines() if line.startswith("| method | PSNR (dB)↑ paper / ours | MAE"))
    assert header.endswith("| real vs truth MAE (mm)↓ paper / ours |")
    hetero = next(line for line in text.splitlines() if line.startswith("| DVSS, hetero (proposed) |"))
    assert hetero.endswith("| - / 5.10 ± 0.10 (n=3) |")
    fixed = next(line for line in text.splitlines() if line.startswith("| DVSS, fixed Gaussian |"))
    assert fixed.endswith("| - / - |")
    claim = next(line for line in text.splitlines() if "hetero < range < fixed (real vs truth MAE)" in line)
    assert "0: yes" not in claim  # no fixed-noise run: the ordering cannot be checked
    broken = results / "cpu" / "dvss-range-l1-s0" / "real_vs_truth.json"
    broken.write_text(json.dumps({"reference": {}}))
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 2
    err = capsys.readouterr().err
    assert f"tofdenoise reproduce: error: {broken}: expected the truth scores" in err


def test_a_run_without_a_record_is_listed_as_missing(tmp_path):
    results = _results_with_three_seeds(tmp_path)
    shutil.rmtree(results / "cpu" / "dvss-range-l1-s2")
    (results / "cpu" / "dvss-range-l1-s1" / "run_info.json").unlink()  # an interrupted copy: no record yet
    page = tmp_path / "results.md"
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 0
    text = page.read_text()
    assert "| DVSS, range-aware Gaussian | 39.89 / 40.00 (n=1) |" in text
    assert "Missing runs (no record in `results/cpu/`): " in text
    listed = next(line for line in text.splitlines() if line.startswith("Missing runs") and "range-l1" in line)
    assert "dvss-range-l1-s1" in listed and "dvss-range-l1-s2" in listed


@pytest.mark.parametrize("rel", ["discussion.md", "cpu/dvss-hetero-l1-s0/notes.md", "cpu"])
def test_the_page_never_replaces_its_own_inputs(tmp_path, capsys, rel):
    """issue 23 case 6: --page <results>/discussion.md overwrote the discussion, which grew on every re-run."""
    results = _results_with_three_seeds(tmp_path)
    (results / "cpu" / "dvss-hetero-l1-s0" / "notes.md").write_text("notes\n")
    before = {p: p.read_bytes() for p in results.rglob("*") if p.is_file()}
    target = results / rel
    for _ in range(2):
        assert main(["--page-only", "--results", str(results), "--page", str(target)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"tofdenoise reproduce: error: --page {target}" in err
    assert {p: p.read_bytes() for p in results.rglob("*") if p.is_file()} == before


def test_the_gpu_profile_says_what_it_needs_before_any_work(tmp_path, capsys):
    """Without data.source_kwargs.root (or without a GPU) --profile gpu stops at once with exit 2, in a dry run too,
    before the stand-in real set (a 50-minute build at that profile) is started."""
    from tofdenoise.experiments.reproduce import profile_needs

    out = tmp_path / "runs"
    args = ["--table", "3", "--profile", "gpu", "--out", str(out), "--results", str(tmp_path / "r")]
    args += ["--page", str(tmp_path / "p.md")]
    for extra in ([], ["--dry-run"]):
        assert main(args + extra) == 2
        err = capsys.readouterr().err
        assert "--profile gpu needs the ToF-FlyingThings3D folder: --extra data.source_kwargs.root=" in err
    assert not out.exists() and not (tmp_path / "p.md").exists()
    nowhere = [f"data.source_kwargs.root={tmp_path / 'nope'}"]
    assert "existing data.source_kwargs.root" in profile_needs("gpu", nowhere, cuda_available=True)
    assert "a CUDA GPU" in profile_needs("gpu", [f"++data.source_kwargs.root={tmp_path}"], cuda_available=False)
    assert profile_needs("gpu", [f"data.source_kwargs.root={tmp_path}"], cuda_available=True) == ""
    assert profile_needs("cpu", []) == ""
    # gpu-short trains on the built-in scenes: it needs a GPU, no data folder
    assert "a CUDA GPU" in profile_needs("gpu-short", [], cuda_available=False)
    assert profile_needs("gpu-short", [], cuda_available=True) == ""


def test_the_gpu_profiles_are_those_whose_runs_train_on_a_gpu(tmp_path):
    """``GPU_PROFILES`` (what ``profile_needs`` asks a CUDA GPU for) is exactly the set of profiles whose composed
    Table III run trains with ``trainer.accelerator=gpu``."""
    from tofdenoise.config import compose_config
    from tofdenoise.experiments.reproduce import GPU_PROFILES, PROFILES
    from tofdenoise.experiments.tables import table_specs

    on_gpu = set()
    for profile in PROFILES:
        spec = table_specs("3", [0], profile_overrides(profile, tmp_path, []))[0]
        if compose_config(list(spec.overrides)).trainer.accelerator == "gpu":
            on_gpu.add(profile)
    assert on_gpu == set(GPU_PROFILES) == {"gpu", "gpu-short"}


def test_dry_run_names_the_executor_and_bad_executor_options_exit_2(tmp_path, capsys):
    out, results, page = tmp_path / "runs", tmp_path / "results", tmp_path / "results.md"
    argv = ["--table", "3", "--seeds", "0", "--out", str(out), "--results", str(results), "--page", str(page)]
    assert main([*argv, "--dry-run", "--executor", "local", "--workers", "3"]) == 0
    printed = capsys.readouterr().out
    assert "executor: local (3 workers, each run in its own process)" in printed
    assert len([line for line in printed.splitlines() if ": would run: " in line]) == 10
    assert main([*argv, "--dry-run", "--executor", "local", "--workers", "0"]) == 2
    assert "tofdenoise reproduce: error: --workers must be a whole number >= 1, got 0" in capsys.readouterr().err
    assert main([*argv, "--dry-run", "--executor", "slurm", "--slurm-extra", "account"]) == 2
    assert "--slurm-extra expects KEY=VALUE" in capsys.readouterr().err
    assert not page.exists() and not results.exists()


def test_every_target_has_its_records_and_its_make_command():
    """Tables 1-3 and the study are the tables' keys, figures 7 and 8 the qualitative figures (6: the validation);
    each target's key names it back, and the Makefile has the variable of each kind."""
    from tofdenoise.experiments.figures import FIGURES
    from tofdenoise.experiments.tables import TABLES

    targets = [Target(kind, name) for kind, names in KINDS.items() for name in names]
    assert {t.key for t in targets if t.kind != "figure"} == set(TABLES)
    assert {t.key for t in targets if t.kind == "figure"} == {"fig6", *FIGURES}
    assert all(target_of_key(t.key) == t for t in targets)
    assert Target("study", "dynrange").make_command("cpu", "0,1,2") == (
        "make reproduce STUDY=dynrange PROFILE=cpu SEEDS=0,1,2"
    )
    assert Target("figure", "6").option == "--figure 6"
    with pytest.raises(ValueError, match="no figure '3'"):
        Target("figure", "3")
    makefile = (Path(__file__).resolve().parents[2] / "Makefile").read_text()
    for variable, kind in (("TABLE", "table"), ("FIGURE", "figure"), ("STUDY", "study")):
        assert f"$(if $({variable}),--{kind} $({variable}))" in makefile


def test_figure_6_validates_the_noise_model_on_the_second_camera_in_this_process(tmp_path):
    """Figure 6 of a (tiny) stand-in real set: its validation captures against the calibration estimated from its
    own calibration captures, committed and on the page; no sub-process (issue 24 point 3: it was one)."""
    from tofdenoise.data_modules.realset import build_realset
    from tofdenoise.experiments.reproduce import Reproduction, validation_figure
    from tofdenoise.reporting.results_page import machine_label, results_markdown

    build_realset(tmp_path / "realset", scenes=1, frames=2, height=16, width=16, log=lambda line: None)
    results = tmp_path / "results"
    job = Reproduction(Target("figure", "6"), results=results, page=tmp_path / "results.md", out=tmp_path)
    logged: list[str] = []
    assert validation_figure(job, log=logged.append) == 0
    data = json.loads((results / "cpu" / "fig6" / "validation.json").read_text())
    assert data["source"] == f"captures: {tmp_path / 'realset' / 'validation'}"  # measured, not simulated
    assert np.isfinite(data["pooled"]["proposed"]["mape_percent"]) and data["pooled"]["proposed"]["n"] > 10
    committed, made = results / "cpu" / "fig6" / "validation.png", tmp_path / "fig6" / "validation.png"
    assert committed.read_bytes() == made.read_bytes()
    assert any("proposed pooled MAPE" in line for line in logged)
    page = results_markdown(results)
    assert "| pooled | proposed |" in page
    # the record says when, with which code and on which machine it was written, and the page repeats it
    provenance = data["provenance"]
    assert provenance["commit"] == code_commit()["commit"] and provenance["machine"] == host_machine()
    written = datetime.strptime(provenance["written"], "%Y-%m-%dT%H:%M:%S%z")
    assert abs((datetime.now(timezone.utc) - written).total_seconds()) < 600
    assert f"Written {provenance['written'][:10]}, " in page and f"on {machine_label(provenance)}." in page


def test_a_figure_record_names_its_provenance_or_says_it_is_older():
    from tofdenoise.reporting.results_page import written_line

    machine = {"cpu": "AMD EPYC", "cpu_id": "AuthenticAMD 25/17", "cpu_count": 2}
    record = {"written": "2026-11-28T16:40:00+0000", "commit": "ab" * 20, "commit_dirty": False, "machine": machine}
    assert written_line(record) == "Written 2026-11-28, commit abababa, on AMD EPYC (AuthenticAMD 25/17)."
    assert written_line({**record, "commit_dirty": True}) == (
        "Written 2026-11-28, commit abababa with uncommitted changes, on AMD EPYC (AuthenticAMD 25/17)."
    )
    assert written_line({**record, "commit": None, "version": "0.3.0"}) == (
        "Written 2026-11-28, package version 0.3.0, on AMD EPYC (AuthenticAMD 25/17)."
    )
    assert written_line(None) == "Written before figure records named their commit and machine."


def _region_result(mae_by_image: dict[str, float]) -> dict:
    images = {u: {"psnr_db": 40.0, "mae_mm": v, "mse_mm2": 9.0, "ssim": 0.99} for u, v in mae_by_image.items()}
    mean = {"psnr_db": 40.0, "mae_mm": sum(mae_by_image.values()) / len(mae_by_image), "mse_mm2": 9.0, "ssim": 0.99}
    return {"mean": mean, "images": images}


def _regions_record(path: Path, set_name: str, off_edge: dict[str, float], edge: dict[str, float], **extra) -> None:
    """A run's regions.json as tofdenoise evaluate --run --edge-jump-mm writes it (only what the page reads)."""
    raw = {u: 10.0 for u in off_edge}
    scored = {
        "inputs_as_recorded": True,
        "restored": {"regions": {"off_edge": _region_result(off_edge), "edge": _region_result(edge)}},
        "input": {"regions": {"off_edge": _region_result(raw), "edge": _region_result(raw)}},
        **extra,
    }
    path.write_text(json.dumps({"sets": {set_name: scored}}))


def test_off_edge_columns_and_orderings_read_each_runs_regions_record(tmp_path, capsys):
    """Table III's off-edge columns and orderings come from each run's regions.json: the column is the mean of the
    off-edge MAE over the seeds; the ordering's steps pair the runs by seed and its interval pairs them by image;
    a set whose rebuilt inputs were not the record's (inputs_as_recorded false) counts as no record, and a record
    without the regions is an error naming it."""
    results = _results_with_three_seeds(tmp_path)
    for seed in range(3):
        for noise, off in (("hetero", 2.0), ("range", 2.1)):
            d = results / "cpu" / f"unet-{noise}-l1-s{seed}"
            d.mkdir(parents=True)
            entry = {"psnr_db": 40.0, "mae_mm": 3.0, "mse_mm2": 9.0, "ssim": 0.99}
            entry["raw"] = {"psnr_db": 30.0, "mae_mm": 7.0, "mse_mm2": 90.0, "ssim": 0.9}
            _write_metrics(d / "metrics.json", {"synthetic": entry, "simulated": entry})
            (d / "run_info.json").write_text(json.dumps({"started": "2026-11-22T10:00:00+0000"}))
            per_image = {"a": off + 0.1 * seed, "b": off + 0.1 * seed + 0.2}
            _regions_record(d / "regions.json", "simulated", per_image, {"a": 40.0, "b": 41.0})
    page = tmp_path / "results.md"
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 0
    lines = page.read_text().splitlines()
    header = next(line for line in lines if line.startswith("| method | PSNR (dB)↑ paper / ours | MAE"))
    cells = [c.strip() for c in header.split("|")]
    column = cells.index("simulator-noised off-edge MAE (mm)↓ paper / ours")
    hetero_line = next(line for line in lines if line.startswith("| U-Net, hetero (proposed) |"))
    hetero = [c.strip() for c in hetero_line.split("|")]
    assert hetero[column] == "- / 2.20 ± 0.10 (n=3)"  # images a, b: 2.1 + 0.1 s mean over s = 0, 1, 2
    assert hetero[cells.index("off-edge MAE (mm)↓ paper / ours")] == "- / -"  # no synthetic regions recorded
    claim = next(line for line in lines if "U-Net: hetero < range (simulator-noised MAE off depth edges)" in line)
    assert "0: yes, 1: yes, 2: yes" in claim and "+0.100 ± 0.000 mm (n=3)" in claim
    assert "[+0.100, +0.100] mm" in claim and "100 % of 2 images" in claim
    # a set rebuilt into other images than its record's is no record
    d = results / "cpu" / "unet-range-l1-s2"
    _regions_record(
        d / "regions.json", "simulated", {"a": 9.0, "b": 9.0}, {"a": 40.0, "b": 41.0}, inputs_as_recorded=False
    )
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 0
    claim = next(
        line for line in page.read_text().splitlines() if "U-Net: hetero < range (simulator-noised MAE off" in line
    )
    assert "0: yes, 1: yes |" in claim and "(n=2)" in claim
    (d / "regions.json").write_text(json.dumps({"sets": {"simulated": {"inputs_as_recorded": True, "restored": {}}}}))
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 2
    assert (
        f"tofdenoise reproduce: error: {d / 'regions.json'}: expected tofdenoise evaluate --run"
        in capsys.readouterr().err
    )


def test_table_3_at_both_profiles_sets_each_profiles_steps_side_by_side(tmp_path):
    """The page's cross-profile table: per ordering of Table III the mean ± std over each profile's seeds of the
    paired step and in how many seeds it holds, hand-computed; absent until the GPU profile has a Table III record."""
    results = tmp_path / "results"

    def run(profile: str, name: str, mae: float) -> None:
        d = results / profile / name
        d.mkdir(parents=True)
        entry = {"psnr_db": 40.0, "mae_mm": mae, "mse_mm2": 9.0, "ssim": 0.99}
        entry["raw"] = {"psnr_db": 30.0, "mae_mm": 7.0, "mse_mm2": 90.0, "ssim": 0.9}
        _write_metrics(d / "metrics.json", {"synthetic": entry})
        (d / "run_info.json").write_text(json.dumps({"started": "2026-11-22T10:00:00+0000"}))

    for seed, (hetero, range_) in enumerate([(2.0, 2.3), (2.1, 2.3), (2.0, 2.4)]):  # steps +0.3, +0.2, +0.4
        run("cpu", f"unet-hetero-l1-s{seed}", hetero)
        run("cpu", f"unet-range-l1-s{seed}", range_)
    (results / "discussion.md").write_text("## Discussion\n")
    page = tmp_path / "results.md"
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 0
    assert "# Table III at both profiles" not in page.read_text()
    run("gpu-short", "unet-hetero-l1-s0", 1.75)
    run("gpu-short", "unet-range-l1-s0", 1.67)  # reversed at the paper's crop size
    run("gpu-short", "unet-range-l1-s1", 1.70)  # no hetero run of seed 1: not paired
    assert main(["--page-only", "--results", str(results), "--page", str(page)]) == 0
    text = page.read_text()
    assert text.index("# Table III at both profiles") < text.index("# Profile `cpu`")
    row = next(line for line in text.splitlines() if line.startswith("| hetero < range for U-Net (synthetic MAE) |"))
    cells = "+0.300 ± 0.100 mm (n=3) | 3 of 3 | -0.080 mm (n=1) | 0 of 1"
    assert row == f"| hetero < range for U-Net (synthetic MAE) | {cells} |"
