"""Grids of training runs: the resumable runner and the named grids (robustness grid, paper tables)."""

from .runner import RunOutcome, RunSpec, read_run, run_all, run_finished

__all__ = ["RunOutcome", "RunSpec", "read_run", "run_all", "run_finished"]
