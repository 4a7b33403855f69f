"""The robustness grid: its runs, the per-run verdict from metrics.json, the table; the whole grid (slow)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

from tofdenoise.cli.grid import main
from tofdenoise.experiments.grids import robustness_rows, robustness_specs
from tofdenoise.experiments.runner import run_all
from tofdenoise.records import learned_verdict, set_entry, write_metrics_json
from tofdenoise.reporting.robustness import robustness_table

REPO = Path(__file__).resolve().parents[2]


def test_the_grid_has_108_distinct_runs_over_both_cameras():
    specs = robustness_specs()
    assert len(specs) == 3 * 3 * 2 * 3 * 2 == len({s.name for s in specs})
    assert {s.meta["sensor"] for s in specs} == {"default", "cam75"}
    assert all((REPO / "configs" / "sensor" / f"{s.meta['sensor']}.yaml").is_file() for s in specs)
    dvss = next(s for s in specs if s.meta["backbone"] == "dvss")
    assert "backbone.kwargs.width=16" in dvss.overrides and "experiment=grid" in dvss.overrides
    with pytest.raises(ValueError, match="unknown backbone"):
        robustness_specs(["vgg"])


def _fake_run(root: Path, name: str, best: float | None, raw: float = 6.0, finished: bool = True) -> None:
    d = root / name
    m = {"psnr_db": 45.0, "mae_mm": 2.0, "mse_mm2": 9.0, "ssim": 0.99, "mae_mm_pooled": 2.0}
    write_metrics_json(
        d / "metrics.json",
        {"synthetic": set_entry(m, {**m, "mae_mm": 6.0}, {"images": 3})},
        run=learned_verdict(100, best, raw),
    )
    info = {"run_name": name, **({"finished": "2026-11-22T00:00:00"} if finished else {})}
    (d / "run_info.json").write_text(json.dumps(info))


def test_rows_judge_each_run_by_its_validation_maes(tmp_path):
    specs = robustness_specs(["unet"], ["hetero"], ["l1"], ["default"], [0, 1, 2])
    _fake_run(tmp_path, specs[0].name, best=4.2)  # 30 % below 6.0 exactly: pass
    _fake_run(tmp_path, specs[1].name, best=4.3)  # 28 %: FAIL
    rows = robustness_rows(specs, tmp_path)
    assert [r["status"] for r in rows] == ["pass", "FAIL", "missing"]
    assert math.isclose(rows[0]["reduction"], 0.3) and rows[0]["test_mae_mm"] == 2.0
    table = robustness_table(rows)
    assert "| unet | default | hetero | l1 | 6.00 | 4.20 / 4.30 / - | 30% / 28% / - | FAIL |" in table
    assert "2 of 3 runs finished; 1 pass" in table and "1 fail: unet-default-hetero-l1-s1" in table


def test_cli_table_only_exit_status_and_markdown(tmp_path, capsys):
    specs = robustness_specs(["unet"], ["fixed"], ["full"], ["cam75"], [0])
    _fake_run(tmp_path, specs[0].name, best=1.0)
    md = tmp_path / "t.md"
    args = [
        "robustness",
        "--out",
        str(tmp_path),
        "--backbones",
        "unet",
        "--noises",
        "fixed",
        "--losses",
        "full",
        "--sensors",
        "cam75",
        "--seeds",
        "0",
        "--table-only",
        "--markdown",
        str(md),
    ]
    assert main(args) == 0
    assert "| pass |" in md.read_text() and "| pass |" in capsys.readouterr().out
    assert main(args[:11] + ["--seeds", "0", "1", "--table-only"]) == 1  # seed 1 has not run: not all pass
    capsys.readouterr()
    assert main(args[:-1] + [str(tmp_path / "t.html")]) == 2
    assert "--markdown" in capsys.readouterr().err
    notes = tmp_path / specs[0].name / "notes.md"  # a file of a run the table is made from
    notes.write_text("by hand\n")
    assert main(args[:-1] + [str(notes)]) == 2
    assert f"tofdenoise grid: error: --markdown {notes} would replace notes.md" in capsys.readouterr().err
    assert notes.read_text() == "by hand\n"


@pytest.mark.slow
def test_robustness_grid_every_run_cuts_the_raw_validation_mae_by_30_percent():
    """The whole grid (hours on 2 CPU cores; resumable: runs/robustness, or $TOFDENOISE_GRID_DIR)."""
    out = Path(os.environ.get("TOFDENOISE_GRID_DIR", REPO / "runs" / "robustness"))
    specs = robustness_specs()
    outcomes = run_all(specs, out)
    assert not [o.spec.name for o in outcomes if o.status == "failed"]
    rows = robustness_rows(specs, out)
    print(robustness_table(rows))
    assert all(r["status"] == "pass" for r in rows), [r["name"] for r in rows if r["status"] != "pass"]


def test_grid_dry_run_names_the_executor(tmp_path, capsys):
    from tofdenoise.cli.grid import main

    argv = ["robustness", "--out", str(tmp_path / "r"), "--backbones", "unet", "--sensors", "default"]
    argv += ["--noises", "hetero", "--losses", "l1", "--seeds", "0", "1", "--dry-run"]
    assert main([*argv, "--executor", "local", "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    assert "executor: local (2 workers" in printed and printed.count(": would run: ") == 2
    assert main([*argv, "--workers", "2"]) == 2
    assert "--workers 2 needs --executor local" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
