"""wandb's environment for a run, in one place: quiet, files under the run folder, one run id, always finished.

Both front ends (``tofdenoise train``, ``tofdenoise fit|test|...``) and the test suite use it:

- ``quiet_wandb()``: ``WANDB_SILENT=true`` and ``WANDB_ERROR_REPORTING=false`` unless already set (no banner,
  no crash reports sent anywhere). ``quiet_wandb(offline=True)`` also sets ``WANDB_MODE=offline`` (the tests).
- ``setup_wandb_env(run_dir)``: the above plus wandb's folders under the run folder (``WANDB_DIR`` = the run
  folder, ``WANDB_CACHE_DIR`` / ``WANDB_CONFIG_DIR`` / ``WANDB_DATA_DIR`` under ``<run_dir>/wandb/``), each
  unless already set.
- ``wandb_run_id(run_dir)``: one run id per run folder, kept in ``<run_dir>/wandb_run_id.txt`` across resumes.
- ``finish_wandb()``: ``wandb.finish()`` when a wandb run is open (a no-op when wandb was never imported).

Whether wandb runs offline is the logger's choice (``configs/logger/wandb_offline.yaml``: ``offline: true``).
"""

from __future__ import annotations

import os
import sys
import uuid
from pathlib import Path

from tofdenoise.atomic import atomic_write_text

__all__ = ["WANDB_ID_FILE", "QUIET_ENV", "quiet_wandb", "setup_wandb_env", "wandb_run_id", "finish_wandb"]

#: file of a run folder holding its wandb run id
WANDB_ID_FILE = "wandb_run_id.txt"
#: environment that keeps wandb quiet and local (set only where the user has not set it)
QUIET_ENV = {"WANDB_SILENT": "true", "WANDB_ERROR_REPORTING": "false"}


def quiet_wandb(offline: bool = False) -> None:
    """Set ``QUIET_ENV`` (and ``WANDB_MODE=offline`` with ``offline``) where the environment does not say otherwise."""
    for key, value in QUIET_ENV.items():
        os.environ.setdefault(key, value)
    if offline:
        os.environ.setdefault("WANDB_MODE", "offline")


def setup_wandb_env(run_dir: str | Path) -> None:
    """``quiet_wandb()`` plus wandb's folders under ``run_dir`` (each only where not set already)."""
    run_dir = Path(run_dir)
    base = run_dir / "wandb"
    quiet_wandb()
    os.environ.setdefault("WANDB_DIR", str(run_dir))
    os.environ.setdefault("WANDB_CACHE_DIR", str(base / ".cache"))
    os.environ.setdefault("WANDB_CONFIG_DIR", str(base / ".config"))
    os.environ.setdefault("WANDB_DATA_DIR", str(base / ".data"))


def wandb_run_id(run_dir: str | Path) -> str:
    """One wandb run id per run folder, kept across resumes (``wandb sync`` then merges the pieces)."""
    path = Path(run_dir) / WANDB_ID_FILE
    if path.is_file():
        return path.read_text().strip()
    run_id = uuid.uuid4().hex[:12]
    atomic_write_text(path, run_id + "\n")
    return run_id


def finish_wandb() -> None:
    """Close the open wandb run, if any (wandb is not imported here: a run without it pays nothing)."""
    wandb = sys.modules.get("wandb")
    if wandb is not None and getattr(wandb, "run", None) is not None:
        wandb.finish()
