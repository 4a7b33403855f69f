"""``tofdenoise-train``: the Hydra entry point (``make train``).

Flow: check the config (valid backbone / noise / loss names, dataset paths) -> ``seed_everything`` ->
instantiate datamodule, model, callbacks, loggers and trainer (``_convert_="all"``: only plain values reach
the classes) -> ``trainer.fit`` (``ckpt_path=last`` resumes ``<run_dir>/checkpoints/last.ckpt``) ->
``trainer.test`` with the best checkpoint (lowest ``val/mae_mm``). The run folder has one writer at a time
(``tofdenoise.run_lock``: a second run of the same folder is refused before it touches it, exit status 2).
The run's records (``run_info.json``,
``config.yaml``, ``metrics.json``, ``per_image/<set>.csv``) are written by the ``RunOutputs`` callback
(``tofdenoise.callbacks.run_outputs``, ``callbacks.run_outputs`` in the config); wandb's environment and its
``wandb.finish()`` at the end come from ``tofdenoise.wandb_env``.

Examples::

    tofdenoise-train                                   # default small CPU run on built-in scenes
    tofdenoise-train experiment=smoke                  # < 2 minutes
    tofdenoise-train backbone=unet noise=range loss=l1 trainer.max_epochs=5
    tofdenoise-train experiment=paper data.root=/data/ToF-FlyingThings3D
    tofdenoise-train paths.run_dir=runs/a ckpt_path=last   # resume a killed run
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from tofdenoise.atomic import WriteError
from tofdenoise.callbacks.checkpointing import CheckpointWriteError
from tofdenoise.cli.checkpoint_check import CheckpointFileError, check_checkpoint_file, resolve_ckpt_path
from tofdenoise.config import ConfigError, hydra_console_script, instantiate_node
from tofdenoise.output_guard import OutputPathError, refuse_overwrite
from tofdenoise.registry import Registry
from tofdenoise.run_lock import RunLock, RunLockedError
from tofdenoise.training.init_weights import InitWeightsError
from tofdenoise.wandb_env import finish_wandb, setup_wandb_env, wandb_run_id

__all__ = ["main", "run", "validate_config"]

log = logging.getLogger("tofdenoise.train")


def _names_or_error(key: str, value: str, registry: Registry) -> None:
    if value not in registry:
        raise ValueError(
            f"config {key}: unknown {registry.kind} {value!r}; valid names: "
            f"{', '.join(sorted(registry.names()))} (choose with `{key.split('.')[0]}=<name>`)"
        )


def validate_config(cfg: DictConfig) -> None:
    """Fail early (before any data or model is built) on unknown names or missing dataset paths."""
    from tofdenoise.models.registry import BACKBONES, is_trainable
    from tofdenoise.physics.noise_models import NOISE_MODELS
    from tofdenoise.training.losses import LOSSES

    for group in ("backbone", "noise", "loss", "data", "model", "trainer"):
        if group not in cfg or cfg[group] is None:
            raise ValueError(f"config: group {group!r} is missing (configs/train.yaml defaults list)")
    _names_or_error("backbone.name", cfg.backbone.name, BACKBONES)
    if not is_trainable(cfg.backbone.name):
        raise ValueError(
            f"config backbone.name: {cfg.backbone.name!r} is a classical filter without trainable "
            "parameters: nothing to train; tune and evaluate it with `tofdenoise-classic` "
            "(docs/models.md#classical-row-joint-bilateral-filter)"
        )
    _names_or_error("noise.name", cfg.noise.name, NOISE_MODELS)
    _names_or_error("loss.name", cfg.loss.name, LOSSES)
    data = cfg.data
    source = data.get("source", "procedural")
    if source not in (None, "procedural"):
        root = data.get("root")
        if root in (None, "", "???"):
            raise ValueError(
                f"config data.root: data source {source!r} needs its dataset folder; set "
                f"data.root=/path/to/dataset (e.g. `make train DATA={source} "
                f"ARGS='data.root=/data/...'`)"
            )
        if not Path(str(root)).expanduser().exists():
            raise FileNotFoundError(
                f"config data.root: dataset folder {root} (data source {source!r}) does not "
                f"exist; set data.root to the dataset folder"
            )
    if data.get("real_dir") not in (None, "") and not Path(str(data.real_dir)).expanduser().exists():
        raise FileNotFoundError(
            f"config data.real_dir: real capture folder {data.real_dir} does not exist "
            "(set data.real_dir=null to skip the real test set)"
        )
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


def _instantiate_group(node: DictConfig | None) -> list[Any]:
    from hydra.utils import instantiate

    out = []
    for _, sub in (node or {}).items():
        if isinstance(sub, DictConfig) and "_target_" in sub:
            out.append(instantiate(sub, _convert_="all"))
    return out


def _run_outputs(callbacks: list[Any]) -> Any:
    """The run's ``RunOutputs`` callback (its records are what a finished run is made of)."""
    from tofdenoise.callbacks.run_outputs import RunOutputs

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
    """Train and/or test as configured; returns ``{"run_dir", "best_ckpt", "metrics"}``."""
    validate_config(cfg)
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
    from hydra.utils import instantiate
    from lightning.pytorch import seed_everything

    run_dir.mkdir(parents=True, exist_ok=True)
    with open_dict(cfg):
        cfg.paths.run_dir = str(run_dir)
    setup_wandb_env(run_dir)
    if cfg.get("logger") and cfg.logger.get("wandb") is not None and cfg.logger.wandb.get("id") is None:
        with open_dict(cfg):
            cfg.logger.wandb.id = wandb_run_id(run_dir)

    # the checkpoint to resume from (or to test) is checked before anything of the run is written
    resume_ckpt = resolve_ckpt_path(cfg.get("ckpt_path"), run_dir) if cfg.get("train", True) else None
    if resume_ckpt is not None:
        check_checkpoint_file(resume_ckpt)
    elif cfg.get("test", True) and not cfg.get("train", True):
        _test_checkpoint(cfg, None, run_dir)

    seed_everything(int(cfg.seed), workers=True)
    datamodule = instantiate_node(cfg.data, "data")
    record_calibration(cfg, datamodule.calib)
    model = instantiate(cfg.model, _convert_="all")
    callbacks = _instantiate_group(cfg.get("callbacks"))
    # run_info.json, config.yaml (written once the checkpoint is restored), metrics.json and the CSVs
    outputs = _run_outputs(callbacks)
    outputs.config_text = OmegaConf.to_yaml(cfg, resolve=True)
    loggers = _instantiate_group(cfg.get("logger"))
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, _convert_="all")
    for lg in trainer.loggers:
        lg.log_hyperparams({"config": OmegaConf.to_container(cfg, resolve=True)})

    result: dict[str, Any] = {"run_dir": str(run_dir), "best_ckpt": None, "metrics": None}
    try:
        if cfg.get("train", True):
            try:
                trainer.fit(model, datamodule=datamodule, ckpt_path=resume_ckpt)
            except SystemExit:
                if trainer.interrupted:  # Lightning's Ctrl-C: it shut down and called sys.exit(1) without a word
                    _say_interrupted(trainer, run_dir)
                    raise SystemExit(EXIT_INTERRUPTED) from None
                raise
        if cfg.get("test", True):
            ckpt = _test_checkpoint(cfg, trainer, run_dir)
            result["best_ckpt"] = ckpt
            trainer.test(model, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
            result["metrics"] = outputs.metrics
    finally:
        finish_wandb()
    return result


#: exit status of a training stopped by Ctrl-C (128 + SIGINT, as a shell reports it; tofdenoise-denoise's too)
EXIT_INTERRUPTED = 130


def _say_interrupted(trainer: Any, run_dir: Path) -> None:
    """The one line after Ctrl-C: where the run stopped, and how to go on (Lightning says only that it shuts down;
    the run is not tested and writes no metrics.json, so it never passes for a finished run)."""
    import sys

    cb = trainer.checkpoint_callback
    last = Path(str(cb.dirpath)) / "last.ckpt" if cb is not None and getattr(cb, "dirpath", None) else None
    resume = (
        f"{last} is kept: resume with `tofdenoise-train <the same overrides> paths.run_dir={run_dir} ckpt_path=last`"
        if last is not None and last.is_file()
        else "no checkpoint was written yet: start it again"
    )
    print(
        f"tofdenoise-train: interrupted (Ctrl-C) at step {trainer.global_step}, epoch {trainer.current_epoch}; "
        f"not tested, no metrics.json; {resume}",
        file=sys.stderr,
    )


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
    best = run_dir / "checkpoints" / "best.ckpt"
    if not best.is_file():
        raise FileNotFoundError(
            f"train=false: no checkpoint to test; {best} does not exist (set ckpt_path=/path/to/model.ckpt)"
        )
    return str(check_checkpoint_file(best))


#: console script ``tofdenoise-train`` (Hydra command line: overrides, ``--multirun``, ``--cfg job``)
main = hydra_console_script(
    "train",
    run,
    "tofdenoise-train",
    (
        CheckpointFileError,
        CheckpointWriteError,
        ConfigError,
        InitWeightsError,
        OutputPathError,
        RunLockedError,
        WriteError,
    ),
)


if __name__ == "__main__":
    main()
