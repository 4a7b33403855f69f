"""What runs: the resumable runner, the named grids (robustness grid, paper tables) and their rows; rendering is
``tofdenoise.reporting``'s."""

from .runner import RunOutcome, RunSpec, run_all

__all__ = ["RunOutcome", "RunSpec", "run_all"]
