"""``tofdenoise classic``: the classical, non-learned row (joint bilateral filter), through the networks' test path.

The Hydra command line (``configs/classical.yaml``); the job itself (tune on validation, test the chosen parameters,
write the records) is :mod:`tofdenoise.experiments.classical_job`.

Examples::

    tofdenoise classic                                    # default data (experiment=default)
    tofdenoise classic experiment=grid paths.run_dir=runs/bilateral
    tofdenoise classic experiment=grid 'classical.grid.sigma_depth_mm=[5,10,20]' data.real_dir=/captures
"""

from __future__ import annotations

from tofdenoise.atomic import WriteError
from tofdenoise.config import hydra_console_script
from tofdenoise.experiments.classical_job import grid_points, run, select_best, tune
from tofdenoise.run_lock import RunLockedError

__all__ = ["main", "run", "grid_points", "tune", "select_best"]

#: console script ``tofdenoise classic`` (Hydra command line, like ``tofdenoise train``)
main = hydra_console_script(
    "classical", run, "tofdenoise classic", (ValueError, FileNotFoundError, RunLockedError, WriteError)
)


if __name__ == "__main__":
    main()
