"""Executors of a grid: N local workers give the records of the sequential runner, byte for byte; the SLURM path
(submitit, run here through its LocalExecutor: the same task code minus the scheduler) requeues a preempted task,
which resumes from ``last.ckpt``; bad options are errors naming the option."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tofdenoise.experiments import executors
from tofdenoise.experiments.executors import (
    LocalExecutor,
    SlurmExecutor,
    SlurmOptions,
    make_executor,
    parse_sbatch_extra,
)
from tofdenoise.experiments.runner import RunSpec, run_all, run_finished

TINY = (
    "experiment=smoke",
    "logger=csv",
    "trainer.enable_progress_bar=false",
    "trainer.enable_model_summary=false",
    "data.source_kwargs.num_samples=10",
    "data.source_kwargs.height=32",
    "data.source_kwargs.width=48",
    "data.crop_size=32",
    "data.batch_size=2",
    "backbone=unet",
    "backbone.kwargs.width=8",
    "backbone.kwargs.stages=2",
)
#: the records a table is built from, compared byte for byte
RECORDS = ("metrics.json", "per_image/synthetic.csv", "csv/metrics.csv")
#: run_info.json fields that legitimately differ between two trainings of the same run: wall-clock times, the
#: speed and memory measured during them
RUN_INFO_VOLATILE = ("started", "finished", "train_seconds", "train_images_per_second", "peak_rss_gib")


def _specs(cache: Path, n: int, *extra: str) -> list[RunSpec]:
    return [RunSpec(f"unet-s{seed}", (*TINY, f"seed={seed}", f"++data.cache_dir={cache}", *extra)) for seed in range(n)]


def _run_info(run_dir: Path, out: Path) -> dict:
    info = json.loads((run_dir / "run_info.json").read_text().replace(str(out), "<out>"))
    for key in RUN_INFO_VOLATILE:
        assert key in info, key  # the list names fields that exist: a renamed field must be looked at
        info.pop(key)
    return info


def _config(run_dir: Path, out: Path) -> str:
    """config.yaml (a record) with the grid's folder replaced and Hydra's ``paths.sweep_dir`` (a default holding
    the composition's clock time, unused by a single run) dropped: the two ways the same run's config may differ."""
    lines = (run_dir / "config.yaml").read_text().replace(str(out), "<out>").splitlines()
    kept = [line for line in lines if not line.startswith("  sweep_dir: outputs/multirun/")]
    assert len(kept) == len(lines) - 1
    return "\n".join(kept)


def test_two_local_workers_give_the_sequential_records_byte_for_byte(tmp_path, capsys):
    """A 4-run grid (seeds 0-3, tiny U-Net, one epoch) with 2 local workers, then sequentially in another folder;
    the two parallel runs share one fresh σ_D cache and split file. About 60 s on 2 cores."""
    cache = tmp_path / "cache"
    specs = _specs(cache, 4, "trainer.max_epochs=1")
    par, seq = tmp_path / "local", tmp_path / "sequential"
    seen: list[str] = []
    t0 = time.perf_counter()
    out_par = run_all(specs, par, executor=LocalExecutor(2), after_each=lambda o: seen.append(o.spec.name))
    t_par = time.perf_counter() - t0
    printed = capsys.readouterr().out
    assert "executor: local (2 workers" in printed and printed.count(": done in ") == 4
    assert [o.status for o in out_par] == ["done"] * 4 and [o.spec.name for o in out_par] == [s.name for s in specs]
    assert sorted(seen) == sorted(s.name for s in specs)  # after_each saw every run once
    t0 = time.perf_counter()
    out_seq = run_all(specs, seq)
    t_seq = time.perf_counter() - t0
    assert [o.status for o in out_seq] == ["done"] * 4
    print(f"4 tiny runs: 2 local workers {t_par:.1f} s, sequential {t_seq:.1f} s")
    for spec in specs:
        a, b = par / spec.name, seq / spec.name
        for name in RECORDS:
            assert (a / name).read_bytes() == (b / name).read_bytes(), f"{spec.name}/{name}"
        info_par, info_seq = _run_info(a, par), _run_info(b, seq)
        # the one difference: the record says two runs shared the machine (their rates are a shared machine's)
        assert info_par["machine"].pop("runs_at_once") == 2 and info_seq["machine"].pop("runs_at_once") == 1
        assert info_par == info_seq
        assert _config(a, par) == _config(b, seq)
    seeds = {json.loads((par / s.name / "metrics.json").read_text())["synthetic"]["mae_mm"] for s in specs}
    assert len(seeds) == 4  # four different runs, not one run four times
    # a second run of the command skips every run, whichever executor
    again = run_all(specs, par, executor=LocalExecutor(2), echo=False)
    assert [o.status for o in again] == ["skipped"] * 4


def test_local_workers_list_failures_with_their_logs_and_go_on(tmp_path, capsys):
    specs = [
        RunSpec("bad", (*TINY, "backbone=nope", f"++data.cache_dir={tmp_path / 'cache'}")),
        RunSpec("also-bad", (*TINY, "loss=nope", f"++data.cache_dir={tmp_path / 'cache'}")),
    ]
    out = run_all(specs, tmp_path / "runs", executor=LocalExecutor(2))
    assert [o.status for o in out] == ["failed", "failed"]
    assert "backbone/nope" in out[0].log_tail and "loss/nope" in out[1].log_tail
    printed = capsys.readouterr().out
    assert "2 run(s) failed:" in printed and "bad (exit 1)" in printed


def test_dry_run_says_which_executor_and_runs_nothing(tmp_path, capsys):
    specs = _specs(tmp_path / "cache", 2)
    for executor, says in (
        (None, "executor: sequential"),
        (LocalExecutor(3), "executor: local (3 workers"),
        (SlurmExecutor(SlurmOptions(partition="gpu", extra={"account": "lab"})), "partition gpu, 1440 min per task"),
    ):
        out = run_all(specs, tmp_path / "runs", dry_run=True, executor=executor)
        assert [o.status for o in out] == ["planned", "planned"]
        printed = capsys.readouterr().out
        assert says in printed and printed.count(": would run: ") == 2
    assert "--account=lab" in SlurmExecutor(SlurmOptions(extra={"account": "lab"})).describe()
    assert not (tmp_path / "runs").exists()


def test_bad_executor_options_name_the_option():
    with pytest.raises(ValueError, match="--workers must be a whole number >= 1, got 0"):
        make_executor("local", 0)
    with pytest.raises(ValueError, match="--workers 4 needs --executor local"):
        make_executor("sequential", 4)
    with pytest.raises(ValueError, match="--executor must be one of sequential, local, slurm, got 'pbs'"):
        make_executor("pbs")
    with pytest.raises(ValueError, match="--slurm-extra expects KEY=VALUE"):
        parse_sbatch_extra(["account"])
    extra = parse_sbatch_extra(["--account=lab", "constraint=a100|h100"])
    assert extra == {"account": "lab", "constraint": "a100|h100"}
    with pytest.raises(ValueError, match="--slurm-time-min must be a whole number >= 1, got 0"):
        SlurmOptions(time_min=0)
    with pytest.raises(ValueError, match="--slurm-signal-delay-s .* must be shorter than --slurm-time-min"):
        SlurmOptions(time_min=2, signal_delay_s=120)


def test_slurm_without_submitit_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "submitit", None)  # what an environment without the extra looks like
    with pytest.raises(RuntimeError, match=r"--executor slurm needs submitit.*pip install -e '\.\[cluster\]'"):
        make_executor("slurm")


def _ppid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def test_submitit_array_task_preempted_is_requeued_and_resumes_from_last_ckpt(tmp_path, capsys):
    """The SLURM path through submitit's LocalExecutor: one array of two runs; once run ``unet-s0`` has written
    ``last.ckpt``, its array task gets submitit's preemption signal (USR2, as SLURM sends it before a preemption
    or a timeout). The task stops its training, submitit requeues it, and the requeued task resumes the run from
    ``last.ckpt`` to the end: its run_info says ``resumed`` and its final checkpoint is at the last epoch.
    About 60 s on 2 idle cores (most of it three Python processes starting)."""
    pytest.importorskip("submitit")
    torch = pytest.importorskip("torch")
    epochs = 5
    first, second = _specs(tmp_path / "cache", 2)
    specs = [
        RunSpec(first.name, (*first.overrides, f"trainer.max_epochs={epochs}")),
        RunSpec(second.name, (*second.overrides, "trainer.max_epochs=1")),  # short: it only shares the array
    ]
    out = tmp_path / "runs"
    executor = SlurmExecutor(SlurmOptions(cluster="local", time_min=30, poll_s=0.5, grace_s=30))
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(outcomes=run_all(specs, out, executor=executor)))
    thread.start()
    run_dir = out / "unet-s0"
    deadline = time.monotonic() + 240
    while not (run_dir / "checkpoints" / "last.ckpt").is_file():  # the first epoch has ended
        assert thread.is_alive() and time.monotonic() < deadline, "run unet-s0 wrote no last.ckpt"
        time.sleep(0.05)
    holder = json.loads((run_dir / "run.lock").read_text())  # the training process holds its folder
    task_pid = _ppid(holder["pid"])  # ... and its parent is the array task, under submitit's local controller
    assert "submitit" in Path(f"/proc/{task_pid}/cmdline").read_bytes().decode()
    os.kill(task_pid, signal.SIGUSR2)
    thread.join(timeout=300)
    assert not thread.is_alive()
    outcomes = result["outcomes"]
    assert [o.status for o in outcomes] == ["done", "done"]
    printed = capsys.readouterr().out
    assert "executor: slurm (submitit's local executor" in printed and "submitted as job" in printed
    log = (run_dir / "train.log").read_text()
    assert "timeout or preemption signal: training stopped" in log
    starts = [line for line in log.splitlines() if line.startswith("# 20") and "tofdenoise.cli.train" in line]
    assert len(starts) == 2 and "ckpt_path=last" not in starts[0] and starts[1].endswith("ckpt_path=last")
    info = json.loads((run_dir / "run_info.json").read_text())
    assert "resumed" in info and run_finished(run_dir)
    last = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert last["epoch"] == epochs - 1 and last["global_step"] == epochs * 3  # 6 train images, batch 2
    assert not (run_dir / "run.lock").exists()
    # the other task was not interrupted: one start, no resume
    other = (out / "unet-s1" / "train.log").read_text()
    assert other.count("tofdenoise.cli.train") == 1 and "resumed" not in json.loads(
        (out / "unet-s1" / "run_info.json").read_text()
    )
    assert list((out / "slurm").glob("*/*_log.out"))  # submitit's logs under <out>/slurm


def test_the_sbatch_script_of_a_table_array(tmp_path, monkeypatch):
    """The options reach sbatch: the script submitit writes for a 21-run array (submitit only checks that
    ``srun`` exists; nothing is submitted). Without SLURM's tools the command refuses before any work."""
    pytest.importorskip("submitit")
    options = SlurmOptions(
        partition="gpu",
        time_min=600,
        cpus_per_task=6,
        mem="48G",
        array_parallelism=8,
        extra={"account": "lab", "constraint": "a100"},
        setup=("module load cuda/12.4",),
    )
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(RuntimeError, match="sbatch and srun is not on PATH here: run the command on the cluster"):
        make_executor("slurm", slurm=options, check_cluster=True)
    assert isinstance(make_executor("slurm", slurm=options), SlurmExecutor)  # a dry run needs no cluster
    for tool in ("sbatch", "srun"):
        (tmp_path / tool).write_text("#!/bin/sh\nexit 1\n")
        (tmp_path / tool).chmod(0o755)
    executor = make_executor("slurm", slurm=options, check_cluster=True)
    inner = executor.make_submitit_executor(tmp_path / "runs")._executor
    inner.parameters["map_count"] = 21  # what submit_array sets for 21 tasks
    script = inner._make_submission_file_text("python -u -m submitit.core._submit x", "uid")
    for line in (
        "#SBATCH --partition=gpu",
        "#SBATCH --time=600",
        "#SBATCH --gpus-per-task=1",
        "#SBATCH --cpus-per-task=6",
        "#SBATCH --mem=48G",
        "#SBATCH --array=0-20%8",
        "#SBATCH --signal=USR2@120",
        "#SBATCH --account=lab",
        "#SBATCH --constraint=a100",
        "#SBATCH --nodes=1",
        "module load cuda/12.4",
    ):
        assert line in script.splitlines(), line
    assert f"#SBATCH --output={tmp_path / 'runs' / 'slurm'}/%A_%a/%A_%a_0_log.out" in script.splitlines()


def test_a_training_that_ignores_sigterm_is_killed_after_the_grace_and_its_lock_cleared(tmp_path):
    """RunTask.stop_training (what a requeue does first): SIGTERM, SIGKILL after ``grace_s``, and the run.lock the
    killed process leaves (it names that pid on this host) is removed, so the requeued task, maybe on another
    node, is not refused. A lock of another process is left alone."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    stubborn = (
        "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('up', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", stubborn], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "up"  # its SIGTERM handler is in place

    (run_dir / "run.lock").write_text(json.dumps({"pid": proc.pid, "host": socket.gethostname()}))
    task = executors.RunTask(RunSpec("run", ()), run_dir, sys.executable, grace_s=1)
    executors._ACTIVE["run"] = proc
    try:
        t0 = time.monotonic()
        assert task.stop_training() == -signal.SIGKILL
        assert 1.0 <= time.monotonic() - t0 < 10
    finally:
        executors._ACTIVE.pop("run", None)
        proc.stdout.close()
    assert not (run_dir / "run.lock").exists()
    (run_dir / "run.lock").write_text(json.dumps({"pid": proc.pid + 1, "host": socket.gethostname()}))
    assert not executors.clear_stale_lock(run_dir, proc.pid) and (run_dir / "run.lock").exists()
