"""Do the committed records reproduce at this commit? One small recorded run per table, rerun and compared.

``tofdenoise reproduce --check`` (``make reproduce-check``; the ``slow`` test ``tests/experiments/
test_reproduce_check.py`` calls :func:`reproduce_check` too):

1. **Which runs.** Per table (I, II, III and the dynamic-range study), the trained row whose recorded runs trained
   fastest (median ``train_seconds`` of its ``run_info.json`` records), seed 0 (:func:`pick_check_runs`): a U-Net
   row for Table III and the study, the cheapest CNN for Table I, DVSS for Table II (it has no other backbone).
2. **The recorded config, exactly.** The run is what ``tofdenoise reproduce`` runs for that record today (its
   table's overrides with the profile's experiment), trained on the calibration the record names (the ``sensor``
   node of its ``config.yaml``, which is the calibration its data were made with, written to a file) and without
   the stand-in real set (its captures were not committed with the records: only the synthetic test split, which
   the config and calibration fix, is compared). A record made before the restore path's defaults changed
   (``legacy_hparams.FORMER_DEFAULTS_UNTIL``; every record without a commit) is rerun with the values it was
   trained with (:func:`former_defaults`: ``model.conditioning.centering=local``, ``fill=pullpush``), which its
   ``config.yaml`` does not name, and the check says so. A record tested without the simulator-noised split (every
   earlier-protocol record) is rerun without it too (``data.simulated_test=false``, :func:`record_test_sets`):
   building that split iterates a DataLoader, whose iterator draws its base seed from torch's global generator
   before training starts, so the split's presence shifts the training stream. Before it trains, the composed
   config is compared with the recorded ``config.yaml`` (:func:`config_drift`, the settings layout of older records
   translated): a setting that changed is printed, and the run is not a rerun of the record.
3. **Compared within a stated tolerance** (:func:`compare_metrics`): the noisy input's test MAE must be the
   record's to 1e-6 mm (the same test images: data, noise and holes); the test MAE, PSNR and the best validation
   MAE within the spread of the row over its recorded seeds (standard deviation, at least :data:`MIN_TOLERANCE`):
   a rerun that moves further than the training seeds move is not the recorded run. CPU training with a fixed seed
   and thread count is bit-identical run to run (``tests/training/test_determinism.py``), so on the machine and
   thread count of the record a rerun of unchanged code gives the record's numbers exactly.

A rerun already in the output folder is reused only when it was made by this very code: the same commit, with no
uncommitted changes then or now (:func:`set_aside_stale_rerun`); any other is moved to ``<out>/superseded/`` and
the run is made again, so that "reproduces at <commit>" always speaks of a rerun made at that commit.

A run that fails is reported plainly with the commit of its record (``run_info.json``'s ``commit``; records made
before commits were recorded say so): the code changed since, on purpose or not. That is a finding, not a reason
to widen the tolerance.
"""

from __future__ import annotations

import math
import os
import statistics
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf

from tofdenoise.atomic import atomic_write_text
from tofdenoise.config import compose_config
from tofdenoise.experiments.runner import RunSpec, run_all
from tofdenoise.experiments.tables import SIM_SET, TABLES, Row, run_name, table_specs
from tofdenoise.experiments.targets import CHECK_TABLES
from tofdenoise.records import (
    METRICS_NAME,
    RUN_INFO_NAME,
    RecordError,
    code_commit,
    cpu_label,
    host_machine,
    is_ancestor,
    load_metrics,
    metric_sets,
    read_record,
    record_commit,
    record_machine,
)

__all__ = [
    "CHECK_TABLES",
    "INPUT_TOLERANCE_MM",
    "MIN_TOLERANCE",
    "CheckRow",
    "CheckRun",
    "check_table_markdown",
    "compare_metrics",
    "config_drift",
    "former_defaults",
    "record_test_sets",
    "pick_check_runs",
    "reproduce_check",
]

#: a run's resolved config, as the training job saves it next to its records (``train_job.CONFIG_NAME``)
CONFIG_NAME = "config.yaml"
#: the noisy input's test MAE must match to this (mm): the same test images, noise and holes
INPUT_TOLERANCE_MM = 1e-6
#: the least tolerance of a trained metric (its seed spread may be smaller than this by chance with three seeds)
MIN_TOLERANCE = {"mae_mm": 0.01, "psnr_db": 0.05, "best_val_mae_mm": 0.01}
#: settings the check itself sets differently from the record: where the run writes and what it is tested on (the
#: calibration is the record's, given as a file; the stand-in real set is not committed), and keys that only say
#: how a run is resumed
CHECK_IGNORES = ("data.sensor", "data.real_dir", "sensor", "hydra")

Log = Callable[[str], None]


def _print(line: str) -> None:
    print(line, flush=True)


@dataclass(frozen=True)
class CheckRun:
    """The run a check reruns for ``table``: its record folder and the row it belongs to."""

    table: str
    row: Row
    seed: int
    record: Path

    @property
    def name(self) -> str:
        return run_name(self.row, self.seed)


@dataclass(frozen=True)
class CheckRow:
    """One compared number: the record's, the rerun's, their difference and the tolerance."""

    run: str
    metric: str
    record: float
    rerun: float
    tolerance: float

    @property
    def diff(self) -> float:
        return self.rerun - self.record

    @property
    def passed(self) -> bool:
        return math.isfinite(self.diff) and abs(self.diff) <= self.tolerance


@dataclass
class CheckResult:
    """What a check found: the compared numbers, and per run its notes (the record's commit, config drift)."""

    rows: list[CheckRow] = field(default_factory=list)
    notes: dict[str, list[str]] = field(default_factory=dict)
    failed_runs: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return not self.failed_runs and bool(self.rows) and all(r.passed for r in self.rows)


def _train_seconds(record: Path) -> float:
    info = read_record(record / RUN_INFO_NAME) or {}
    value = info.get("train_seconds")
    return float(value) if isinstance(value, (int, float)) else math.inf


def pick_check_runs(profile_dir: Path, tables: Sequence[str] = CHECK_TABLES, seed: int = 0) -> list[CheckRun]:
    """Per table, the trained row whose recorded runs trained fastest (median ``train_seconds``), its ``seed`` run;
    rows without a ``seed`` record holding ``config.yaml``, or whose record was resumed, are passed over. A
    ``ValueError`` for a table with none."""
    picked = []
    for table in tables:
        best: tuple[float, str, CheckRun] | None = None
        for row in TABLES[table]:
            if row.key == "raw" or row.kind != "train":
                continue
            record = profile_dir / run_name(row, seed)
            if not (record / CONFIG_NAME).is_file() or not (record / METRICS_NAME).is_file():
                continue
            if (read_record(record / RUN_INFO_NAME) or {}).get("resumed"):
                continue  # its data order after the stop differs from an uninterrupted run's: not rerun bit for bit
            seconds = [_train_seconds(profile_dir / run_name(row, s)) for s in (0, 1, 2)]
            finite = [s for s in seconds if math.isfinite(s)] or [math.inf]
            key = (statistics.median(finite), row.key)
            if best is None or key < best[:2]:
                best = (*key, CheckRun(table, row, seed, record))
        if best is None:
            raise ValueError(f"{profile_dir}: no recorded seed-{seed} run of table {table} with its {CONFIG_NAME}")
        picked.append(best[2])
    return picked


def _upgraded(flat: Mapping[str, Any]) -> dict[str, Any]:
    """A flattened config in today's settings layout: ``data.<source key>`` -> ``data.source_kwargs.<key>``,
    ``model.<flat setting>`` -> ``model.<group>.<field>`` (the layouts before issue 24)."""
    # heavy (torch, lightning through the training packages): imported when a check runs, not with the CLI
    from tofdenoise.experiments.train_job import FORMER_SOURCE_KEYS
    from tofdenoise.training.legacy_hparams import LEGACY_KEYS

    out = {}
    for key, value in flat.items():
        head, _, tail = key.partition(".")
        if head == "data" and tail in FORMER_SOURCE_KEYS:
            key = f"data.source_kwargs.{tail}"
        elif head == "model" and tail in LEGACY_KEYS:
            group, name = LEGACY_KEYS[tail]
            key = f"model.{group}.{name}"
        out[key] = value
    return out


def config_drift(recorded_yaml: str, now_yaml: str) -> tuple[list[str], list[str]]:
    """``(changed, added)`` between a record's ``config.yaml`` and today's composed config of the run (both
    resolved YAML text): ``changed`` the settings whose value differs or that today's config lacks
    (``key: recorded -> now``), ``added`` the settings only today's config has (``key = value``, new settings the
    record predates). Where the runs write, the sensor file and the real set are not compared (the check sets
    them), nor what ``tofdenoise train`` ignores when it compares two attempts of a run (``SAME_RUN_IGNORES``)."""

    from tofdenoise.experiments.train_job import _comparable  # heavy (lightning): see _upgraded

    def comparable(text: str) -> dict[str, Any]:
        flat = _upgraded(_comparable(text))
        return {k: v for k, v in flat.items() if not any(k == p or k.startswith(p + ".") for p in CHECK_IGNORES)}

    recorded, now = comparable(recorded_yaml), comparable(now_yaml)
    unset = "<unset>"
    changed = [
        f"{k}: {recorded[k]!r} -> {now.get(k, unset)!r}" for k in sorted(recorded) if now.get(k, unset) != recorded[k]
    ]
    added = [f"{k} = {now[k]!r}" for k in sorted(now.keys() - recorded.keys())]
    return changed, added


def _seed_spread(profile_dir: Path, row: Row, metric: str, seed: int = 0) -> float:
    """The standard deviation of ``metric`` over the recorded seeds of ``row`` whose record is of the test protocol
    of the ``seed`` run's (both scored the simulator-noised split or neither: a row part re-run under the current
    protocol does not mix the two; NaN with fewer than two)."""
    recorded = {}  # seed -> (scored the simulator-noised split, metrics)
    for other in (0, 1, 2):
        path = profile_dir / run_name(row, other) / METRICS_NAME
        if path.is_file():
            metrics = load_metrics(path)
            recorded[other] = (SIM_SET in metric_sets(metrics), metrics)
    own = recorded[seed][0] if seed in recorded else None
    values = [_metric(metrics, metric) for current, metrics in recorded.values() if own is None or current == own]
    finite = [v for v in values if math.isfinite(v)]
    return statistics.stdev(finite) if len(finite) >= 2 else math.nan


def _metric(metrics: Mapping[str, Any], metric: str) -> float:
    if metric == "best_val_mae_mm":
        value = metrics.get("best_val_mae_mm")
    elif metric.startswith("raw_"):
        value = (metrics.get("synthetic") or {}).get("raw", {}).get(metric[4:])
    else:
        value = (metrics.get("synthetic") or {}).get(metric)
    return float(value) if isinstance(value, (int, float)) else math.nan


def compare_metrics(
    name: str, recorded: Mapping[str, Any], rerun: Mapping[str, Any], spreads: Mapping[str, float]
) -> list[CheckRow]:
    """The compared numbers of one run (module docstring, step 3): the noisy input's test MAE to
    :data:`INPUT_TOLERANCE_MM`, then test MAE, test PSNR and best validation MAE each within ``spreads[metric]``
    (the row's seed spread), at least :data:`MIN_TOLERANCE`."""
    rows = [
        CheckRow(name, "raw_mae_mm", _metric(recorded, "raw_mae_mm"), _metric(rerun, "raw_mae_mm"), INPUT_TOLERANCE_MM)
    ]
    for metric, floor in MIN_TOLERANCE.items():
        spread = spreads.get(metric, math.nan)
        tolerance = max(floor, spread) if math.isfinite(spread) else floor
        rows.append(CheckRow(name, metric, _metric(recorded, metric), _metric(rerun, metric), tolerance))
    return rows


#: how a table is named in the check's notes
TABLE_NAMES = {"1": "Table I", "2": "Table II", "3": "Table III", "dynrange": "the dynamic-range study"}
#: how each compared number is named in the table
METRIC_LABELS = {
    "raw_mae_mm": "input test MAE (mm)",
    "mae_mm": "test MAE (mm)",
    "psnr_db": "test PSNR (dB)",
    "best_val_mae_mm": "best val MAE (mm)",
}


def check_table_markdown(rows: Sequence[CheckRow]) -> list[str]:
    """The comparison as a Markdown table: record, rerun, difference, tolerance, pass/fail."""
    lines = ["| run | metric | record | rerun | diff | tolerance | result |", "|---|---|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(
            f"| {r.run} | {METRIC_LABELS.get(r.metric, r.metric)} | {r.record:.4f} | {r.rerun:.4f} | "
            f"{r.diff:+.4f} | {r.tolerance:.4g} | {'pass' if r.passed else 'FAIL'} |"
        )
    return lines


def former_defaults(info: Mapping[str, Any] | None) -> tuple[list[str], str]:
    """The overrides that rerun a record with the restore-path defaults it was trained with, and a note: the former
    values (``legacy_hparams.FORMER_DEFAULTS``) for a record without a commit or made at a commit before
    ``FORMER_DEFAULTS_UNTIL``; none for a later one; none, with a note saying so, when git cannot tell."""
    from tofdenoise.training.legacy_hparams import FORMER_DEFAULTS, FORMER_DEFAULTS_UNTIL  # heavy package (torch)

    commit = record_commit(info)
    after = None if commit is None else is_ancestor(FORMER_DEFAULTS_UNTIL, commit)
    if after is None and commit is not None:
        since = FORMER_DEFAULTS_UNTIL[:12]
        return [], f"cannot tell whether {commit[:12]} predates the restore-path defaults of {since}"
    if after:
        return [], ""
    overrides = [f"++model.{group}.{name}={value}" for (group, name), value in FORMER_DEFAULTS.items()]
    return overrides, (
        f"made before the restore-path defaults changed ({FORMER_DEFAULTS_UNTIL[:12]}): rerun with the values it was "
        "trained with, " + ", ".join(o[2:] for o in overrides)
    )


def record_test_sets(metrics: Mapping[str, Any]) -> tuple[list[str], str]:
    """The overrides that rerun a record with the test sets it had, and a note: ``data.simulated_test=false`` for a
    record without a simulator-noised set (module docstring, step 2); none for one with it."""
    if SIM_SET in metric_sets(metrics):
        return [], ""
    return ["++data.simulated_test=false"], (
        "tested without the simulator-noised split, as the record was (building the split draws from torch's global "
        "generator before training: its presence shifts the training stream)"
    )


def _check_spec(run: CheckRun, profile: str, calibration: Path, extra: Sequence[str] = ()) -> RunSpec:
    from tofdenoise.experiments.reproduce import PROFILES  # the workflow module: imported when a check runs

    common = [*PROFILES[profile], f"++data.sensor={calibration}", "++data.real_dir=null", *extra]
    return next(s for s in table_specs(run.table, [run.seed], common) if s.name == run.name)


def _composed_yaml(spec: RunSpec, run_dir: Path) -> str:
    cfg = compose_config([*spec.overrides, f"paths.run_dir={run_dir}"])
    return OmegaConf.to_yaml(cfg, resolve=True)


#: what a run's ``prepared_data`` says about its inputs: the calibration, the noise models' matching, the split
INPUT_FIELDS = ("calibration", "variance_scale", "sizes", "holes", "max_depth_mm")


def _prepared(info: Mapping[str, Any] | None, key: str) -> Any:
    """A ``prepared_data`` field of a ``run_info.json``, at its top level or, in today's layout, under
    ``source_settings`` (where the source's own settings such as ``max_depth_mm`` moved)."""
    prepared = (info or {}).get("prepared_data") or {}
    return prepared[key] if key in prepared else (prepared.get("source_settings") or {}).get(key)


def _inputs_note(record: Path, rerun: Path) -> str:
    """Whether the rerun prepared the record's inputs (``run_info.json``'s ``prepared_data``: calibration
    fingerprint, variance scale, split sizes, hole settings, depth range)."""
    mine, theirs = read_record(rerun / RUN_INFO_NAME), read_record(record / RUN_INFO_NAME)
    present = [k for k in INPUT_FIELDS if _prepared(theirs, k) is not None]
    differ = [k for k in present if _prepared(theirs, k) != _prepared(mine, k)]
    if not differ:
        return "inputs prepared as recorded (" + ", ".join(present) + ")"
    return "inputs differ from the record's: " + "; ".join(
        f"{k}: {_prepared(theirs, k)!r} -> {_prepared(mine, k)!r}" for k in differ
    )


def _commit_note(info: Mapping[str, Any] | None) -> str:
    commit = record_commit(info)
    if commit is None:
        return "record made at an unrecorded commit (before run_info.json named it)"
    dirty = " with uncommitted changes" if (info or {}).get("commit_dirty") else ""
    return f"record made at {commit[:12]}{dirty}"


def _machine_label(machine: Mapping[str, Any]) -> str:
    cpu = cpu_label(machine)
    threads = machine.get("torch_threads")
    return f"{cpu or 'an unnamed CPU'}" + (f", {threads} threads" if threads else "")


def machine_note(info: Mapping[str, Any] | None, here: Mapping[str, Any] | None = None) -> str:
    """Where the record trained, against this machine (``here``, default :func:`~tofdenoise.records.host_machine`):
    CPU training reruns bit for bit only on the same CPU kind and thread count, so a rerun elsewhere is compared within
    the tolerance alone."""
    machine = record_machine(info)
    here = dict(here) if here is not None else host_machine()
    if machine is None:
        return (
            "record trained on an unrecorded machine (before run_info.json named it): a bit-for-bit rerun is not "
            "expected"
        )
    label = _machine_label(machine)
    if machine.get("accelerator") not in (None, "cpu"):
        return f"record trained on {machine.get('gpu') or machine.get('accelerator')} ({label})"
    same = all(machine.get(k) == here.get(k) for k in ("cpu", "cpu_id"))
    if same:
        return f"record trained on this CPU kind ({label})"
    return f"record trained on {label}; this machine is {_machine_label(here)}: a bit-for-bit rerun is not expected"


def _provenance(info: Mapping[str, Any] | None) -> tuple[Any, Any, Any]:
    """What identifies the code that made a run: (commit, commit_dirty, version)."""
    info = info or {}
    return info.get("commit"), info.get("commit_dirty"), info.get("version")


def set_aside_stale_rerun(rerun: Path, head: Mapping[str, Any], dry_run: bool = False) -> str | None:
    """Move a rerun folder that this code did not make to ``<its folder>/superseded/<name>-<commit>`` (``-2``,
    ``-3``, ... when taken), so that the check trains it again; returns what was done, None for a rerun that is kept
    (made at ``head``'s commit, with no uncommitted changes then or now) or no folder at all. A rerun without a
    ``run_info.json`` (never started, or of unknown code) is set aside too. ``dry_run``: say what would be done."""
    if not rerun.exists():
        return None
    info = read_record(rerun / RUN_INFO_NAME)
    made, now = _provenance(info), _provenance(head)
    if info is not None and made == now and now[0] is not None and not now[1]:
        return None
    label = (made[0] or "unknown")[:12]
    if info is None:
        origin = "of unknown code (no run_info.json)"
    else:
        origin = f"made at {label if made[0] else f'version {made[2]}'}"
        origin += " with uncommitted changes" if made[1] else ""
    dest = rerun.parent / "superseded" / f"{rerun.name}-{label}"
    n = 2
    while dest.exists():
        dest = rerun.parent / "superseded" / f"{rerun.name}-{label}-{n}"
        n += 1
    if dry_run:
        return f"{rerun.name}: the rerun in {rerun} was {origin}: it would be moved to {dest} and made again"
    dest.parent.mkdir(parents=True, exist_ok=True)
    os.replace(rerun, dest)
    return f"{rerun.name}: the rerun in {rerun} was {origin}: moved to {dest}, made again at this commit"


def reproduce_check(
    results: Path,
    out: Path,
    profile: str = "cpu",
    tables: Sequence[str] = CHECK_TABLES,
    dry_run: bool = False,
    extra: Sequence[str] = (),
    log: Log = _print,
) -> CheckResult:
    """Rerun one recorded run per table at this commit and compare it with its record (module docstring); the
    table is logged and written to ``<out>/reproduce-check.md``. Reruns in ``out`` made by this code are reused
    (finished) or resumed, any other is set aside (:func:`set_aside_stale_rerun`). ``extra``:
    Hydra overrides for every rerun after the profile's (as ``tofdenoise reproduce --extra``: the records must
    have been made with them too, else the config comparison names them)."""
    from tofdenoise.physics.calibration import SensorCalibration, save_calibration  # heavy (torch)

    profile_dir = Path(results) / profile
    runs = pick_check_runs(profile_dir, tables)
    head = code_commit()
    here = head.get("commit_describe") or head.get("commit") or f"version {head.get('version')}"
    result = CheckResult()
    specs = []
    for run in runs:
        recorded_yaml = (run.record / CONFIG_NAME).read_text(encoding="utf-8")
        sensor = (yaml.safe_load(recorded_yaml) or {}).get("sensor")
        if not isinstance(sensor, dict):
            raise RecordError(f"{run.record / CONFIG_NAME}: no 'sensor' mapping (the calibration the run used)")
        calibration = Path(out) / "calibrations" / f"{run.name}.yaml"
        try:
            calib = SensorCalibration.from_dict(sensor, source=str(run.record / CONFIG_NAME))
        except (ValueError, TypeError) as exc:
            raise RecordError(f"{run.record / CONFIG_NAME}: its 'sensor' is no calibration ({exc})") from None
        if not dry_run:
            save_calibration(calib, calibration)
        info = read_record(run.record / RUN_INFO_NAME)
        former, former_note = former_defaults(info)
        test_sets, test_sets_note = record_test_sets(load_metrics(run.record / METRICS_NAME))
        spec = _check_spec(run, profile, calibration, [*extra, *former, *test_sets])
        changed, added = config_drift(recorded_yaml, _composed_yaml(spec, Path(out) / run.name))
        notes = [f"{TABLE_NAMES.get(run.table, run.table)}: {run.name}"]
        notes.append(_commit_note(info))
        notes.append(machine_note(info))
        notes += [note for note in (former_note, test_sets_note) if note]
        if changed:
            notes.append("config changed since the record: " + "; ".join(changed))
        if added:
            notes.append("settings the record predates (today's value): " + "; ".join(added))
        result.notes[run.name] = notes
        specs.append(spec)
    for run in runs:
        for note in result.notes[run.name]:
            log(f"[reproduce-check] {note}")
        moved = set_aside_stale_rerun(Path(out) / run.name, head, dry_run=dry_run)
        if moved:
            log(f"[reproduce-check] {moved}")
    outcomes = run_all(specs, Path(out), dry_run=dry_run)
    if dry_run:
        return result
    for run, outcome in zip(runs, outcomes):
        if outcome.status not in ("done", "skipped"):
            result.failed_runs.append(run.name)
            continue
        recorded = load_metrics(run.record / METRICS_NAME)
        rerun = load_metrics(Path(out) / run.name / METRICS_NAME)
        result.notes[run.name].append(_inputs_note(run.record, Path(out) / run.name))
        spreads = {m: _seed_spread(profile_dir, run.row, m, run.seed) for m in MIN_TOLERANCE}
        result.rows += compare_metrics(run.name, recorded, rerun, spreads)
    lines = [
        f"Reproducibility check at {here} (profile {profile}): one recorded run per table, rerun and compared.",
        "",
    ]
    lines += check_table_markdown(result.rows)
    for name in result.failed_runs:
        lines.append(f"\n{name}: the rerun did not finish (see {Path(out) / name / 'train.log'})")
    failing = sorted({r.run for r in result.rows if not r.passed} | set(result.failed_runs))
    lines.append("")
    for run in runs:
        state = "does NOT reproduce" if run.name in failing else "reproduces"
        lines.append(f"- {run.name} {state} at {here}; {'; '.join(result.notes[run.name][1:])}.")
    if failing:
        lines.append(
            "A record that does not reproduce was made by other code than this commit's or depends on something "
            "its config does not fix: the difference is a finding about the records, not a tolerance to widen."
        )
    text = "\n".join(lines) + "\n"
    atomic_write_text(Path(out) / "reproduce-check.md", text)
    for line in text.splitlines():
        log(line)
    return result
