"""``tofdenoise fit|validate|test|predict --config FILE``: the LightningCLI front end.

It drives the same classes as the Hydra entry point (``DepthRestorer``, ``ToFDataModule``) from YAML files
generated from the Hydra configs (``configs/cli/{default,smoke,paper}.yaml``, see
``tofdenoise.cli.export_cli_config``). Examples::

    tofdenoise fit --config configs/cli/smoke.yaml
    tofdenoise fit --config configs/cli/default.yaml --model.init_args.backbone unet --ckpt_path last
    tofdenoise test --config configs/cli/default.yaml --ckpt_path outputs/cli/default/checkpoints/best.ckpt
    tofdenoise predict --config configs/cli/default.yaml --ckpt_path outputs/cli/default/checkpoints/best.ckpt

The run's records come from the ``RunOutputs`` callback of the configs (as in the Hydra run): ``fit`` and
``test`` write ``run_info.json``, ``test`` also ``metrics.json`` and ``per_image/<set>.csv``, all into
``trainer.default_root_dir``; ``predict`` writes PNG/``.npy`` depth maps through ``DepthPredictionWriter``.
wandb's environment (quiet, its files under ``trainer.default_root_dir``) and its ``wandb.finish()`` at the end
come from ``tofdenoise.wandb_env``. ``trainer.default_root_dir`` has one writer at a time (``tofdenoise.run_lock``,
taken before any class is instantiated): a second command on the same folder is refused, exit status 2.

A key the command does not take (a typo in a ``--config`` file, ``trainer.max_epochz``) is one line naming the file
and the key, with the closest key it does take, exit status 2 (jsonargparse's own report is its whole usage text).
"""

from __future__ import annotations

import argparse
import difflib
import inspect
import re
import sys
from pathlib import Path
from typing import Any

import yaml
from lightning.pytorch.cli import LightningCLI

from tofdenoise.atomic import WriteError
from tofdenoise.config import ConfigError
from tofdenoise.output_guard import OutputPathError, refuse_overwrite
from tofdenoise.records import FITTED, fit_best_checkpoints, training_state
from tofdenoise.run_lock import RunLock, RunLockedError, is_worker_rank, release_all
from tofdenoise.training.checkpoint_file import CheckpointFileError, check_checkpoint_file
from tofdenoise.wandb_env import finish_wandb, quiet_wandb, setup_wandb_env

__all__ = ["ToFLightningCLI", "main", "build_cli"]


class ToFLightningCLI(LightningCLI):
    """LightningCLI over ``DepthRestorer`` / ``ToFDataModule`` that checks ``--ckpt_path`` before anything is
    written and keeps wandb's files in the run folder."""

    def before_instantiate_classes(self) -> None:
        sub = self.config.get("subcommand") if hasattr(self.config, "get") else None
        cfg = self.config[sub] if sub else self.config
        root = cfg.get("trainer", {}).get("default_root_dir") if hasattr(cfg, "get") else None
        if root:
            root_path = Path(str(root)).expanduser().resolve()
            # one writer per run folder, taken before anything is written there (released by main())
            if not is_worker_rank():
                RunLock(root_path).acquire()
            model = cfg.get("model") if hasattr(cfg, "get") else None
            init = (model.get("init_args") or {}).get("init_weights") if hasattr(model, "get") else None
            if init not in (None, ""):  # the run's checkpoints never replace the weights it starts from
                refuse_overwrite(
                    [],
                    [Path(str(init)).expanduser()],
                    "--trainer.default_root_dir",
                    output_folders=[root_path / "checkpoints"],
                )
            root_path.mkdir(parents=True, exist_ok=True)
            setup_wandb_env(root_path)

    def parse_arguments(self, parser: Any, args: Any) -> None:
        """An argument or ``--config`` key that the command does not take is a ``ConfigError`` line naming the file
        and the key (``unknown_key_message``), not jsonargparse's usage text."""
        parsers = [parser, *getattr(getattr(parser, "_subcommands_action", None), "_name_parser_map", {}).values()]
        for each in parsers:
            each.exit_on_error = False
        try:
            super().parse_arguments(parser, args)
        except argparse.ArgumentError as exc:
            argv = list(sys.argv[1:] if args is None else args)
            sub = argv[0] if argv and argv[0] in self.subcommands() else None
            target = parsers[0] if sub is None else parser._subcommands_action._name_parser_map[sub]
            keys = [a.dest for a in target._actions if not a.dest.endswith(".help")]
            raise ConfigError(unknown_key_message(str(exc), argv, keys)) from None

    def instantiate_classes(self) -> None:
        """A class that refuses its arguments (a bad data setting, a calibration file that cannot be read) is one
        ``ConfigError`` line naming the cause, not jsonargparse's chain of Union errors and tracebacks."""
        try:
            super().instantiate_classes()
        except (ValueError, TypeError, OSError) as exc:
            cause: BaseException = exc
            while cause.__cause__ is not None:
                cause = cause.__cause__
            raise ConfigError(str(cause).strip().splitlines()[0] if str(cause).strip() else repr(cause)) from exc

    def _check_ckpt_path(self) -> None:
        """Check ``--ckpt_path`` before the trainer writes anything (SaveConfigCallback's config.yaml)."""
        sub = self.config.get("subcommand") if hasattr(self.config, "get") else None
        cfg = self.config[sub] if sub else self.config
        ckpt = cfg.get("ckpt_path") if hasattr(cfg, "get") else None
        if ckpt in (None, "", "best", "hpc") or str(ckpt).startswith("registry"):
            return
        if ckpt == "last":  # Lightning resolves it to the checkpoint callbacks' last.ckpt
            for cb in self.trainer.checkpoint_callbacks:
                dirpath = getattr(cb, "dirpath", None)
                last = Path(str(dirpath)) / f"{cb.CHECKPOINT_NAME_LAST}{cb.FILE_EXTENSION}" if dirpath else None
                if last is not None and last.is_file():
                    check_checkpoint_file(last, option="--ckpt_path")
            return
        check_checkpoint_file(ckpt, option="--ckpt_path")

    def _parse_ckpt_path(self) -> None:
        # Lightning (2.6) reads the hyperparameters of a --ckpt_path file while parsing: check the file first
        sub = self.config.get("subcommand") if hasattr(self.config, "get") else None
        ckpt = self.config[sub].get("ckpt_path") if sub else None
        if ckpt not in (None, "", "last", "best", "hpc") and not str(ckpt).startswith("registry"):
            check_checkpoint_file(ckpt, option="--ckpt_path")
        parse = getattr(super(), "_parse_ckpt_path", None)
        if parse is not None:
            parse()

    def before_fit(self) -> None:
        self._check_ckpt_path()

    def before_validate(self) -> None:
        self._check_ckpt_path()

    def before_test(self) -> None:
        self._check_ckpt_path()
        root = Path(str(self.trainer.default_root_dir)).expanduser().resolve()
        state = training_state(root)
        if state is None:
            return
        if state != FITTED:
            raise OutputPathError(
                f"--trainer.default_root_dir {root} holds a training run whose fit has not ended (or whose "
                "run_info.json cannot be read): resume the fit (--ckpt_path last) before testing it, or give the test "
                "its own folder (--trainer.default_root_dir ...)"
            )
        # the fit's folder: its own best.ckpt is tested and recorded with the fit's record (RunOutputs keeps the fit's
        # fields); another checkpoint's scores (or an untrained model's, without --ckpt_path) would be recorded as the
        # fit's
        sub = self.config.get("subcommand") if hasattr(self.config, "get") else None
        cfg = self.config[sub] if sub else self.config
        ckpt = cfg.get("ckpt_path") if hasattr(cfg, "get") else None
        best = fit_best_checkpoints(root)
        if ckpt != "best" and (ckpt in (None, "") or Path(str(ckpt)).expanduser().resolve() not in best):
            raise OutputPathError(
                f"--trainer.default_root_dir {root} holds a training run's records; a test there tests that run's "
                f"best checkpoint (--ckpt_path {' or '.join(sorted(map(str, best)))}), whose scores it records as the "
                f"run's. Give a test of {ckpt or 'the untrained model'} its own folder (--trainer.default_root_dir ...)"
            )

    def before_predict(self) -> None:
        self._check_ckpt_path()


def build_cli(args: list[str] | None = None, run: bool = True) -> ToFLightningCLI:
    """The CLI object (``run=False``: parse the config and instantiate model/data/trainer without running)."""
    # the model and the data (heavy: models, kernels) load once wandb is quieted (``main``)
    from tofdenoise.data_modules import ToFDataModule
    from tofdenoise.training.module import DepthRestorer

    return ToFLightningCLI(
        DepthRestorer,
        ToFDataModule,
        subclass_mode_model=True,
        subclass_mode_data=True,
        save_config_kwargs={"overwrite": True},
        args=args,
        run=run,
        auto_configure_optimizers=False,
    )


def _config_files(args: list[str]) -> list[str]:
    """The ``--config FILE`` arguments, in order."""
    files = [args[i + 1] for i, arg in enumerate(args) if arg in ("--config", "-c") and i + 1 < len(args)]
    return files + [arg.split("=", 1)[1] for arg in args if arg.startswith("--config=")]


def _dotted_keys(node: Any, prefix: str = "") -> list[str]:
    if not isinstance(node, dict):
        return []
    keys = []
    for key, value in node.items():
        dotted = f"{prefix}{key}"
        keys += [dotted, *_dotted_keys(value, dotted + ".")]
    return keys


def _init_parameters(class_path: str) -> list[str]:
    """The keyword arguments of the class that ``class_path`` names ([] when it cannot be imported)."""
    module, _, name = class_path.rpartition(".")
    try:
        cls = getattr(__import__(module, fromlist=[name]), name)
        return [p for p in inspect.signature(cls.__init__).parameters if p not in ("self", "args", "kwargs")]
    except Exception:  # noqa: BLE001 - only a suggestion
        return []


def unknown_key_message(message: str, args: list[str], valid_keys: list[str]) -> str:
    """One line for jsonargparse's error ``message``: a key the command does not take, named with the ``--config``
    file that holds it (or the option given) and the closest key it takes; any other error's first lines."""
    key, candidates = None, valid_keys
    top = re.search(r"does not accept option '([^']+)'", message)
    nested = re.search(r'Parser key "([^"]+)".*?Option \'([^\']+)\' is not accepted', message, re.S)
    if top:
        key = top.group(1)
    elif nested:
        section, option = nested.groups()
        key = f"{section}.init_args.{option}"
        class_path = re.search(r"class_path '([^']+)'", message)
        params = _init_parameters(class_path.group(1)) if class_path else []
        candidates = [f"{section}.init_args.{p}" for p in params]
    if key is None:
        lines = [line.strip() for line in message.strip().splitlines() if line.strip()]
        return "; ".join(lines[:2]) + (" ..." if len(lines) > 2 else "")
    where = f"option --{key}"
    for path in reversed(_config_files(args)):  # the last file that sets it (later files override earlier ones)
        try:
            keys = _dotted_keys(yaml.safe_load(Path(path).read_text(encoding="utf-8")))
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            continue
        if key in keys or key.replace(".init_args.", ".") in keys:
            where = f"--config {path}"
            break
    close = difflib.get_close_matches(key, candidates, n=1, cutoff=0.6)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    return f"{where}: unknown key '{key}'{hint} ('tofdenoise {args[0] if args else 'fit'} --help' lists the keys)"


def _check_config_files(args: list[str]) -> None:
    """Every ``--config FILE`` is UTF-8 YAML (jsonargparse's UnicodeDecodeError traceback and its YAML error name no
    file): ``ConfigError`` naming the file."""
    for i, arg in enumerate(args):
        path = args[i + 1] if arg == "--config" and i + 1 < len(args) else None
        path = arg.split("=", 1)[1] if arg.startswith("--config=") else path
        if path is None or not Path(path).is_file():
            continue
        try:
            yaml.safe_load(Path(path).read_bytes().decode("utf-8"))
        except UnicodeDecodeError as exc:
            raise ConfigError(
                f"--config {path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}); save "
                "the file as UTF-8"
            ) from None
        except yaml.YAMLError as exc:
            where = getattr(exc, "problem_mark", None)
            at = f" at line {where.line + 1}, column {where.column + 1}" if where is not None else ""
            problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
            raise ConfigError(f"--config {path}: not valid YAML{at}: {problem}") from None


def main(args: list[str] | None = None) -> Any:
    """Console script ``tofdenoise``."""
    quiet_wandb()
    from tofdenoise.training.init_weights import InitWeightsError  # heavy (torch), after wandb is quieted

    try:
        _check_config_files(sys.argv[1:] if args is None else args)
        build_cli(args)
    except (
        CheckpointFileError,
        ConfigError,
        InitWeightsError,
        OutputPathError,
        RunLockedError,
        WriteError,
    ) as exc:  # one line, not a traceback
        print(f"tofdenoise: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    finally:
        finish_wandb()
        release_all()
    return 0


if __name__ == "__main__":
    main()
