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


def _fake_python(tmp_path, ignore_sigterm: bool, records_first: bool = False):
    """A stand-in for ``python -m tofdenoise.cli.train ... paths.run_dir=D``: it takes the run folder's lock as a
    training does, then trains forever (``ignore_sigterm``: it does not end on SIGTERM, like a step that hangs;
    ``records_first``: it first writes a finished run's records, like a process slow to exit after its test)."""
    script = tmp_path / ("stubborn.py" if ignore_sigterm else "trainer.py")
    script.write_text(
        f"#!{sys.executable}\n"
        "import json, os, signal, socket, sys, time\n"
        "run_dir = [a.split('=', 1)[1] for a in sys.argv if a.startswith('paths.run_dir=')][0]\n"
        "json.dump({'pid': os.getpid(), 'host': socket.gethostname()}, open(os.path.join(run_dir, 'run.lock'), 'w'))\n"
        + (
            "json.dump({'finished': 'now'}, open(os.path.join(run_dir, 'run_info.json'), 'w'))\n"
            "json.dump({'results': {}}, open(os.path.join(run_dir, 'metrics.json'), 'w'))\n"
            if records_first
            else ""
        )
        + ("signal.signal(signal.SIGTERM, signal.SIG_IGN)\n" if ignore_sigterm else "")
        + "print('training', flush=True)\n"
        "time.sleep(60)\n"
    )
    script.chmod(0o755)
    return str(script)


@pytest.mark.parametrize("ignore_sigterm", [False, True])
def test_time_budget_stops_a_run_at_its_end_and_keeps_it_resumable(tmp_path, capsys, ignore_sigterm):
    import time

    from tofdenoise.experiments.runner import TimeBudget

    budget = TimeBudget(time.monotonic() + 1.5, grace_s=1.0)
    t0 = time.monotonic()
    out = run_all([RunSpec("r", SMOKE)], tmp_path, python=_fake_python(tmp_path, ignore_sigterm), budget=budget)
    took = time.monotonic() - t0
    assert [o.status for o in out] == ["stopped"]
    # SIGTERM ends it at once; one that ignores SIGTERM is killed after the grace period
    assert 1.4 < took < (5.0 if ignore_sigterm else 4.0), took
    assert out[0].returncode == (-9 if ignore_sigterm else -15)
    assert not (tmp_path / "r" / "run.lock").exists()  # a killed run's lock is cleared: the folder can travel
    assert not run_finished(tmp_path / "r")
    log = (tmp_path / "r" / "train.log").read_text()
    assert "the time budget ended: training stopped" in log
    assert "stopped at the end of the time budget" in capsys.readouterr().out


def test_time_budget_end_after_a_runs_records_keeps_it_as_finished(tmp_path, capsys):
    """A run stopped by the budget after it wrote its finished records (on its way out) is done, not thrown away:
    on a GPU machine a finished DVSS run was once stopped one second after its records."""
    import time

    from tofdenoise.experiments.runner import TimeBudget

    fake = _fake_python(tmp_path, ignore_sigterm=False, records_first=True)
    out = run_all([RunSpec("r", SMOKE)], tmp_path, python=fake, budget=TimeBudget(time.monotonic() + 1.5, grace_s=1.0))
    assert [o.status for o in out] == ["done"] and out[0].returncode == -15
    assert run_finished(tmp_path / "r") and not (tmp_path / "r" / "run.lock").exists()
    assert "it had written its records" in (tmp_path / "r" / "train.log").read_text()
    assert "stopped at the end of the time budget" not in capsys.readouterr().out


def test_time_budget_defers_runs_that_would_not_fit_but_resumes_started_ones(tmp_path, capsys):
    import time

    from tofdenoise.experiments.runner import TimeBudget

    (tmp_path / "resumed" / "checkpoints").mkdir(parents=True)
    (tmp_path / "resumed" / "checkpoints" / "last.ckpt").write_bytes(b"")
    estimates = {"long": 3600.0, "resumed": 3600.0}
    budget = TimeBudget(time.monotonic() + 1.0, estimate=lambda spec: estimates.get(spec.name), grace_s=1.0)
    fake = _fake_python(tmp_path, ignore_sigterm=False)
    out = run_all([RunSpec("long", SMOKE), RunSpec("resumed", SMOKE)], tmp_path, python=fake, budget=budget)
    assert [o.status for o in out] == ["deferred", "stopped"]
    assert not (tmp_path / "long").exists()  # a deferred run writes nothing
    printed = capsys.readouterr().out
    assert "[1/2] long: not started: needs about 60.0 min, 0.0 min left of the time budget" in printed
    # the budget is spent: nothing starts, not even a run that would resume
    out = run_all([RunSpec("resumed", SMOKE)], tmp_path, python=fake, budget=TimeBudget(time.monotonic() - 1))
    assert [o.status for o in out] == ["deferred"]


def test_time_budget_with_local_workers_defers_and_stops_as_the_sequential_runner(tmp_path, capsys):
    """Two local workers share one budget: a run that would not fit is deferred as a worker takes it up, the two
    that start are stopped at the budget's end (resumable, not recorded), and the outcomes come back in order."""
    import time

    from tofdenoise.experiments.executors import LocalExecutor
    from tofdenoise.experiments.runner import TimeBudget

    estimates = {"long": 3600.0}
    budget = TimeBudget(time.monotonic() + 1.5, estimate=lambda spec: estimates.get(spec.name), grace_s=1.0)
    fake = _fake_python(tmp_path, ignore_sigterm=False)
    specs = [RunSpec("a", SMOKE), RunSpec("long", SMOKE), RunSpec("b", SMOKE)]
    t0 = time.monotonic()
    out = run_all(specs, tmp_path, python=fake, executor=LocalExecutor(2), budget=budget)
    took = time.monotonic() - t0
    assert [o.status for o in out] == ["stopped", "deferred", "stopped"]
    assert 1.4 < took < 4.0, took  # a and b side by side, each stopped at the deadline
    assert not (tmp_path / "long").exists()
    for name in ("a", "b"):
        assert "the time budget ended: training stopped" in (tmp_path / name / "train.log").read_text()
        assert not run_finished(tmp_path / name)
    printed = capsys.readouterr().out
    assert "[2/3] long: not started: needs about 60.0 min" in printed
    assert printed.count("stopped at the end of the time budget") == 2


def test_time_budget_needs_an_executor_that_takes_one(tmp_path):
    from tofdenoise.experiments.runner import TimeBudget

    class Elsewhere:  # an executor without budgets (a SLURM array has its own time limit)
        name = "slurm"

    with pytest.raises(ValueError, match="time budget needs the sequential or the local executor, not slurm"):
        run_all([RunSpec("r", SMOKE)], tmp_path, executor=Elsewhere(), budget=TimeBudget.minutes(1))
    with pytest.raises(ValueError, match="positive number of minutes"):
        TimeBudget.minutes(0)
