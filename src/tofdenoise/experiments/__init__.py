"""What runs: the resumable runner, the named grids (robustness grid, paper tables) and their rows; rendering is
``tofdenoise.reporting``'s."""

from .runner import RunOutcome, RunSpec, read_run, run_all, run_finished

__all__ = ["RunOutcome", "RunSpec", "read_run", "run_all", "run_finished"]
