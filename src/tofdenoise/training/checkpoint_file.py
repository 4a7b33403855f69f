"""Is a checkpoint file complete? Checked before a resumed or tested run writes anything into its folder.

A run killed while its checkpoint was copied, a full disk or a partial download leaves a truncated
``last.ckpt``. Lightning would only fail on it after the run had started writing (``run_info.json``,
``config.yaml``), replacing the records of a finished run with those of an attempt that never ran.
:func:`check_checkpoint_file` reads the file first: it must be a complete zip archive (PyTorch's format since
1.6) whose members pass their CRC check, and ``torch.load`` (memory-mapped, on CPU) must give a Lightning
checkpoint dict with a ``state_dict``. Otherwise :class:`CheckpointFileError` says in one line which file is
broken and what to do: resume from ``best.ckpt`` (when there is one) or delete the file to start afresh.

:func:`resolve_ckpt_path` turns the Hydra entry point's ``ckpt_path`` setting (``null``, ``last`` or a file)
into the checkpoint to resume from.
"""

from __future__ import annotations

import logging
import os
import zipfile
from pathlib import Path

from tofdenoise.records import LAST_CHECKPOINT

__all__ = ["CheckpointFileError", "check_checkpoint_file", "resolve_ckpt_path"]

log = logging.getLogger("tofdenoise.train")


class CheckpointFileError(ValueError):
    """A checkpoint file is truncated, corrupt or not a Lightning checkpoint (message names the file)."""


def _advice(path: Path, option: str) -> str:
    best = path.with_name("best.ckpt")
    if path.name != best.name and best.is_file():
        return (
            f"resume from the best checkpoint instead ({option}={best}) or delete {path} to start a fresh "
            f"run in that folder"
        )
    return f"delete {path} to start a fresh run in that folder, or give another checkpoint ({option}=FILE)"


def _problem(path: Path) -> str | None:
    if not zipfile.is_zipfile(path):
        return (
            f"not a complete checkpoint ({path.stat().st_size} bytes, no zip directory: truncated or not a "
            f"PyTorch checkpoint)"
        )
    try:
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        return f"a damaged zip archive ({exc})"
    if bad is not None:
        return f"a damaged checkpoint (member {bad} fails its CRC check)"
    import torch

    try:
        payload = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling error means an unusable checkpoint
        return f"not loadable by torch.load ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
    if not isinstance(payload, dict) or "state_dict" not in payload:
        return "not a Lightning checkpoint (no 'state_dict' entry)"
    return None


def check_checkpoint_file(path: str | os.PathLike[str], option: str = "ckpt_path") -> Path:
    """Return ``Path(path)`` when it is a complete Lightning checkpoint, else raise :class:`CheckpointFileError`.

    ``option`` is the setting the advice names (``ckpt_path`` for Hydra, ``--ckpt_path`` for LightningCLI).
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointFileError(f"checkpoint {path} does not exist")
    problem = _problem(path)
    if problem is not None:
        raise CheckpointFileError(f"checkpoint {path} is {problem}; {_advice(path, option)}")
    return path


def resolve_ckpt_path(ckpt_path: str | None, run_dir: Path) -> str | None:
    """``None`` -> fresh run; ``"last"`` -> ``<run_dir>/checkpoints/last.ckpt`` when it exists (else fresh);
    any other value -> that file (which must exist)."""
    if ckpt_path in (None, "", "null"):
        return None
    if ckpt_path == "last":
        last = run_dir / LAST_CHECKPOINT
        if last.is_file():
            log.info("resuming from %s", last)
            return str(last)
        log.info("ckpt_path=last: %s does not exist yet, starting a fresh run", last)
        return None
    path = Path(str(ckpt_path)).expanduser()
    if not path.is_file():
        raise FileNotFoundError(
            f"config ckpt_path: checkpoint {path} does not exist "
            "(use ckpt_path=last to resume the run in paths.run_dir)"
        )
    return str(path)
