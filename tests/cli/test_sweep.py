"""Every training job is safe to run again (issue 25): a finished run folder returns its records, a sweep's jobs get
stable folders shared with the grids' runner, the entry function returns the validation MAE, an Optuna search of
the recipe, and trainer=ddp across nodes under SLURM (composed and instantiated, not run)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from tofdenoise.cli.train import main
from tofdenoise.config import ConfigError, compose_config
from tofdenoise.experiments.runner import RunSpec, run_all
from tofdenoise.experiments.train_job import RunConfigMismatchError, run, validate_config
from tofdenoise.records import read_metrics_json
from tofdenoise.run_lock import RunLock

REPO = Path(__file__).resolve().parents[2]


def _stamps(run_dir: Path) -> dict[str, int]:
    """mtime (ns) of every checkpoint and record of a run folder: what a training would rewrite."""
    names = ["metrics.json", "run_info.json", "config.yaml", "per_image/synthetic.csv"]
    files = [run_dir / n for n in names] + sorted((run_dir / "checkpoints").glob("*.ckpt"))
    return {str(p.relative_to(run_dir)): p.stat().st_mtime_ns for p in files}


def _train_cli(args: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "WANDB_MODE": "offline"}
    return subprocess.run(
        [sys.executable, "-m", "tofdenoise.cli.train", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=env,
        timeout=600,
    )


def _sweep_args(tiny, sweep_dir: Path, cache: Path) -> list[str]:
    """The tiny run's overrides for a multirun: the jobs' folders come from hydra.sweep.dir / subdir."""
    return [a for a in tiny("X", cache) if not a.startswith("paths.run_dir=")] + [
        f"hydra.sweep.dir={sweep_dir}",
        "logger=csv",
    ]


def test_a_finished_run_returns_its_recorded_val_mae_and_trains_nothing(tmp_path, data_cache, tiny, capsys):
    args = tiny(tmp_path / "run", data_cache) + ["logger=csv"]
    first = run(compose_config(args))
    assert first["reused"] is False
    recorded = read_metrics_json(tmp_path / "run" / "metrics.json")
    assert first["val_mae_mm"] == recorded["best_val_mae_mm"] and recorded["trained_steps"] == 6
    before = _stamps(tmp_path / "run")
    capsys.readouterr()

    # the function Hydra calls: it returns the run's lowest validation MAE as a float, here from the records
    value = main.entry(compose_config(args))
    assert type(value) is float and value == recorded["best_val_mae_mm"]
    out = capsys.readouterr().out
    assert "finished before" in out and "nothing trained" in out
    assert _stamps(tmp_path / "run") == before  # no checkpoint or record written again

    # the same folder with another setting is another run: refused, naming the setting, nothing written
    with pytest.raises(RunConfigMismatchError, match=r"model\.optim\.lr: 0\.0002 there, 0\.001 now"):
        run(compose_config(args + ["model.optim.lr=1e-3"]))
    assert _stamps(tmp_path / "run") == before
    # where files go, the loggers and the progress bar are not part of a run's identity
    again = run(compose_config(args + ["trainer.enable_progress_bar=true", "logger=none"]))
    assert again["reused"] is True and again["val_mae_mm"] == value


def test_a_multirun_twice_trains_each_run_once_in_folders_the_runner_shares(tmp_path, data_cache, tiny):
    sweep = tmp_path / "sweep"
    args = ["-m", *_sweep_args(tiny, sweep, data_cache), "seed=0,1"]
    proc = _train_cli(args)
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = ["unet-hetero-full-s0", "unet-hetero-full-s1"]
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == names  # stable, short names
    assert proc.stdout.count("finished before") == 0
    for name in names:
        assert json.loads((sweep / name / "run_info.json").read_text())["seed"] == int(name[-1])
    before = {n: _stamps(sweep / n) for n in names}
    metrics = {n: (sweep / n / "metrics.json").read_bytes() for n in names}

    again = _train_cli(args)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stdout.count("finished before") == 2 and "Restoring states" not in again.stdout + again.stderr
    assert {n: _stamps(sweep / n) for n in names} == before  # nothing trained, tested or rewritten
    assert {n: (sweep / n / "metrics.json").read_bytes() for n in names} == metrics

    # the grids' runner (tofdenoise reproduce, tofdenoise grid) names its runs the same way: it skips them
    specs = [RunSpec(n, ("backbone=unet", f"seed={n[-1]}")) for n in names]
    outcomes = run_all(specs, sweep, echo=False)
    assert [o.status for o in outcomes] == ["skipped", "skipped"]


def test_two_jobs_of_one_folder_refuse_the_sweep_before_any_job_trains(tmp_path, data_cache, tiny):
    """A sweep over a setting its folder names do not vary (the learning rate here): the first job trained, the
    second was refused afterwards as another config in that folder. Now refused up front, both jobs named."""
    sweep = tmp_path / "sweep"
    proc = _train_cli(["-m", *_sweep_args(tiny, sweep, data_cache), "model.optim.lr=1e-3,2e-3"])
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "multirun jobs #0 and #1 would both write" in proc.stderr and "Traceback" not in proc.stderr
    assert not sweep.exists() or not any(p.is_dir() for p in sweep.iterdir())


def test_a_joblib_multirun_trains_each_run_once_in_its_worker_and_keeps_the_run_locks(tmp_path, data_cache, tiny):
    """Hydra's joblib launcher (the ``launchers`` extra) runs the jobs in loky worker processes: the same stable
    folders as the basic launcher, a second identical sweep trains nothing, and a job whose folder another process
    holds is refused in one line (the run lock is taken in the worker), exit status 2, nothing written there."""
    sweep = tmp_path / "sweep"
    launcher = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]
    args = ["-m", *_sweep_args(tiny, sweep, data_cache), "seed=0,1", *launcher]
    proc = _train_cli(args)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Joblib.Parallel(n_jobs=2,backend=loky" in proc.stdout + proc.stderr  # the jobs ran in worker processes
    names = ["unet-hetero-full-s0", "unet-hetero-full-s1"]
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == names
    assert (proc.stdout + proc.stderr).count("finished before") == 0
    for name in names:
        assert json.loads((sweep / name / "run_info.json").read_text())["seed"] == int(name[-1])
        assert read_metrics_json(sweep / name / "metrics.json")["trained_steps"] == 6
        assert not (sweep / name / "run.lock").exists()  # each worker released its folder
    before = {n: _stamps(sweep / n) for n in names}

    again = _train_cli(args)
    assert again.returncode == 0, again.stderr[-3000:]
    assert (again.stdout + again.stderr).count("finished before") == 2
    assert {n: _stamps(sweep / n) for n in names} == before  # nothing trained, tested or rewritten

    # a folder another process writes (this one holds its lock): the worker's job is refused in one line
    held = sweep / "unet-hetero-full-s2"
    lock = RunLock(held).acquire()
    try:
        locked = _train_cli(["-m", *_sweep_args(tiny, sweep, data_cache), "seed=2", *launcher])
    finally:
        lock.release()
    assert locked.returncode == 2, locked.stderr[-3000:]
    line = locked.stderr.strip().splitlines()[-1]
    assert line.startswith(f"tofdenoise train: error: run folder {held} is locked by pid {os.getpid()}")
    assert "Traceback" not in locked.stderr
    assert not (held / "checkpoints").exists() and not (held / "metrics.json").exists()


def test_the_submitit_launchers_compose_with_the_train_config(tmp_path):
    """hydra/launcher=submitit_local and submitit_slurm (the ``launchers`` extra) compose with configs/train.yaml,
    also with the Optuna search, and their launcher is built with its logs under the sweep folder (no SLURM run)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.utils import instantiate

    from tofdenoise.config import config_dir

    sweep = tmp_path / "sweep"
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        for name, cls in [("submitit_local", "LocalLauncher"), ("submitit_slurm", "SlurmLauncher")]:
            cfg = compose(
                "train",
                [f"hydra/launcher={name}", f"paths.sweep_dir={sweep}", "hydra.launcher.timeout_min=30"],
                return_hydra_config=True,
            )
            assert cfg.hydra.launcher._target_ == f"hydra_plugins.hydra_submitit_launcher.submitit_launcher.{cls}"
            launcher = instantiate(cfg.hydra.launcher)
            assert type(launcher).__name__ == cls
            assert launcher.params["submitit_folder"] == f"{sweep}/.submitit/%j"
            assert launcher.params["timeout_min"] == 30
        cfg = compose("train", ["hydra/launcher=joblib", "hparams_search=recipe"], return_hydra_config=True)
        assert cfg.hydra.sweeper._target_.endswith("OptunaSweeper")
        assert cfg.hydra.launcher._target_.endswith("JoblibLauncher")
    GlobalHydra.instance().clear()


def test_an_optuna_search_of_the_recipe_returns_its_best_validation_mae(tmp_path, data_cache, tiny):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="the sweep extra (pip install -e '.[sweep]')")
    sweep = tmp_path / "search"
    search = ["-m", "hparams_search=recipe", "hydra.sweeper.n_trials=3"]
    proc = _train_cli([*search, *_sweep_args(tiny, sweep, data_cache)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = OmegaConf.to_container(OmegaConf.load(sweep / "optimization_results.yaml"))
    assert result["name"] == "optuna" and isinstance(result["best_value"], float)
    trials = {p.name: read_metrics_json(p / "metrics.json") for p in sweep.iterdir() if p.is_dir()}
    assert 1 <= len(trials) <= 3  # a repeated combination of the discrete values is its finished folder
    values = {name: m["best_val_mae_mm"] for name, m in trials.items()}
    # the best value is a trial's recorded validation MAE: the lowest one (direction minimize)
    assert result["best_value"] == min(values.values())
    best = result["best_params"]
    best_dir = min(values, key=values.get)
    assert best_dir == (
        f"unet-hetero-full-lr{best['model.optim.lr']}-wu{best['model.optim.warmup_steps']}-wd{best['++model.optim.weight_decay']}-s0"
    )
    saved = OmegaConf.load(sweep / best_dir / "config.yaml")
    assert saved.model.optim.lr == best["model.optim.lr"]
    assert saved.model.optim.weight_decay == best["++model.optim.weight_decay"]


def test_hparams_search_without_the_sweeper_installed_is_one_line_naming_the_extra(monkeypatch, capsys):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name.endswith("hydra_optuna_sweeper") else real(name, *a)
    )
    monkeypatch.setattr(sys, "argv", ["tofdenoise train", "-m", "hparams_search=recipe"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("tofdenoise train: error: hparams_search=recipe needs the Optuna sweeper")
    assert ".[sweep]" in err


SLURM_TWO_NODES = {
    "SLURM_NTASKS": "8",
    "SLURM_NTASKS_PER_NODE": "4",
    "SLURM_NNODES": "2",
    "SLURM_PROCID": "5",
    "SLURM_LOCALID": "1",
    "SLURM_NODEID": "1",
    "SLURM_JOB_NAME": "ddp",
    "SLURM_JOB_ID": "4242",
    "SLURM_NODELIST": "gpu[07-08]",
}
DDP_ON_CPU = ["trainer=ddp", "trainer.accelerator=cpu", "trainer.precision=32-true", "trainer.sync_batchnorm=false"]


def _clear_dist_env(monkeypatch):
    """No SLURM or DDP variables; the process-wide rank Lightning sets when a DDP trainer is built (its
    rank_zero_only.rank: else every later test of this process would log as rank 5) is restored afterwards."""
    from lightning.pytorch.utilities.rank_zero import rank_zero_only
    from lightning_utilities.core.rank_zero import rank_zero_only as utils_rank_zero_only

    dist = ["MASTER_ADDR", "MASTER_PORT", "RANK", "LOCAL_RANK", "NODE_RANK", "WORLD_SIZE"]
    for key in [k for k in os.environ if k.startswith("SLURM_")] + dist:
        monkeypatch.setenv(key, "")  # recorded (set or not) so that what Lightning sets later is undone
        monkeypatch.delenv(key)
    for holder in (rank_zero_only, utils_rank_zero_only):
        monkeypatch.setattr(holder, "rank", getattr(holder, "rank", 0))


def test_trainer_ddp_takes_nodes_and_tasks_from_the_config_or_the_slurm_job(tmp_path, monkeypatch):
    from hydra.utils import instantiate
    from lightning.fabric.plugins.environments import SLURMEnvironment

    from tofdenoise.run_lock import is_worker_rank

    _clear_dist_env(monkeypatch)
    overrides = [*DDP_ON_CPU, f"paths.run_dir={tmp_path}"]
    # outside SLURM: one node, two devices, or what the config says
    cfg = compose_config(overrides)
    assert (cfg.trainer.num_nodes, cfg.trainer.devices) == (1, 2)
    assert compose_config([*overrides, "trainer.num_nodes=3"]).trainer.num_nodes == 3

    # task 5 of a 2 nodes x 4 tasks SLURM job: the job's shape, rank from SLURM_PROCID, master = first node
    for key, value in SLURM_TWO_NODES.items():
        monkeypatch.setenv(key, value)
    cfg = compose_config(overrides)
    assert (cfg.trainer.num_nodes, cfg.trainer.devices, cfg.trainer.strategy) == (2, 4, "ddp")
    trainer = instantiate(cfg.trainer, _convert_="all")
    env = trainer.strategy.cluster_environment
    assert isinstance(env, SLURMEnvironment)
    assert (trainer.num_nodes, trainer.num_devices, trainer.world_size) == (2, 4, 8)
    assert (trainer.global_rank, trainer.local_rank, trainer.node_rank) == (5, 1, 1)
    assert env.main_address == "gpu07" and not trainer.is_global_zero
    assert is_worker_rank()  # task 5 writes into the folder task 0 holds the lock of
    monkeypatch.setenv("SLURM_PROCID", "0")
    assert not is_worker_rank()
    validate_config(cfg)
    # a config that contradicts the job (8 tasks) is refused before anything starts, naming the settings
    with pytest.raises(ConfigError, match=r"trainer\.num_nodes x trainer\.devices = 3 x 4 = 12 .* 8 tasks"):
        validate_config(compose_config([*overrides, "trainer.num_nodes=3"]))


def test_a_ddp_job_lightning_would_launch_inside_a_multirun_is_refused(tmp_path, data_cache, tiny, monkeypatch):
    """Lightning starts a DDP run's rank 1 by running the command line again: in a multirun, the whole sweep."""
    _clear_dist_env(monkeypatch)
    sweep = tmp_path / "sweep"
    proc = _train_cli(["-m", *_sweep_args(tiny, sweep, data_cache), *DDP_ON_CPU, "trainer.devices=2", "seed=0"])
    assert proc.returncode == 2, proc.stderr[-2000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("tofdenoise train: error: trainer.strategy: a DDP run of several processes cannot be")
    assert not list(sweep.glob("*/checkpoints"))
