"""``tofdenoise classic``: the classical, non-learned row (joint bilateral filter), through the networks' test path.

The Hydra command line (``configs/classical.yaml``); the job itself (tune on validation, test the chosen parameters,
write the records) is :mod:`tofdenoise.experiments.classical_job`.

Examples::

    tofdenoise classic                                    # default data (experiment=default)
    tofdenoise classic experiment=grid paths.run_dir=runs/bilateral
    tofdenoise classic experiment=grid 'classical.grid.sigma_depth_mm=[5,10,20]' data.real_dir=/captures
"""

from __future__ import annotations

from tofdenoise.config import hydra_console_script
from tofdenoise.lazy import lazy_getattr

#: the job's functions, imported on first use (``tofdenoise classic --help`` imports no torch)
_LAZY = dict.fromkeys(("run", "grid_points", "tune", "select_best"), "tofdenoise.experiments.classical_job")

__all__ = ["main", *_LAZY]

__getattr__ = lazy_getattr(__name__, _LAZY)


def job():
    """The job Hydra's entry calls once the command line is parsed, and the errors printed as one line, exit 2."""
    from tofdenoise.atomic import WriteError
    from tofdenoise.experiments.classical_job import run
    from tofdenoise.run_lock import RunLockedError

    return run, (ValueError, FileNotFoundError, RunLockedError, WriteError)


#: console script ``tofdenoise classic`` (Hydra command line, like ``tofdenoise train``)
main = hydra_console_script("classical", job, "tofdenoise classic", __doc__)


if __name__ == "__main__":
    main()
