"""``tofdenoise train``: the Hydra entry point (``make train``): composes ``configs/train.yaml`` with the command line
and calls the training job, ``tofdenoise.experiments.train_job``.

The job is safe to run again: a folder that holds a finished run returns its recorded metrics without training, an
interrupted run resumes from ``<run_dir>/checkpoints/last.ckpt``; the run folder has one writer at a time
(``tofdenoise.run_lock``: a second run of the same folder is refused before it touches it, exit status 2). The
entry function returns the run's lowest validation MAE (``val/mae_mm``), what a Hydra sweeper optimises
(``hparams_search=recipe``: Optuna; needs ``pip install -e '.[sweep]'``, installed by ``make venv``).

Examples::

    tofdenoise train                                   # default small CPU run on built-in scenes
    tofdenoise train experiment=smoke                  # < 2 minutes
    tofdenoise train backbone=unet noise=range loss=l1 trainer.max_epochs=5
    tofdenoise train data.source_kwargs.num_samples=100 ++data.source_kwargs.hfov_deg=70   # the source's settings
    tofdenoise train experiment=paper data.source_kwargs.root=/data/ToF-FlyingThings3D
    tofdenoise train paths.run_dir=runs/a          # again: finished -> its metrics, killed -> resumes
    tofdenoise train -m seed=0,1,2 paths.sweep_dir=runs/sweep      # runs/sweep/unet-hetero-full-s{0,1,2}
    tofdenoise train -m hparams_search=recipe experiment=smoke     # Optuna search of lr, warm-up, decay
"""

from __future__ import annotations

import importlib.util
import sys

from tofdenoise.config import hydra_console_script
from tofdenoise.lazy import lazy_getattr

#: the training job's functions, imported on first use (``tofdenoise train --help`` imports no torch)
_LAZY = dict.fromkeys(("run", "validate_config", "record_calibration"), "tofdenoise.experiments.train_job")

__all__ = ["main", *_LAZY]

PROG = "tofdenoise train"
#: the Hydra sweeper plug-in of ``hparams_search`` (the ``sweep`` extra)
SWEEPER_MODULE = "hydra_plugins.hydra_optuna_sweeper"

__getattr__ = lazy_getattr(__name__, _LAZY)


def job():
    """What Hydra's entry calls, imported once the command line is parsed: the function that returns a run's lowest
    validation MAE, and the errors printed as one ``tofdenoise train: error: ...`` line with exit status 2."""
    from tofdenoise.atomic import WriteError
    from tofdenoise.callbacks.checkpointing import CheckpointWriteError
    from tofdenoise.config import ConfigError
    from tofdenoise.experiments.train_job import RunConfigMismatchError, validation_objective
    from tofdenoise.output_guard import OutputPathError
    from tofdenoise.run_lock import RunLockedError
    from tofdenoise.training.checkpoint_file import CheckpointFileError
    from tofdenoise.training.init_weights import InitWeightsError
    from tofdenoise.training.module import CheckpointMismatchError

    errors = (
        CheckpointFileError,
        CheckpointMismatchError,
        CheckpointWriteError,
        ConfigError,
        InitWeightsError,
        OutputPathError,
        RunConfigMismatchError,
        RunLockedError,
        WriteError,
    )
    return validation_objective, errors


_hydra_main = hydra_console_script("train", job, PROG, __doc__)


def _needs_sweeper(argv: list[str]) -> str | None:
    """The ``hparams_search=...`` option of the command line when its sweeper plug-in is not installed."""
    for arg in argv:
        if arg.lstrip("+").startswith("hparams_search=") and importlib.util.find_spec(SWEEPER_MODULE) is None:
            return arg
    return None


def main() -> None:
    """Console script ``tofdenoise train`` (Hydra command line: overrides, ``--multirun``, ``--cfg job``)."""
    missing = _needs_sweeper(sys.argv[1:])
    if missing is not None:
        print(
            f"{PROG}: error: {missing} needs the Optuna sweeper (hydra-optuna-sweeper), which is not installed; "
            "install the sweep extra: pip install -e '.[sweep]' (make venv installs it)",
            file=sys.stderr,
        )
        raise SystemExit(2)
    _hydra_main()


#: the function Hydra calls for every job (it returns the job's lowest validation MAE)
main.entry = _hydra_main.entry  # type: ignore[attr-defined]


if __name__ == "__main__":
    main()
