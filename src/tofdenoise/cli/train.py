"""``tofdenoise-train``: the Hydra entry point (``make train``).

Flow: check the config (valid backbone / noise / loss names, dataset paths) -> ``seed_everything`` ->
instantiate datamodule, model, callbacks, loggers and trainer (``_convert_="all"``: only plain values reach
the classes) -> ``trainer.fit`` (``ckpt_path=last`` resumes ``<run_dir>/checkpoints/last.ckpt``) ->
``trainer.test`` with the best checkpoint (lowest ``val/mae_mm``) -> ``metrics.json`` and ``run_info.json``
in the run folder. ``wandb.finish()`` always runs at the end.

Examples::

    tofdenoise-train                                   # default small CPU run on built-in scenes
    tofdenoise-train experiment=smoke                  # < 2 minutes
    tofdenoise-train backbone=unet noise=range loss=l1 trainer.max_epochs=5
    tofdenoise-train experiment=paper data.root=/data/ToF-FlyingThings3D
    tofdenoise-train paths.run_dir=runs/a ckpt_path=last   # resume a killed run
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

import hydra
from lightning.pytorch.callbacks import Callback
from omegaconf import DictConfig, OmegaConf, open_dict

from tofdenoise.atomic import atomic_write_text
from tofdenoise.cli.checkpoint_check import CheckpointFileError, check_checkpoint_file

__all__ = ["main", "run", "validate_config", "resolve_ckpt_path", "config_dir", "compose_config",
           "write_json_atomic", "write_test_outputs", "RunRecords", "RUN_INFO_NAME", "METRICS_NAME"]

log = logging.getLogger("tofdenoise.train")

RUN_INFO_NAME = "run_info.json"
METRICS_NAME = "metrics.json"
WANDB_ID_FILE = "wandb_run_id.txt"


def config_dir() -> Path:
    """The repository's ``configs/`` folder (``tofdenoise.paths.CONFIG_DIR`` when available)."""
    try:
        from tofdenoise.paths import CONFIG_DIR

        return Path(CONFIG_DIR)
    except ImportError:  # pragma: no cover - paths.py is part of the package
        return Path(__file__).resolve().parents[3] / "configs"


def compose_config(overrides: list[str] | None = None, config_name: str = "train") -> DictConfig:
    """Compose the Hydra config without running it (tests, ``export_cli_config``, notebooks)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose(config_name=config_name, overrides=list(overrides or []))


def write_json_atomic(path: Path, payload: Any) -> None:
    """JSON with sorted keys, written atomically."""
    atomic_write_text(path, json.dumps(payload, indent=2, sort_keys=True, allow_nan=True) + "\n")


def _names_or_error(kind: str, key: str, value: str, valid: list[str]) -> None:
    if value not in valid:
        raise ValueError(f"config {key}: unknown {kind} {value!r}; valid names: {', '.join(valid)} "
                         f"(choose with `{key.split('.')[0]}=<name>`)")


def validate_config(cfg: DictConfig) -> None:
    """Fail early (before any data or model is built) on unknown names or missing dataset paths."""
    from tofdenoise.training.losses import available_losses
    from tofdenoise.models import available_backbones
    from tofdenoise.physics.noise_models import available_noise_models

    for group in ("backbone", "noise", "loss", "data", "model", "trainer"):
        if group not in cfg or cfg[group] is None:
            raise ValueError(f"config: group {group!r} is missing (configs/train.yaml defaults list)")
    _names_or_error("backbone", "backbone.name", cfg.backbone.name, available_backbones())
    _names_or_error("noise model", "noise.name", cfg.noise.name, available_noise_models())
    _names_or_error("loss", "loss.name", cfg.loss.name, available_losses())
    data = cfg.data
    source = data.get("source", "procedural")
    if source not in (None, "procedural"):
        root = data.get("root")
        if root in (None, "", "???"):
            raise ValueError(f"config data.root: data source {source!r} needs its dataset folder; set "
                             f"data.root=/path/to/dataset (e.g. `make train DATA={source} "
                             f"ARGS='data.root=/data/...'`)")
        if not Path(str(root)).expanduser().exists():
            raise FileNotFoundError(f"config data.root: dataset folder {root} (data source {source!r}) does not "
                                    f"exist; set data.root to the dataset folder")
    if data.get("real_dir") not in (None, "") and not Path(str(data.real_dir)).expanduser().exists():
        raise FileNotFoundError(f"config data.real_dir: real capture folder {data.real_dir} does not exist "
                                "(set data.real_dir=null to skip the real test set)")
    for name, node in (cfg.get("logger") or {}).items():
        target = str((node or {}).get("_target_", ""))
        if target.endswith("TensorBoardLogger"):
            try:
                import tensorboard  # noqa: F401
            except ImportError:
                try:
                    import tensorboardX  # noqa: F401
                except ImportError as exc:
                    raise ImportError(f"config logger.{name}: the TensorBoard logger needs the `tensorboard` "
                                      "package (pip install tensorboard), or use logger=wandb_offline / csv") from exc


def resolve_ckpt_path(ckpt_path: str | None, run_dir: Path) -> str | None:
    """``None`` -> fresh run; ``"last"`` -> ``<run_dir>/checkpoints/last.ckpt`` when it exists (else fresh);
    any other value -> that file (which must exist)."""
    if ckpt_path in (None, "", "null"):
        return None
    if ckpt_path == "last":
        last = run_dir / "checkpoints" / "last.ckpt"
        if last.is_file():
            log.info("resuming from %s", last)
            return str(last)
        log.warning("ckpt_path=last: %s does not exist yet, starting a fresh run", last)
        return None
    path = Path(str(ckpt_path)).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"config ckpt_path: checkpoint {path} does not exist "
                                "(use ckpt_path=last to resume the run in paths.run_dir)")
    return str(path)


def _setup_wandb_env(run_dir: Path) -> None:
    base = run_dir / "wandb"
    os.environ.setdefault("WANDB_DIR", str(run_dir))
    os.environ.setdefault("WANDB_CACHE_DIR", str(base / ".cache"))
    os.environ.setdefault("WANDB_CONFIG_DIR", str(base / ".config"))
    os.environ.setdefault("WANDB_DATA_DIR", str(base / ".data"))
    os.environ.setdefault("WANDB_SILENT", "true")
    os.environ.setdefault("WANDB_ERROR_REPORTING", "false")


def _wandb_run_id(run_dir: Path) -> str:
    """One wandb run id per run folder, kept across resumes (``wandb sync`` then merges the pieces)."""
    path = run_dir / WANDB_ID_FILE
    if path.is_file():
        return path.read_text().strip()
    import uuid

    run_id = uuid.uuid4().hex[:12]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(run_id + "\n")
    return run_id


def _instantiate_group(node: DictConfig | None) -> list[Any]:
    from hydra.utils import instantiate

    out = []
    for _, sub in (node or {}).items():
        if isinstance(sub, DictConfig) and "_target_" in sub:
            out.append(instantiate(sub, _convert_="all"))
    return out


def _finish_wandb() -> None:
    wandb = sys.modules.get("wandb")
    if wandb is not None and getattr(wandb, "run", None) is not None:
        wandb.finish()


def run(cfg: DictConfig) -> dict[str, Any]:
    """Train and/or test as configured; returns ``{"run_dir", "best_ckpt", "metrics"}``."""
    from hydra.utils import instantiate
    from lightning.pytorch import seed_everything

    validate_config(cfg)
    run_dir = Path(str(cfg.paths.run_dir)).expanduser().resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    with open_dict(cfg):
        cfg.paths.run_dir = str(run_dir)
    _setup_wandb_env(run_dir)
    if cfg.get("logger") and cfg.logger.get("wandb") is not None and cfg.logger.wandb.get("id") is None:
        with open_dict(cfg):
            cfg.logger.wandb.id = _wandb_run_id(run_dir)

    # the checkpoint to resume from (or to test) is checked before anything of the run is written
    resume_ckpt = resolve_ckpt_path(cfg.get("ckpt_path"), run_dir) if cfg.get("train", True) else None
    if resume_ckpt is not None:
        check_checkpoint_file(resume_ckpt)
    elif cfg.get("test", True) and not cfg.get("train", True):
        _test_checkpoint(cfg, None, run_dir)

    seed_everything(int(cfg.seed), workers=True)
    run_info = {"backbone": cfg.backbone.name, "noise": cfg.noise.name, "loss": cfg.loss.name,
                "run_name": str(cfg.run_name), "data": str(cfg.data.get("source", "procedural")),
                "seed": int(cfg.seed), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    # a resumed or test-only attempt rewrites the run's records only once its checkpoint is loaded
    deferred = resume_ckpt is not None or not cfg.get("train", True)
    records = RunRecords(run_dir, run_info, cfg, resumed=resume_ckpt is not None)
    if not deferred:
        records.write()

    datamodule = instantiate(cfg.data, _convert_="all")
    model = instantiate(cfg.model, _convert_="all")
    callbacks = _instantiate_group(cfg.get("callbacks"))
    if deferred:
        callbacks.append(records)
    loggers = _instantiate_group(cfg.get("logger"))
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False, _convert_="all")
    for lg in trainer.loggers:
        lg.log_hyperparams({"config": OmegaConf.to_container(cfg, resolve=True)})

    result: dict[str, Any] = {"run_dir": str(run_dir), "best_ckpt": None, "metrics": None}
    try:
        if cfg.get("train", True):
            trainer.fit(model, datamodule=datamodule, ckpt_path=resume_ckpt)
            records.write_if_pending(trainer)  # a resumed run that had nothing left to train
        if cfg.get("test", True):
            ckpt = _test_checkpoint(cfg, trainer, run_dir)
            result["best_ckpt"] = ckpt
            trainer.test(model, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
            if trainer.is_global_zero:
                result["metrics"] = write_test_outputs(model, run_dir)
        run_info["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        run_info["global_step"] = int(trainer.global_step)
        run_info["best_ckpt"] = result["best_ckpt"]
        if trainer.is_global_zero:
            write_json_atomic(run_dir / RUN_INFO_NAME, run_info)
    finally:
        _finish_wandb()
    return result


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
        raise FileNotFoundError(f"train=false: no checkpoint to test; {best} does not exist "
                                "(set ckpt_path=/path/to/model.ckpt)")
    return str(check_checkpoint_file(best))


class RunRecords(Callback):
    """``run_info.json`` and ``config.yaml`` of a run attempt (atomic writes).

    A fresh run writes them at once (``write()``). A resumed or test-only run writes them only once Lightning
    has restored its checkpoint (``on_train_start`` / ``on_test_start``; or after a fit with nothing left to
    train), so an attempt that fails to load its checkpoint leaves the records of the earlier attempt
    untouched. A resumed attempt keeps the first attempt's ``started`` time and adds ``resumed``.
    """

    def __init__(self, run_dir: Path, run_info: dict[str, Any], cfg: DictConfig, resumed: bool = False) -> None:
        self.run_dir, self.run_info, self.cfg, self.resumed = run_dir, run_info, cfg, resumed
        self.pending = True

    def write(self) -> None:
        path = self.run_dir / RUN_INFO_NAME
        if self.resumed and self.pending and path.is_file():
            try:
                started = json.loads(path.read_text(encoding="utf-8")).get("started")
            except (OSError, ValueError, AttributeError):
                started = None
            if started:
                self.run_info["resumed"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
                self.run_info["started"] = started
        write_json_atomic(path, self.run_info)
        atomic_write_text(self.run_dir / "config.yaml", OmegaConf.to_yaml(self.cfg, resolve=True))
        self.pending = False

    def write_if_pending(self, trainer: Any) -> None:
        if self.pending and trainer.is_global_zero:
            self.write()

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        self.write_if_pending(trainer)

    def on_test_start(self, trainer: Any, pl_module: Any) -> None:
        self.write_if_pending(trainer)


def write_test_outputs(model: Any, run_dir: Path) -> dict[str, Any]:
    """``<run_dir>/metrics.json`` (final test metrics per set, restored + raw, and the learned guard's run-level
    fields ``trained_steps``, ``best_val_mae_mm``, ``raw_val_mae_mm``, ``learned_margin``, ``learned``,
    ``learned_reason`` from ``model.learned_record()``) and ``<run_dir>/per_image/<set>.csv`` from a
    ``DepthRestorer`` after ``trainer.test``."""
    from tofdenoise.training.results import write_metrics_json, write_per_image_csv

    results = dict(getattr(model, "test_results", {}) or {})
    if not results:
        raise RuntimeError("no test results to write: trainer.test produced no test set")
    results = _with_dataset_skips(results, model)
    for set_name, per in (getattr(model, "test_per_image", {}) or {}).items():
        write_per_image_csv(run_dir / "per_image" / f"{set_name}.csv", per["rows"], per["raw_rows"],
                            names=per["names"])
    learned = model.learned_record() if hasattr(model, "learned_record") else None
    write_metrics_json(run_dir / METRICS_NAME, results, run=learned)
    return json.loads((run_dir / METRICS_NAME).read_text())


#: test set name -> the datamodule's ``skipped_samples`` key of the samples it left out before testing
_SKIP_KEYS = {"synthetic": "test", "real": "real"}


def _with_dataset_skips(results: dict[str, Any], model: Any) -> dict[str, Any]:
    """Add the samples the datamodule left out of a test set (no valid pixel, a capture scene without an input
    frame) to that set's ``skipped_images``: they never reached the metric, which counts only its own."""
    trainer = getattr(model, "_trainer", None)
    skipped = getattr(getattr(trainer, "datamodule", None), "skipped_samples", None) or {}
    out = {}
    for set_name, entry in results.items():
        n = len(skipped.get(_SKIP_KEYS.get(set_name, set_name), []))
        if n and isinstance(entry, dict):
            entry = {**entry, "skipped_images": int(entry.get("skipped_images") or 0) + n}
        out[set_name] = entry
    return out


def _hydra_entry(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        # the folder Hydra created (paths.run_dir may contain ${now:...}: resolve it once)
        with open_dict(cfg):
            cfg.paths.run_dir = HydraConfig.get().runtime.output_dir
    try:
        run(cfg)
    except CheckpointFileError as exc:  # one line that says what to do, not a traceback
        print(f"tofdenoise-train: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None


def main() -> None:
    """Console script ``tofdenoise-train`` (Hydra command line: overrides, ``--multirun``, ``--cfg job``)."""
    hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="train")(_hydra_entry)()


if __name__ == "__main__":
    main()
