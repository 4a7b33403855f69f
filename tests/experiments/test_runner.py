"""The resumable run-grid runner: runs, skips finished runs, resumes interrupted ones, lists failures."""

from __future__ import annotations

import json
import sys

import pytest

from tofdenoise.experiments.runner import RunSpec, run_all, run_finished

SMOKE = (
    "experiment=smoke",
    "logger=csv",
    "trainer.max_epochs=1",
    "trainer.enable_progress_bar=false",
    "data.source_kwargs.num_samples=10",
    "data.source_kwargs.height=32",
    "data.source_kwargs.width=48",
    "data.crop_size=32",
    "backbone.kwargs.width=8",
    "backbone.kwargs.stages=2",
    "trainer.enable_model_summary=false",
)


def test_spec_refuses_run_dir_overrides_and_bad_names():
    with pytest.raises(ValueError, match="run folder"):
        RunSpec("a", ("paths.run_dir=/tmp/x",))
    with pytest.raises(ValueError, match="plain folder name"):
        RunSpec("a/b", ())


def test_duplicate_names_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unique.*dup"):
        run_all([RunSpec("dup", ()), RunSpec("dup", ())], tmp_path, dry_run=True, echo=False)


def test_run_skip_and_failure_listed(tmp_path, capsys):
    data_cache = tmp_path / "cache"
    specs = [RunSpec("bad", (*SMOKE, "backbone=nope")), RunSpec("good", (*SMOKE, f"++data.cache_dir={data_cache}"))]
    out = run_all(specs, tmp_path, python=sys.executable)
    assert [o.status for o in out] == ["failed", "done"]  # the failure did not stop the next run
    assert out[0].returncode != 0 and "backbone/nope" in out[0].log_tail
    printed = capsys.readouterr().out
    assert "1 run(s) failed" in printed and "bad (exit" in printed
    assert run_finished(tmp_path / "good")
    metrics = json.loads((tmp_path / "good" / "metrics.json").read_text())
    assert "synthetic" in metrics
    # a second run of the command: the finished run is skipped, the failed one is tried again (and fails again)
    seen = []
    again = run_all(specs, tmp_path, python=sys.executable, echo=False, after_each=lambda o: seen.append(o.status))
    assert [o.status for o in again] == ["failed", "skipped"]
    assert seen == ["failed", "skipped"]  # after_each sees every spec as it ends, in order


def test_dry_run_marks_resume(tmp_path, capsys):
    (tmp_path / "r" / "checkpoints").mkdir(parents=True)
    (tmp_path / "r" / "checkpoints" / "last.ckpt").write_bytes(b"")
    out = run_all([RunSpec("r", SMOKE)], tmp_path, dry_run=True)
    assert out[0].status == "planned"
    assert "(resume)" in capsys.readouterr().out and not (tmp_path / "r" / "train.log").exists()
