"""Which code made a record: the git commit of the checkout the running ``tofdenoise`` package was imported from.

Every ``run_info.json`` written at training time carries ``commit`` (:func:`code_commit`): the 40-hex commit of the
checkout, ``commit_dirty`` (``true`` when tracked files differ from that commit: an uncommitted edit, a changed
config; the records and the results page that ``tofdenoise reproduce`` itself writes into the checkout,
``OUTPUT_PATHS``, do not count, so the runs after a table's first recorded one are not marked dirty by it) and
``commit_describe`` (``git describe --always``, with ``-dirty`` appended when ``commit_dirty``). An
installed package outside a checkout (a wheel in site-packages) records ``commit: null`` and its ``version``
instead. Records written before these fields existed read as before (:func:`record_commit` gives ``None``).

``code_digest`` (:func:`code_digest`) names the code by its content, whatever git says: the SHA-256 of the package's
sources and the Hydra configs (each file's path and content). Two records with the same digest ran the same code,
even where a copied checkout's git named a stale commit (``commit_dirty`` then says only that something differed).

Beside the commit, ``machine`` names what it ran on (:func:`host_machine`, completed by the training callback with
torch's version, thread count and accelerator): CPU training is bit-identical run to run only on the same machine
kind and thread count (docs/training.md#determinism), so a record says which it was.
"""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
import time
from collections.abc import Mapping
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

__all__ = [
    "RUNS_AT_ONCE_ENV",
    "code_commit",
    "code_digest",
    "cpu_label",
    "host_machine",
    "is_ancestor",
    "record_commit",
    "record_machine",
    "written_provenance",
]

#: where Linux names the CPU model (``model name`` lines)
CPUINFO = Path("/proc/cpuinfo")
#: set by an executor that trains several runs at a time on one machine (``tofdenoise reproduce --executor local
#: --workers N``) to N: a run's rate is then one of N sharing its CPUs and GPU, and its record says so
RUNS_AT_ONCE_ENV = "TOFDENOISE_RUNS_AT_ONCE"
#: the folder holding the ``tofdenoise`` package (``src/`` in a checkout)
_PACKAGE_DIR = Path(__file__).resolve().parents[1]
#: paths of a checkout (from its top) that hold outputs, not code: the committed records and the page built from them
OUTPUT_PATHS = ("docs/results", "docs/results.md")


def _run_git(folder: Path, *args: str) -> subprocess.CompletedProcess | None:
    """``git -C folder args`` run to its end, or None when git is missing or does not answer."""
    try:
        return subprocess.run(
            ["git", "-C", str(folder), *args], capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return None


def _git(folder: Path, *args: str) -> str | None:
    """``git -C folder args`` stripped, or None when git is missing, the folder is no checkout, or git fails."""
    done = _run_git(folder, *args)
    return done.stdout.strip() if done is not None and done.returncode == 0 else None


def is_ancestor(older: str, commit: str, folder: Path = _PACKAGE_DIR) -> bool | None:
    """Is ``older`` an ancestor of (or equal to) ``commit`` in the checkout holding ``folder`` (default: this
    package's)? None when git cannot tell (no git, no checkout, a commit it does not have)."""
    done = _run_git(folder, "merge-base", "--is-ancestor", older, commit)
    return None if done is None else {0: True, 1: False}.get(done.returncode)


def _version() -> str | None:
    try:
        return metadata.version("tofdenoise")
    except metadata.PackageNotFoundError:
        return None


@lru_cache(maxsize=8)
def _commit_of(folder: Path) -> tuple[tuple[str, Any], ...]:
    commit = _git(folder, "rev-parse", "--verify", "HEAD")
    if not commit:
        return (("commit", None), ("commit_dirty", None), ("version", _version()))
    # refresh the index's stat data first, so a file touched but not changed does not count as dirty
    _git(folder, "update-index", "-q", "--refresh")
    outputs = [f":(top,exclude){path}" for path in OUTPUT_PATHS]
    # diff-index --quiet exits 1 (None here) when a tracked file outside the outputs differs from HEAD
    dirty = _git(folder, "diff-index", "--quiet", "HEAD", "--", ":(top)", *outputs) is None
    describe = _git(folder, "describe", "--always", "--abbrev=12")
    return (
        ("commit", commit),
        ("commit_dirty", dirty),
        ("commit_describe", f"{describe}-dirty" if describe and dirty else describe),
    )


#: the files whose content is a run's code: the package's sources (Python, the native kernel's C++) and configs
CODE_SUFFIXES = (".py", ".cpp", ".h", ".yaml")


def code_digest(*folders: str | Path) -> str:
    """``sha256:<hex>`` of the code in ``folders`` (default: the imported ``tofdenoise`` package and the checkout's
    ``configs/``, where there is one): every file ending in one of :data:`CODE_SUFFIXES` below them (caches left
    out), in the order of its path relative to its folder, hashed as that path and its content's own SHA-256. A
    missing folder counts as empty. Pure of git: equal digests are equal code, whichever commit a checkout names."""
    if not folders:
        from tofdenoise.paths import CONFIG_DIR, PACKAGE_DIR

        folders = (PACKAGE_DIR, CONFIG_DIR)
    return _digest(tuple(Path(f).resolve() for f in folders))


@lru_cache(maxsize=8)
def _digest(folders: tuple[Path, ...]) -> str:
    total = hashlib.sha256()
    for index, folder in enumerate(folders):
        files = (
            sorted(
                p
                for p in folder.rglob("*")
                if p.suffix in CODE_SUFFIXES and p.is_file() and "__pycache__" not in p.parts
            )
            if folder.is_dir()
            else []
        )
        for path in files:
            rel = path.relative_to(folder).as_posix()
            total.update(f"{index}:{rel}:{hashlib.sha256(path.read_bytes()).hexdigest()}\n".encode())
    return "sha256:" + total.hexdigest()


def code_commit(folder: str | Path | None = None) -> dict[str, Any]:
    """The commit of the code that runs: ``{"commit", "commit_dirty", "commit_describe"}`` of the git checkout
    holding ``folder`` (default: the imported ``tofdenoise`` package); outside a checkout ``{"commit": None,
    "commit_dirty": None, "version": <installed version>}``. Read once per process and folder (a training run
    records the code it started with)."""
    return dict(_commit_of(Path(folder).resolve() if folder is not None else _PACKAGE_DIR))


def record_commit(run_info: Mapping[str, Any] | None) -> str | None:
    """The commit a ``run_info.json`` names, or None for a record written before commits were recorded (or made
    outside a checkout)."""
    if not run_info:
        return None
    commit = run_info.get("commit")
    return str(commit) if commit else None


def _cpu_fields(cpuinfo: Path) -> dict[str, str]:
    """The first processor's ``vendor_id``, ``cpu family``, ``model`` and ``model name`` lines of ``cpuinfo``
    (Linux); {} where there is no such file."""
    wanted = ("vendor_id", "cpu family", "model", "model name")
    fields: dict[str, str] = {}
    try:
        lines = cpuinfo.read_text(errors="replace").splitlines()
    except OSError:
        return fields
    for line in lines:
        if not line.strip() and fields:  # the end of the first processor's block
            break
        key, _, value = line.partition(":")
        if key.strip() in wanted and value.strip():
            fields.setdefault(key.strip(), value.strip())
    return fields


def host_machine(cpuinfo: Path = CPUINFO) -> dict[str, Any]:
    """The machine this process runs on, for a record: ``{"cpu": model name (``platform.processor()`` where Linux's
    cpuinfo does not tell), "cpu_id": "vendor family/model" (e.g. ``AuthenticAMD 25/17``: a virtual machine's model
    name often leaves the generation out), "cpu_count": logical CPUs this process may use, "arch": e.g. x86_64,
    "system": e.g. Linux, "runs_at_once": how many runs the executor that started this one trained at a time on
    this machine at most, its worker count (``RUNS_AT_ONCE_ENV``; 1 where it did not say)}`` (values None where the
    platform does not tell)."""
    fields = _cpu_fields(cpuinfo)
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    family, model = fields.get("cpu family"), fields.get("model")
    cpu_id = " ".join(v for v in (fields.get("vendor_id"), f"{family}/{model}" if family and model else None) if v)
    return {
        "cpu": fields.get("model name") or platform.processor() or None,
        "cpu_id": cpu_id or None,
        "cpu_count": usable,
        "arch": platform.machine() or None,
        "system": platform.system() or None,
        "runs_at_once": _runs_at_once(),
    }


def written_provenance(cpuinfo: Path = CPUINFO) -> dict[str, Any]:
    """Who wrote a record that no training run writes (a figure's ``validation.json``): ``{"written": local time
    with its UTC offset (``%Y-%m-%dT%H:%M:%S%z``, as ``run_info.json``'s ``started``), the commit fields of
    :func:`code_commit`, "machine": :func:`host_machine`}``. :func:`record_commit` and :func:`record_machine` read it
    as they read a ``run_info.json``."""
    return {
        "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        **code_commit(),
        "machine": host_machine(cpuinfo),
    }


def _runs_at_once() -> int:
    value = os.environ.get(RUNS_AT_ONCE_ENV, "1")
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"{RUNS_AT_ONCE_ENV}={value!r}: expected a whole number >= 1 (runs trained at a time)")
    return int(value)


def record_machine(run_info: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The ``machine`` a ``run_info.json`` names, or None for a record written before machines were recorded."""
    machine = (run_info or {}).get("machine")
    return dict(machine) if isinstance(machine, Mapping) else None


def cpu_label(machine: Mapping[str, Any]) -> str:
    """A machine's CPU in a few words: its model name with its vendor family/model in brackets (``AMD EPYC
    (AuthenticAMD 25/17)``), either alone where the other is missing, "" where neither is known."""
    cpu_id = f"({machine['cpu_id']})" if machine.get("cpu_id") else None
    return " ".join(str(v) for v in (machine.get("cpu"), cpu_id) if v)
