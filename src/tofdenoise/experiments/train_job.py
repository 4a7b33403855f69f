"""One training job of ``tofdenoise train``, safe to run again: the workflow behind the Hydra entry point.

:func:`run` (``cfg`` composed from ``configs/train.yaml``) takes the run folder's lock (``tofdenoise.run_lock``) and

* **returns the records of a finished run** when ``train`` and ``reuse_finished`` are on (the defaults) and the
  folder holds one (``tofdenoise.records.run_finished``, the rule the grids' runner skips runs by): nothing
  is trained or rewritten, and the result is read from its ``metrics.json``. ``reuse_finished=false`` trains it again
  from ``ckpt_path`` (``last``: continue it, e.g. with more epochs; ``null``: start over). The folder's
  ``config.yaml`` must describe the same run (every setting but where files go, the loggers and callbacks,
  ``train``/``test``/``ckpt_path``/``reuse_finished``, the progress bar, the model summary and ``data.cache_dir``);
  another run's folder is refused (:class:`RunConfigMismatchError`, naming the settings that differ), never passed
  off as this run's result;
* **resumes an interrupted run** from ``<run_dir>/checkpoints/last.ckpt`` (``ckpt_path: last``, the default; a
  fresh run when there is none yet);
* otherwise checks the config (valid backbone / noise / loss / data source names, the source's settings), seeds,
  instantiates the
  datamodule, model, callbacks, loggers and trainer (``_convert_="all"``: only plain values reach the classes),
  fits and tests the best checkpoint (lowest ``val/mae_mm``).

Its result holds ``val_mae_mm``: the lowest validation MAE of the run (``val/mae_mm``, what ``best.ckpt`` is chosen
by; ``best_val_mae_mm`` of ``metrics.json``). :func:`validation_objective` returns it alone: the value the Hydra
entry point returns to a sweeper (``hparams_search=recipe``, the Optuna sweeper minimises it).

The run's records (``run_info.json``, ``config.yaml``, ``metrics.json``, ``per_image/<set>.csv``) are written by the
``RunOutputs`` callback (``tofdenoise.callbacks.run_outputs``, ``callbacks.run_outputs`` in the config); wandb's
environment and its ``wandb.finish()`` at the end come from ``tofdenoise.wandb_env``.
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch import seed_everything
from omegaconf import DictConfig, OmegaConf, open_dict

from tofdenoise.callbacks.run_outputs import RunOutputs
from tofdenoise.config import ConfigError, instantiate_node
from tofdenoise.data_modules.datamodule import BLIND_NOISE, blind_percentiles
from tofdenoise.models.registry import BACKBONES, is_trainable
from tofdenoise.output_guard import OutputPathError, refuse_overwrite
from tofdenoise.physics.noise_models import NOISE_MODELS
from tofdenoise.records import (
    BEST_CHECKPOINT,
    FITTED,
    LAST_CHECKPOINT,
    METRICS_NAME,
    RUN_INFO_NAME,
    UNREADABLE,
    VARIANCE_MATCH_WEIGHTS,
    fit_best_checkpoints,
    matched_on_whole_maps,
    read_metrics_json,
    read_run,
    run_finished,
    training_state,
)
from tofdenoise.registry import Registry
from tofdenoise.run_lock import RunLock
from tofdenoise.training.checkpoint_file import check_checkpoint_file, resolve_ckpt_path
from tofdenoise.training.losses import LOSSES
from tofdenoise.training.module import CheckpointMismatchError, checkpoint_backbone
from tofdenoise.wandb_env import finish_wandb, setup_wandb_env, wandb_run_id

__all__ = [
    "RunConfigMismatchError",
    "check_ddp_in_sweep",
    "check_same_run",
    "check_finished_run",
    "check_resumed_run",
    "check_slurm_shape",
    "check_source_config",
    "SAME_RUN_IGNORES",
    "record_calibration",
    "check_test_only",
    "run",
    "validate_config",
    "validation_objective",
]

log = logging.getLogger("tofdenoise.train")

#: the saved config file of a run (written by RunOutputs next to run_info.json)
CONFIG_NAME = "config.yaml"
#: settings that may differ between two attempts of the same run: where files go, what is logged, which steps
#: run (``train``/``test``/``ckpt_path``/``reuse_finished``), console output, the location of the data cache and
#: whether the training steps run compiled (``model.compile``: the same network and optimisation, executed by
#: torch.compile; runs recorded before the key existed stay the same run)
SAME_RUN_IGNORES = (
    "model.compile",
    "paths",
    "ckpt_path",
    "reuse_finished",
    "train",
    "test",
    "logger",
    "callbacks",
    "trainer.default_root_dir",
    "trainer.enable_progress_bar",
    "trainer.enable_model_summary",
    "data.cache_dir",
)


#: the data source settings that were ToFDataModule arguments (``data.num_samples``, ``data.root``, ...) before they
#: moved into ``data.source_kwargs`` (issue 24): an override of the former place is refused with the new one named.
#: Historical: a new source adds nothing here.
FORMER_SOURCE_KEYS = (
    "num_samples",
    "height",
    "width",
    "min_depth_mm",
    "max_depth_mm",
    "max_depth_fraction",
    "hfov_deg",
    "root",
    "list_file",
    "list_files",
    "depth_unit_mm",
    "min_valid_mm",
    "max_valid_mm",
)


class RunConfigMismatchError(ValueError):
    """The run folder holds a finished run of another config (the message names the settings that differ)."""


def _names_or_error(key: str, value: str, registry: Registry) -> None:
    if value not in registry:
        raise ValueError(
            f"config {key}: unknown {registry.kind} {value!r}; valid names: "
            f"{', '.join(sorted(registry.names()))} (choose with `{key.split('.')[0]}=<name>`)"
        )


def validate_config(cfg: DictConfig) -> None:
    """Fail early (before any data or model is built) on unknown names or missing dataset paths."""

    for group in ("backbone", "noise", "loss", "data", "model", "trainer"):
        if group not in cfg or cfg[group] is None:
            raise ValueError(f"config: group {group!r} is missing (configs/train.yaml defaults list)")
    _names_or_error("backbone.name", cfg.backbone.name, BACKBONES)
    if not is_trainable(cfg.backbone.name):
        raise ValueError(
            f"config backbone.name: {cfg.backbone.name!r} is a classical filter without trainable "
            "parameters: nothing to train; tune and evaluate it with `tofdenoise classic` "
            "(docs/models.md#classical-row-joint-bilateral-filter)"
        )
    _names_or_error("noise.name", cfg.noise.name, NOISE_MODELS)
    _names_or_error("loss.name", cfg.loss.name, LOSSES)
    data = cfg.data
    check_source_config(data)
    if data.get("real_dir") not in (None, "") and not Path(str(data.real_dir)).expanduser().exists():
        raise FileNotFoundError(
            f"config data.real_dir: real capture folder {data.real_dir} does not exist "
            "(set data.real_dir=null to skip the real test set)"
        )
    check_slurm_shape(cfg.trainer)
    check_ddp_in_sweep(cfg.trainer)
    for name, node in (cfg.get("logger") or {}).items():
        target = str((node or {}).get("_target_", ""))
        if target.endswith("TensorBoardLogger"):
            try:
                import tensorboard  # noqa: F401
            except ImportError:
                try:
                    import tensorboardX  # noqa: F401
                except ImportError as exc:
                    raise ImportError(
                        f"config logger.{name}: the TensorBoard logger needs the `tensorboard` "
                        "package (pip install tensorboard), or use logger=wandb_offline / csv"
                    ) from exc


def _slurm_tasks() -> int:
    """The task count of a multi-task SLURM step Lightning takes as its environment, else 1."""
    tasks = os.environ.get("SLURM_NTASKS", "")
    if not tasks.isdigit() or os.environ.get("SLURM_JOB_NAME") in ("bash", "interactive"):
        return 1  # Lightning's own rule for its SLURM environment
    return int(tasks)


def _is_ddp(trainer: DictConfig) -> bool:
    return str(trainer.get("strategy") or "").startswith("ddp")


def check_ddp_in_sweep(trainer: DictConfig) -> None:
    """``ConfigError`` for a DDP run of several processes inside a Hydra multirun (``-m``) that Lightning would
    launch itself: it starts the other processes by running the command line again, which here is the whole sweep
    (every job of it, once per rank). Under SLURM (``srun`` starts every process) a sweep's DDP job is fine."""

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return
    if _is_ddp(trainer) and trainer.get("devices", 1) != 1 and _slurm_tasks() <= 1:
        raise ConfigError(
            "trainer.strategy: a DDP run of several processes cannot be a job of a multirun (-m): Lightning starts "
            "its other processes by running the command line again, here the whole sweep; run DDP jobs one at a "
            "time (without -m), or under SLURM with one task per device (docs/cluster.md)"
        )


def check_slurm_shape(trainer: DictConfig) -> None:
    """A DDP run started by SLURM (``srun``, one task per device) needs ``trainer.num_nodes x trainer.devices`` to be
    the job's task count, else its processes wait for ranks that never come; Lightning checks this only for the
    processes it launches itself. ``ConfigError`` naming both settings and the job's ``SLURM_NTASKS`` otherwise."""
    tasks = _slurm_tasks()
    if tasks <= 1 or not _is_ddp(trainer):
        return
    nodes, devices = trainer.get("num_nodes", 1), trainer.get("devices", 1)
    if isinstance(nodes, int) and isinstance(devices, int) and nodes * devices != tasks:
        raise ConfigError(
            f"trainer.num_nodes x trainer.devices = {nodes} x {devices} = {nodes * devices} processes, but this SLURM "
            f"job started {tasks} tasks (SLURM_NTASKS; --nodes x --ntasks-per-node): one task per device; leave "
            "both settings to trainer=ddp's defaults (the job's SLURM_NNODES and SLURM_NTASKS_PER_NODE) or match them"
        )


def _instantiate_group(node: DictConfig | None) -> list[Any]:

    out = []
    for _, sub in (node or {}).items():
        if isinstance(sub, DictConfig) and "_target_" in sub:
            out.append(instantiate(sub, _convert_="all"))
    return out


def _run_outputs(callbacks: list[Any]) -> Any:
    """The run's ``RunOutputs`` callback (its records are what a finished run is made of)."""

    found = [cb for cb in callbacks if isinstance(cb, RunOutputs)]
    if len(found) != 1:
        raise ValueError(
            f"config callbacks: expected one tofdenoise.callbacks.run_outputs.RunOutputs (it writes "
            f"run_info.json, config.yaml and metrics.json), found {len(found)}; keep "
            "callbacks.run_outputs of configs/callbacks/default.yaml"
        )
    return found[0]


def record_calibration(cfg: DictConfig, calib: Any) -> None:
    """Set ``cfg.sensor`` to the calibration the data module resolved, before the config is saved.

    ``data.sensor`` may name a calibration file or a preset (``++data.sensor=mycam/calibration.yaml``) and so
    override the ``sensor`` group. Without this, the saved ``config.yaml`` would show that group's camera, which
    the run never used."""
    with open_dict(cfg):
        cfg.sensor = calib.to_dict()


def run(cfg: DictConfig) -> dict[str, Any]:
    """Train and/or test as configured, or return the records of the finished run in the folder (module
    docstring); returns ``{"run_dir", "best_ckpt", "metrics", "val_mae_mm", "reused"}`` (``reused``: True when
    the folder's finished run was returned and nothing ran). A bad config is one ``ConfigError`` naming the key."""
    try:
        validate_config(cfg)
    except (ValueError, FileNotFoundError, ImportError) as exc:
        raise ConfigError(str(exc)) from None
    run_dir = Path(str(cfg.paths.run_dir)).expanduser().resolve()
    with RunLock(run_dir):  # one writer per run folder (held already when Hydra's callback took it)
        refuse_replacing_inputs(cfg, run_dir)
        return _run_locked(cfg, run_dir)


def refuse_replacing_inputs(cfg: DictConfig, run_dir: Path) -> None:
    """The run's checkpoints never replace the weights it starts from: ``model.init_weights`` inside
    ``<run_dir>/checkpoints`` (fine-tuning from the folder's own ``best.ckpt``) was overwritten by the run's first
    checkpoint (``OutputPathError``, before anything is written)."""
    init = (cfg.get("model") or {}).get("init_weights")
    if init not in (None, ""):
        refuse_overwrite([], [Path(str(init)).expanduser()], "paths.run_dir", output_folders=[run_dir / "checkpoints"])


def _run_locked(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:

    run_dir.mkdir(parents=True, exist_ok=True)
    with open_dict(cfg):
        cfg.paths.run_dir = str(run_dir)
    finished = cfg.get("train", True) and cfg.get("reuse_finished", True) and run_finished(run_dir)
    setup_wandb_env(run_dir)
    if cfg.get("logger") and cfg.logger.get("wandb") is not None and cfg.logger.wandb.get("id") is None:
        with open_dict(cfg):
            cfg.logger.wandb.id = wandb_run_id(run_dir)

    # the checkpoint to resume from (or to test) is checked before anything of the run is written
    resume_ckpt = None
    if cfg.get("train", True) and not finished:
        resume_ckpt = resolve_ckpt_path(cfg.get("ckpt_path"), run_dir)
        if resume_ckpt is not None:
            check_checkpoint_file(resume_ckpt)
            check_resume_backbone(cfg, resume_ckpt)
            check_resumed_run(cfg, run_dir)
    elif not cfg.get("train", True) and cfg.get("test", True):
        check_test_only(cfg, run_dir)
        _test_checkpoint(cfg, None, run_dir)

    seed_everything(int(cfg.seed), workers=True)
    datamodule = instantiate_node(cfg.data, "data")
    record_calibration(cfg, datamodule.calib)
    if finished:
        return _recorded_result(cfg, run_dir)
    model = instantiate_node(cfg.model, "model")
    callbacks = _instantiate_group(cfg.get("callbacks"))
    # run_info.json, config.yaml (written once the checkpoint is restored), metrics.json and the CSVs
    outputs = _run_outputs(callbacks)
    outputs.config_text = OmegaConf.to_yaml(cfg, resolve=True)
    loggers = _instantiate_group(cfg.get("logger"))
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, _convert_="all")
    for lg in trainer.loggers:
        lg.log_hyperparams({"config": OmegaConf.to_container(cfg, resolve=True)})

    result: dict[str, Any] = {"run_dir": str(run_dir), "best_ckpt": None, "metrics": None, "reused": False}
    try:
        if cfg.get("train", True):
            try:
                trainer.fit(model, datamodule=datamodule, ckpt_path=resume_ckpt)
            except SystemExit:
                if trainer.interrupted:  # Lightning's Ctrl-C or SIGTERM: it shut down and exited without a word
                    _say_interrupted(trainer, run_dir)
                    raise SystemExit(EXIT_SIGTERM if trainer.received_sigterm else EXIT_INTERRUPTED) from None
                raise
        if cfg.get("test", True):
            ckpt = _test_checkpoint(cfg, trainer, run_dir)
            result["best_ckpt"] = ckpt
            trainer.test(model, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
            result["metrics"] = outputs.metrics
    finally:
        finish_wandb()
    result["val_mae_mm"] = model.learned_record().get("best_val_mae_mm")
    return result


#: exit status of a training stopped by Ctrl-C (128 + SIGINT, as a shell reports it; tofdenoise denoise's too)
EXIT_INTERRUPTED = 130
#: exit status of a training stopped by SIGTERM (128 + SIGTERM: a scheduler's preemption or time limit, which a
#: requeue wrapper tells apart from a user's Ctrl-C)
EXIT_SIGTERM = 143


def _say_interrupted(trainer: Any, run_dir: Path) -> None:
    """The one line after Ctrl-C or SIGTERM: where the run stopped, and how to go on (Lightning says only that it
    shuts down; the run is not tested and writes no metrics.json, so it never passes for a finished run)."""
    cb = trainer.checkpoint_callback
    last = Path(str(cb.dirpath)) / "last.ckpt" if cb is not None and getattr(cb, "dirpath", None) else None
    resume = (
        f"{last} is kept: run the same command again to resume (ckpt_path=last is the default)"
        if last is not None and last.is_file()
        else "no checkpoint was written yet: start it again"
    )
    how = "stopped by SIGTERM" if trainer.received_sigterm else "interrupted (Ctrl-C)"
    print(
        f"tofdenoise train: {how} at step {trainer.global_step}, epoch {trainer.current_epoch}; "
        f"not tested, no metrics.json; {resume}",
        file=sys.stderr,
    )


def check_source_config(data: DictConfig) -> None:
    """``data.source`` names a registered source and ``data.source_kwargs`` holds only its settings (the source's
    ``config_keys()``; a dataset folder is checked by the source itself when the datamodule is built). A source
    setting at the top of ``data`` (``++data.num_samples=10``, the former place) is an error saying where it goes."""
    from tofdenoise.data_modules.sources import DATA_SOURCES, check_source_kwargs

    source = data.get("source", "procedural")
    _names_or_error("data.source", source, DATA_SOURCES)
    settings = data.get("source_kwargs")
    try:
        check_source_kwargs(source, OmegaConf.to_container(settings, resolve=True) if settings is not None else None)
    except ValueError as exc:
        raise ValueError(f"config {exc}") from None
    for key in DATA_SOURCES.get(source).config_keys():
        if key in data:
            raise ValueError(
                f"config data.{key}: a setting of the {source} source, set it as data.source_kwargs.{key} "
                "(e.g. `make train ARGS='data.source_kwargs.num_samples=100'`; docs/data.md)"
            )


def _comparable(cfg_yaml: str) -> dict[str, Any]:
    """The settings of a resolved config (its YAML text) that decide a run's result: ``SAME_RUN_IGNORES`` left
    out, flattened to ``{"model.optim.lr": 0.001, ...}``. A config recorded before the settings groups
    (``data.source_kwargs``, ``model.optim``, ...) is another config: its records stay readable, but its folder is not
    continued by this code."""
    flat: dict[str, Any] = {}

    def walk(node: Any, prefix: str) -> None:
        if prefix in SAME_RUN_IGNORES:
            return
        if isinstance(node, dict) and node:
            for key, value in node.items():
                walk(value, f"{prefix}.{key}" if prefix else str(key))
        else:
            flat[prefix] = node

    walk(OmegaConf.to_container(OmegaConf.create(cfg_yaml), resolve=False), "")
    return flat


def check_same_run(cfg: DictConfig, run_dir: Path, resuming: bool = False, testing: bool = False) -> None:
    """Raise :class:`RunConfigMismatchError` when ``<run_dir>/config.yaml`` (the config of the run recorded there)
    differs from ``cfg`` in a setting outside ``SAME_RUN_IGNORES``; a folder without ``config.yaml`` passes.
    ``resuming``: ``cfg`` would resume the folder's checkpoint (the message says how to start afresh instead);
    ``testing``: ``cfg`` would test the folder's run (``train=false``)."""
    saved_path = run_dir / CONFIG_NAME
    try:
        saved_text = saved_path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return
    saved, now = _comparable(saved_text), _comparable(OmegaConf.to_yaml(cfg, resolve=True))
    info, _ = read_run(run_dir)
    if not testing and matched_on_whole_maps(info):
        # same config, another training noise: the baseline's variance was matched on whole maps (1.17-1.21x hetero's
        # in the training crops); reused or resumed, the folder's record would pass as this code's match
        raise RunConfigMismatchError(
            f"run folder {run_dir} holds a run whose {info['prepared_data']['noise']} noise was variance-matched on "
            f"whole maps ({RUN_INFO_NAME}: noise_record without weights: {VARIANCE_MATCH_WEIGHTS}), an earlier "
            "protocol than this code's match over the training crops' coverage; train it again from the start "
            "(reuse_finished=false ckpt_path=null, its checkpoints and records replaced) or choose another folder"
        )
    differ = sorted(k for k in saved.keys() | now.keys() if saved.get(k, "<unset>") != now.get(k, "<unset>"))
    if differ:
        shown = "; ".join(f"{k}: {saved.get(k, '<unset>')!r} there, {now.get(k, '<unset>')!r} now" for k in differ[:6])
        more = f" (and {len(differ) - 6} more)" if len(differ) > 6 else ""
        other = "another folder (paths.run_dir, or in a sweep run_name=... / hydra.sweep.subdir=... so that each job "
        other += "gets its own)"
        if testing:
            raise RunConfigMismatchError(
                f"run folder {run_dir} holds a training run of another config ({saved_path}), whose records a "
                f"test with this config (train=false) would write as that run's: {shown}{more}; test it with its own "
                f"config, or give this test {other}"
            )
        if resuming:
            state = "a finished" if run_finished(run_dir) else "an interrupted"
            raise RunConfigMismatchError(
                f"run folder {run_dir} holds {state} run of another config ({saved_path}), which this command would "
                f"resume from its checkpoint ({LAST_CHECKPOINT}) and record as this config's: {shown}{more}; resume "
                f"it with its own config, choose {other}, or set ckpt_path=null (with reuse_finished=false for a "
                "finished run) to train this folder again from the start with this config, its checkpoints and "
                "records replaced"
            )
        raise RunConfigMismatchError(
            f"run folder {run_dir} holds a finished run of another config ({saved_path}): {shown}{more}; "
            f"choose {other}, or set reuse_finished=false ckpt_path=null to train that folder again from the start "
            "with this config, its checkpoints and records replaced"
        )


def check_before_writing(cfg: DictConfig, run_dir: str | Path) -> None:
    """What ``hydra.callbacks.run_lock.before_job`` (``configs/train.yaml``) checks with the run folder's lock held,
    before Hydra writes ``.hydra/`` or its log there: the noise settings (:func:`check_noise`), a checkpoint to
    resume (its backbone, and the folder's recorded config: :func:`check_resumed_run`), a test-only run in a folder
    of a training run (:func:`check_test_only`), then a finished run in the folder
    (:func:`check_finished_run`). A ``ValueError`` is one line and exit status 2, the folder left as it was."""
    check_noise(cfg)
    run_dir = Path(str(run_dir)).expanduser().resolve()
    finished = cfg.get("train", True) and cfg.get("reuse_finished", True) and run_finished(run_dir)
    if cfg.get("train", True) and not finished:
        given = cfg.get("ckpt_path")
        resume = None
        if given == "last":
            resume = run_dir / LAST_CHECKPOINT if (run_dir / LAST_CHECKPOINT).is_file() else None
        elif given not in (None, "", "null"):
            resume = Path(str(given)).expanduser()
        if resume is not None:
            check_checkpoint_file(resume)  # a broken file is named first: the way out differs
            check_resume_backbone(cfg, resume)
            check_resumed_run(cfg, run_dir)
    elif not cfg.get("train", True) and cfg.get("test", True):
        check_test_only(cfg, run_dir)
    check_finished_run(cfg, run_dir)


def check_resume_backbone(cfg: DictConfig, ckpt: str | Path) -> None:
    """A checkpoint to resume from (``ckpt_path``) that was written for another backbone than ``model.backbone`` is
    a ``CheckpointMismatchError`` naming the file and both backbones, before the data are prepared (it was a
    traceback from Lightning's restore once they were). The full architecture (``backbone_kwargs``, conditioning)
    is still compared when the checkpoint is restored. A file without hyper-parameters is left to that check."""
    theirs = checkpoint_backbone(str(ckpt))
    mine = (cfg.get("model") or {}).get("backbone")
    if theirs is not None and mine is not None and str(mine) != theirs:
        raise CheckpointMismatchError(
            f"ckpt_path {ckpt}: the checkpoint was written for backbone {theirs!r}, this run builds {str(mine)!r}; "
            f"select backbone={theirs} to resume it, or another checkpoint"
        )


def _config_calibration(data):
    """The calibration the data module resolves from the composed ``data`` node (``sensor``, ``signal_route``,
    ``signal_dynamic_range``); a ``ConfigError`` naming ``data`` when it cannot be read."""
    from tofdenoise.data_modules.datamodule import data_calibration

    sensor = data.get("sensor")
    if isinstance(sensor, DictConfig):
        sensor = OmegaConf.to_container(sensor, resolve=True)
    try:
        return data_calibration(sensor, data.get("signal_route", "linear"), data.get("signal_dynamic_range"))
    except (ValueError, FileNotFoundError) as exc:
        raise ConfigError(f"data: {exc}") from None


def check_noise(cfg: DictConfig) -> None:
    """The training noise model (``data.noise`` / ``data.noise_kwargs``, from the ``noise`` group) is built once, as
    the data module will build it: an unknown model, an unknown keyword or a value out of range
    (``noise.kwargs.sigma_mm=-5``) is a ``ConfigError`` naming ``noise.kwargs`` and the setting, before anything is
    written (it was a traceback after the trainer started). A ``range`` model without ``alpha_mm`` takes its
    coefficients from the calibration, which is read only then."""

    data = cfg.get("data") or {}
    name = str(data.get("noise", "hetero")).lower()
    kwargs = data.get("noise_kwargs") or {}
    if isinstance(kwargs, DictConfig):
        kwargs = OmegaConf.to_container(kwargs, resolve=True)
    if not isinstance(kwargs, dict):
        raise ConfigError(f"noise.kwargs: expected a mapping of keyword arguments, got {kwargs!r}")
    calib = _config_calibration(data) if name == "range" and kwargs.get("alpha_mm") is None else None
    if name == BLIND_NOISE:  # its sigma range comes from the training split (the data module reads it)
        try:
            blind_percentiles(kwargs)
        except ValueError as exc:
            raise ConfigError(f"noise.kwargs of noise={name}: {exc}") from None
        kwargs = {k: v for k, v in kwargs.items() if k != "percentiles"}
        kwargs.setdefault("sigma_lo_mm", kwargs.get("sigma_hi_mm", 1.0))
        kwargs.setdefault("sigma_hi_mm", kwargs["sigma_lo_mm"])
    try:
        NOISE_MODELS.build(name, calib=calib, **kwargs)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"noise.kwargs of noise={name}: {exc}") from None


def check_finished_run(cfg: DictConfig, run_dir: str | Path) -> None:
    """The same-run check of a finished run folder (:func:`check_same_run`), made before Hydra writes anything there.

    Hydra writes ``.hydra/config.yaml``, ``hydra.yaml``, ``overrides.yaml`` and starts its log in the run folder
    before the run code starts, so a run refused by the check in :func:`run` had already rewritten the finished
    run's Hydra record with the refused settings (issue 41). The Hydra callback (``hydra.callbacks.run_lock.
    before_job``, :class:`tofdenoise.run_lock.HydraRunLock`) calls this with the composed config (no ``hydra``
    node) once it holds the folder's lock: a folder that :func:`run` would return as a finished run must hold a
    run of this config (``RunConfigMismatchError``), else nothing is written. The ``sensor`` compared is the
    calibration the data module resolves (:func:`record_calibration`), as in :func:`run`."""

    run_dir = Path(str(run_dir)).expanduser().resolve()
    if not (cfg.get("train", True) and cfg.get("reuse_finished", True) and run_finished(run_dir)):
        return
    check_same_run(_with_calibration(cfg, run_dir), run_dir)


def _with_calibration(cfg: DictConfig, run_dir: Path) -> DictConfig:
    """``cfg`` as the run records it in ``config.yaml``: its folder, and the calibration the data module resolves
    (:func:`record_calibration`), so that it compares with a recorded config."""
    calib = _config_calibration(cfg.get("data") or {})
    cfg = cfg.copy()
    with open_dict(cfg):
        cfg.paths.run_dir = str(run_dir)
    record_calibration(cfg, calib)
    return cfg


def check_resumed_run(cfg: DictConfig, run_dir: str | Path) -> None:
    """The same-run check of a resume: a checkpoint resumed in a folder whose ``config.yaml`` records another config
    is a :class:`RunConfigMismatchError` naming the settings. Resumed, the folder's optimiser and schedule came
    back with the earlier settings, the new ones took effect part-way (another loss, noise or crop size for the
    remaining steps; a learning rate never, the schedule being restored; ``model.init_weights`` not read) and the
    records named the new config as the whole run's."""
    run_dir = Path(str(run_dir)).expanduser().resolve()
    check_same_run(_with_calibration(cfg, run_dir), run_dir, resuming=True)


def check_test_only(cfg: DictConfig, run_dir: str | Path) -> None:
    """A test-only run (``train=false``) in a folder that holds a training run tests that run: its own ``best.ckpt``
    (``ckpt_path`` unset, ``last`` or that file) with the config it was trained with, once its fit has ended; its
    records keep the fit's fields (``RunOutputs``). Another checkpoint, or a fit that has not ended (resume it
    first), is an ``OutputPathError``; another config a :class:`RunConfigMismatchError`. Their scores were recorded
    as the training run's (``run_info.json`` rewritten with 0 steps and no training cost, another test set's
    ``metrics.json``; an interrupted fit marked finished), and a report listed one network as two runs. A folder
    without a training run takes any test."""
    run_dir = Path(str(run_dir)).expanduser().resolve()
    state = training_state(run_dir)
    if state is None:
        return
    own = "give the test its own folder (paths.run_dir=...), or score the run without writing there: tofdenoise "
    own += f"evaluate --run {run_dir} --out scores.json"
    if state != FITTED:
        why = "whose run_info.json cannot be read" if state == UNREADABLE else "whose fit has not ended (resume it)"
        raise OutputPathError(
            f"run folder {run_dir} holds a training run {why}, which a test-only run would mark as "
            f"tested and finished: {own}"
        )
    given = cfg.get("ckpt_path")
    if given not in (None, "", "null", "last"):
        tested = Path(str(given)).expanduser().resolve()
        if tested not in fit_best_checkpoints(run_dir):
            raise OutputPathError(
                f"run folder {run_dir} holds a training run, whose records a test of another checkpoint ({tested}) "
                f"would replace: {own}"
            )
    check_same_run(_with_calibration(cfg, run_dir), run_dir, testing=True)


def _recorded_result(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """The result of the finished run in ``run_dir`` (same config, checked), read from its records."""
    check_same_run(cfg, run_dir)
    info, _ = read_run(run_dir)
    metrics = read_metrics_json(run_dir / METRICS_NAME)
    best = metrics.get("best_val_mae_mm")
    val = None if best is None else float(best)
    print(
        f"[{cfg.get('run_name', run_dir.name)}] finished before ({RUN_INFO_NAME} finished {info.get('finished')}): "
        f"nothing trained, recorded metrics from {run_dir / METRICS_NAME} | best val/mae_mm "
        + ("n/a" if val is None else f"{val:.3f}"),
        flush=True,
    )
    return {
        "run_dir": str(run_dir),
        "best_ckpt": info.get("best_ckpt"),
        "metrics": metrics,
        "val_mae_mm": val,
        "reused": True,
    }


def _test_checkpoint(cfg: DictConfig, trainer: Any, run_dir: Path) -> str | None:
    """Best checkpoint of this fit; when not training, ``ckpt_path`` or ``<run_dir>/checkpoints/best.ckpt``."""
    if cfg.get("train", True):
        cb = trainer.checkpoint_callback
        best = getattr(cb, "best_model_path", "") if cb is not None else ""
        if best:
            return best
        # fast_dev_run (checkpointing disabled) or no validation: test the weights in memory
        log.warning("no best checkpoint was written (fast_dev_run or no validation): testing current weights")
        return None
    given = cfg.get("ckpt_path")
    if given not in (None, "", "last"):
        return str(check_checkpoint_file(resolve_ckpt_path(given, run_dir)))
    best = run_dir / BEST_CHECKPOINT
    if not best.is_file():
        raise FileNotFoundError(
            f"train=false: no checkpoint to test; {best} does not exist (set ckpt_path=/path/to/model.ckpt)"
        )
    return str(check_checkpoint_file(best))


def validation_objective(cfg: DictConfig) -> float | None:
    """:func:`run`, returning the run's lowest validation MAE in mm (``val/mae_mm``, the monitored metric) as a
    float: what the Hydra entry point gives a sweeper to minimise; ``None`` when no validation ran."""
    return run(cfg)["val_mae_mm"]
