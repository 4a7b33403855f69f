"""``tofdenoise reproduce``'s workflow: one of the paper's tables or figures, or a study (``targets``), resumable, and
``docs/results.md`` rebuilt from the committed records.

Steps: (1) the stand-in real set, once per profile (``data_modules.realset.build_realset``: a second simulated camera
with another frequency, contrast, harmonics, dark level and gain, mixed pixels at depth edges writes its calibration
captures and its capture set, and its calibration is estimated from them; ``<out>/realset``,
docs/camera-tutorial.md); (2) every run of the target, trained with that calibration and tested on the synthetic
split and on that capture set, each run a process of its own (``runner.run_all`` through ``executor``: sequential,
local workers, a SLURM array); finished runs are skipped, interrupted ones resume, a failing run does not stop the
others and is listed; (3) each finished run's records copied to ``<results>/<profile>/<run>/`` as it ends, with,
for a learned run, its real-set predictions scored against the stand-in's rendered truth (``write_truth_record``:
``real_vs_truth.json``, the page's "real vs truth" columns) and its own test sets scored again with the depth-edge
pixels apart (``write_regions_record``: ``regions.json``, the page's "where the error sits"); (4) the
page rebuilt from those records under its lock (``atomic.exclusive_lock``), so two commands committing runs at once
cannot drop one's run from it.

Figure 6 validates the noise model on the stand-in camera (``physics.validation.validate_to_folder``: its
validation captures against the calibration estimated from its own calibration captures). Figures 7 and 8 train
the runs of their columns for the first seed when missing, then render the figure from those runs' best checkpoints
(``figures``), check it against the runs' per-image records and commit ``figure.png`` and ``figure.json``.
"""

from __future__ import annotations

import json
import math
import os
import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tofdenoise.atomic import atomic_write_bytes, atomic_write_text, exclusive_lock
from tofdenoise.experiments.dynrange import gain_figure_png, gains
from tofdenoise.experiments.figures import (
    FIGURE_JSON,
    FIGURE_PNG,
    FIGURES,
    FigureMismatch,
    build_figure,
    encode_png_palette,
    figure_specs,
)
from tofdenoise.experiments.grid_data import prepare_grid_data
from tofdenoise.experiments.runner import RunSpec, TimeBudget, run_all
from tofdenoise.experiments.schedule import CURVES_FIGURE, curves_figure_png, schedule_curves
from tofdenoise.experiments.tables import TABLES, run_name, table_specs
from tofdenoise.experiments.targets import GPU_PROFILES, PROFILES, REALSET_SIZES, Target
from tofdenoise.records import (
    BEST_CHECKPOINT,
    METRICS_NAME,
    PER_IMAGE_DIR,
    REGIONS_NAME,
    RUN_INFO_NAME,
    TRUTH_NAME,
    cpu_label,
    read_run,
    record_commit,
    record_machine,
    run_finished,
    write_scene_record,
)
from tofdenoise.reporting import find_runs, load_runs, render_html
from tofdenoise.reporting.results_page import (
    CURRENT,
    DYNRANGE_FIGURE,
    EARLIER,
    RUN_FILES,
    comparable_metrics,
    load_records,
    record_protocol,
    results_markdown,
    run_minutes,
    seeds_present,
)

__all__ = [
    "GPU_PROFILES",
    "PROFILES",
    "REALSET_SIZES",
    "RECORD_FILES",
    "Reproduction",
    "copy_records",
    "ensure_realset",
    "without_recorded",
    "write_truth_record",
    "write_regions_record",
    "record_provenance",
    "warn_replaced_records",
    "profile_needs",
    "profile_overrides",
    "recorded_seconds",
    "reproduce",
    "write_page",
]

#: what a finished run leaves in docs/results/<profile>/<run>/ (small files; checkpoints and panels stay in runs/)
RECORD_FILES = (
    METRICS_NAME,
    RUN_INFO_NAME,
    "config.yaml",
    "csv/metrics.csv",
    f"{PER_IMAGE_DIR}/synthetic.csv",
    f"{PER_IMAGE_DIR}/simulated.csv",
    f"{PER_IMAGE_DIR}/real.csv",
    TRUTH_NAME,
    REGIONS_NAME,
)

Log = Callable[[str], None]


def _print(line: str) -> None:
    print(line, flush=True)


def profile_overrides(profile: str, realset_dir: Path, extra: list[str]) -> list[str]:
    """The overrides of every run: the profile's experiment, the second camera's calibration and capture set."""
    return [
        *PROFILES[profile],
        f"++data.sensor={realset_dir / 'calibration.yaml'}",
        f"++data.real_dir={realset_dir / 'captures'}",
        *extra,
    ]


def profile_needs(profile: str, extra: list[str], cuda_available: bool | None = None) -> str:
    """What ``profile`` needs that is missing ("" when nothing): the GPU profiles train on a CUDA GPU
    (``experiment=paper`` sets ``trainer=gpu``); ``gpu`` on ToF-FlyingThings3D (``--extra
    data.source_kwargs.root=FOLDER``, an existing folder), ``gpu-short`` on the built-in procedural scenes."""
    if profile not in GPU_PROFILES:
        return ""
    if profile == "gpu":
        roots = [e.split("=", 1)[1] for e in extra if e.lstrip("+").startswith("data.source_kwargs.root=")]
        if not roots:
            return "the ToF-FlyingThings3D folder: --extra data.source_kwargs.root=/path/to/ToF-FlyingThings3D"
        if not Path(roots[-1]).expanduser().is_dir():
            return f"an existing data.source_kwargs.root folder (ToF-FlyingThings3D), got {roots[-1]}"
    if cuda_available is None:
        import torch  # heavy: only for the GPU profile

        cuda_available = torch.cuda.is_available()
    if not cuda_available:
        return "a CUDA GPU (experiment=paper trains with trainer=gpu); torch.cuda.is_available() is False here"
    return ""


def ensure_realset(realset_dir: Path, profile: str, dry_run: bool = False, log: Log = _print) -> None:
    """The profile's stand-in real set (``REALSET_SIZES``), one scene per CPU core at a time; finished steps and
    complete scenes are skipped, so it is cheap to repeat. A dry run only says what it would build."""
    scenes, height, width = REALSET_SIZES[profile]
    what = f"the stand-in real set (second camera): {realset_dir}, {scenes} scenes of {height} x {width}"
    if dry_run:
        log(f"[reproduce] would build {what}")
        return
    from tofdenoise.data_modules.realset import build_realset  # heavy (torch): not for a dry run or the page

    log(f"[reproduce] {what}")
    build_realset(realset_dir, scenes=scenes, height=height, width=width, log=log, workers=os.cpu_count() or 1)


def write_truth_record(run_dir: Path, realset_dir: Path, device: str = "auto", log: Log = _print) -> bool:
    """Score a finished run's best checkpoint on the stand-in capture set against its rendered truth and write
    ``<run_dir>/real_vs_truth.json`` atomically (``inference.capture_eval.evaluate_checkpoint``); True when written.

    Nothing is done for a run that has not finished or has no ``checkpoints/best.ckpt`` (the classical filter's job
    writes its own), for a capture set without truth (a real camera's), or when the record is newer than the
    checkpoint and scored as many scenes as the set holds (a repeated ``reproduce`` skips it; a set that grew, e.g.
    from 24 to the paper's 200 scenes, is scored again). A checkpoint or capture set that cannot be scored is logged
    with its reason and leaves no file: the run's other records are still committed, its truth columns stay empty."""
    ckpt, captures = run_dir / BEST_CHECKPOINT, realset_dir / "captures"
    out = run_dir / TRUTH_NAME
    if not (run_finished(run_dir) and ckpt.is_file()):
        return False
    from tofdenoise.data_modules.real_captures import list_scenes  # heavy (torch): not for the page
    from tofdenoise.inference.capture_eval import evaluate_checkpoint, has_truth

    if not has_truth(captures):
        return False
    if out.is_file() and out.stat().st_mtime >= ckpt.stat().st_mtime:
        try:
            scored = json.loads(out.read_text(encoding="utf-8")).get("scenes")
        except (OSError, json.JSONDecodeError, AttributeError):
            scored = None
        if scored == len(list_scenes(captures)):
            return False
    try:
        result = evaluate_checkpoint(ckpt, captures, realset_dir / "calibration.yaml", device)
    except (FileNotFoundError, ValueError) as exc:
        log(f"[reproduce] {run_dir.name}: not scored against the stand-in's truth: {exc}")
        return False
    write_scene_record(out, result)
    mae = result["truth"]["mean"]["mae_mm"]
    log(f"[reproduce] {run_dir.name}: real set against the truth, MAE {mae:.3f} mm -> {out}")
    return True


def write_regions_record(run_dir: Path, device: str = "auto", log: Log = _print) -> bool:
    """Score a finished run's own test sets again with the depth-edge pixels apart from the rest and write
    ``<run_dir>/regions.json`` atomically (``inference.run_eval.evaluate_run`` with ``training.metrics.EDGE_JUMP_MM``,
    the sets its ``metrics.json`` has of synthetic and simulated); True when written. Nothing is done for a run
    that has not finished or has no ``checkpoints/best.ckpt``, or whose record is newer than the checkpoint; a run
    that cannot be scored again is logged with its reason and leaves no file."""
    ckpt, out = run_dir / BEST_CHECKPOINT, run_dir / REGIONS_NAME
    if not (run_finished(run_dir) and ckpt.is_file()):
        return False
    if out.is_file() and out.stat().st_mtime >= ckpt.stat().st_mtime:
        return False
    from tofdenoise.inference.run_eval import evaluate_run  # heavy (torch, hydra): not for the page
    from tofdenoise.training.metrics import EDGE_JUMP_MM

    try:
        result = evaluate_run(run_dir, device=device, edge_jump_mm=EDGE_JUMP_MM)
    except (FileNotFoundError, ValueError) as exc:
        log(f"[reproduce] {run_dir.name}: its test sets not scored by region: {exc}")
        return False
    write_scene_record(out, result)
    parts = []
    for name, scored in result["sets"].items():
        regions = scored["restored"]["regions"]
        edge, off_edge = regions["edge"]["mean"]["mae_mm"], regions["off_edge"]["mean"]["mae_mm"]
        parts.append(f"{name} edge {edge:.3f} / off-edge {off_edge:.3f} mm")
    log(f"[reproduce] {run_dir.name}: MAE by region: {'; '.join(parts)} -> {out}")
    return True


def _same_run(run_dir: Path, record_dir: Path) -> bool:
    """True when the committed record ``record_dir`` is of the run in ``run_dir``: both ``run_info.json`` readable,
    with the same start time."""
    info, _ = read_run(run_dir)
    record, _ = read_run(record_dir)
    return bool(info and record and info.get("started") and info.get("started") == record.get("started"))


def copy_records(run_dirs: list[Path], dest: Path) -> list[str]:
    """Copy each finished run's records (``RECORD_FILES`` that exist) to ``dest/<run>/`` atomically; the names. The
    per-scene records (``TRUTH_NAME``, ``REGIONS_NAME``) are written in ``write_scene_record``'s compact form, the
    same numbers, whichever form the run folder holds (one written by an older version is indented); a file that is
    not JSON is copied as it is, for the page to report. Where ``dest/<run>/`` holds the record of another run of
    that name (another start time: a run trained again, by ``--rerun-earlier`` or for a figure), a record file that
    the run folder lacks is removed, so that no file of the replaced record (an earlier run's score against the
    truth, say) stays beside the new run's metrics; a record of the same run keeps what its folder lacks."""
    copied = []
    for run_dir in run_dirs:
        if not run_finished(run_dir):
            continue
        replaced = not _same_run(run_dir, dest / run_dir.name)
        for name in RECORD_FILES:
            source, target = run_dir / name, dest / run_dir.name / name
            if not source.is_file():
                if replaced:
                    target.unlink(missing_ok=True)
                continue
            data = source.read_bytes()
            if name in (TRUTH_NAME, REGIONS_NAME):
                try:
                    write_scene_record(target, json.loads(data))
                    continue
                except (ValueError, TypeError):  # not a strict JSON object: as it is
                    pass
            atomic_write_bytes(target, data)
        copied.append(run_dir.name)
    return copied


def record_provenance(record_dir: Path) -> str | None:
    """Where a committed record came from, for a message: "made at <commit> on <CPU>" from its ``run_info.json``
    (either part "unrecorded" when the record does not say); None when there is no readable ``run_info.json``."""
    info, _ = read_run(record_dir)
    if info is None:
        return None
    commit = (record_commit(info) or "")[:12] or "an unrecorded commit"
    machine = record_machine(info)
    return f"made at {commit} on {(cpu_label(machine) if machine else '') or 'an unrecorded machine'}"


def warn_replaced_records(specs: list[Any], out: Path, dest: Path, log: Log = _print) -> list[str]:
    """Log each run of ``specs`` that has no finished run folder in ``out`` but a committed record in ``dest``:
    training it (a figure needs the checkpoint, which records do not keep) replaces that record, and the tables
    that show it change with it. Returns those runs' names."""
    replaced = []
    for spec in specs:
        if run_finished(Path(out) / spec.name):
            continue
        made = record_provenance(dest / spec.name)
        if made is not None:
            replaced.append(spec.name)
            log(
                f"[reproduce] {spec.name}: no finished run folder in {out}; training it replaces its committed record "
                f"in {dest / spec.name} ({made}), and the tables that show it change with it"
            )
    return replaced


def without_recorded(
    specs: list[Any],
    dest: Path,
    log: Log = _print,
    rerun_earlier: bool = False,
    rerun_without_truth: bool = False,
) -> list[Any]:
    """``specs`` less the runs whose records (``metrics.json`` and ``run_info.json``) are committed in ``dest``: what
    ``--skip-recorded`` runs on a machine that does not hold their run folders. With ``rerun_earlier`` a record of
    the earlier test protocol does not count (``--rerun-earlier``: the run trains again under the current one); with
    ``rerun_without_truth`` a record without its score against the stand-in set's truth (``TRUTH_NAME``) does not
    count (``--rerun-without-truth``: that score needs the run's checkpoint, which a record does not carry). The runs
    left out, and those run again, are logged."""
    if not dest.is_dir():  # a mistyped --results or --profile would otherwise train everything without a word
        log(f"[reproduce] --skip-recorded: {dest}: no such folder, so no run is committed there: all are run")
    recorded = [s.name for s in specs if all((dest / s.name / name).is_file() for name in RUN_FILES)]
    # (asked for, option, which records, does a record of this run not count)
    rules = (
        (rerun_earlier, "--rerun-earlier", "of the earlier protocol", lambda run: _protocol(dest / run) == EARLIER),
        (
            rerun_without_truth,
            "--rerun-without-truth",
            f"without {TRUTH_NAME}",
            lambda run: not (dest / run / TRUTH_NAME).is_file(),
        ),
    )
    for asked, option, which, again in rules:
        rerun = [name for name in recorded if asked and again(name)]
        if rerun:
            log(f"[reproduce] {option}: {len(rerun)} record(s) {which} run again: {', '.join(rerun)}")
            recorded = [name for name in recorded if name not in rerun]
    if recorded:
        log(f"[reproduce] --skip-recorded: {len(recorded)} run(s) committed in {dest}, not run: {', '.join(recorded)}")
    return [s for s in specs if s.name not in recorded]


#: an estimate from the records is scaled by this (a run on another machine of the same kind, a busier disk)
ESTIMATE_MARGIN = 1.15


def _wall_seconds(run_info: Path) -> float | None:
    """A committed ``run_info.json``'s start-to-finish span (``results_page.run_minutes``: the page's wall minutes) in
    seconds; None when the file cannot be read, either time is missing, or the run was resumed (its span includes
    the stop)."""
    try:
        info = json.loads(run_info.read_text())
    except (OSError, ValueError):
        return None
    minutes = run_minutes(info) if isinstance(info, dict) else math.nan
    return minutes * 60.0 if math.isfinite(minutes) else None


def _family(name: str) -> tuple[str, ...]:
    """What sets a run's cost, read from its folder name ``<backbone>-<noise>-<loss>[-<tag>]-s<seed>``: the name less
    its noise and its seed (the training noise and the seed do not change a step's cost)."""
    parts = name.split("-")
    if len(parts) >= 4 and parts[-1][:1] == "s" and parts[-1][1:].isdigit():
        return (parts[0], *parts[2:-1])
    return (name,)


def _protocol(run_dir: Path) -> str:
    """The test protocol of a committed run (``results_page.record_protocol``; an unreadable metrics.json or
    run_info.json: earlier)."""
    try:
        metrics = json.loads((run_dir / METRICS_NAME).read_text())
        info = json.loads((run_dir / RUN_INFO_NAME).read_text())
    except (OSError, ValueError):
        return EARLIER
    if not isinstance(metrics, dict) or not isinstance(info, dict):
        return EARLIER
    return record_protocol({"metrics": metrics, "run_info": info})


def recorded_seconds(dest: Path, spec: RunSpec) -> float | None:
    """How long ``spec`` is expected to take on this profile's machine: the median wall time (start of training to
    its records, tests included) of the runs committed in ``dest`` of the same backbone, loss and variant (any
    noise, any seed) and of the current test protocol where any is (its tests cost what this code's do), times
    ``ESTIMATE_MARGIN``; None when none is recorded. The median, not the longest: a run timed while the machine was
    shared would otherwise keep every later run of its family from starting, and a run that overruns the budget is
    stopped and resumes from its last epoch, so little is lost."""
    family = _family(spec.name)
    walls: dict[str, list[float]] = {CURRENT: [], EARLIER: []}
    for info in dest.glob(f"*/{RUN_INFO_NAME}"):
        if _family(info.parent.name) == family and (w := _wall_seconds(info)) is not None:
            walls[_protocol(info.parent)].append(w)
    chosen = walls[CURRENT] or walls[EARLIER]
    return statistics.median(chosen) * ESTIMATE_MARGIN if chosen else None


def run_estimate(dest: Path, spec: RunSpec, given: dict[str, float] | None = None) -> float | None:
    """The seconds ``spec`` is expected to take under a time budget: ``given`` minutes for its run name or, failing
    that, its backbone (``--run-minutes``: the records' walls may come from another code or another sharing of the
    machine), else :func:`recorded_seconds`."""
    given = given or {}
    for key in (spec.name, _family(spec.name)[0]):  # the run, then its backbone
        if key in given:
            return 60.0 * given[key]
    return recorded_seconds(dest, spec)


def parse_run_minutes(items: list[str]) -> dict[str, float]:
    """``["dvss=5", "restormer=4.5"]`` -> ``{"dvss": 5.0, "restormer": 4.5}`` (``--run-minutes``); a ValueError that
    names the item for anything else."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            minutes = float(value)
        except ValueError:
            minutes = float("nan")
        if not sep or not name or not (math.isfinite(minutes) and minutes > 0):
            raise ValueError(
                f"--run-minutes expects NAME=MINUTES (a backbone or a run name, a positive number), got {item!r}"
            )
        out[name] = minutes
    return out


def write_report(dest: Path) -> None:
    """The offline HTML report of the recorded runs (``dest/report.html``), when there are any."""
    if not any(dest.glob(f"*/{METRICS_NAME}")):
        return
    runs, skipped = load_runs(find_runs([dest]))
    if runs:
        title = f"tofdenoise: paper tables, {dest.name} profile"
        atomic_write_text(dest / "report.html", render_html(runs, title, skipped))


def write_dynrange_figure(
    dest: Path, seeds: list[int] | None = None, records: dict[str, dict[str, Any]] | None = None
) -> None:
    """The dynamic-range study's gain figure from the committed records (``dest/dynrange/gains.png``), over
    ``seeds`` (default: every seed with records), from the records the page's gain table reads (no seed whose runs
    of one world are of two protocols). ``records``: ``load_records(dest)`` where the caller has read them."""
    records = load_records(dest) if records is None else records
    seeds = seeds_present(records) if seeds is None else seeds
    items = gains(comparable_metrics(["dynrange"], seeds, records), seeds)
    if items:
        atomic_write_bytes(dest / DYNRANGE_FIGURE, gain_figure_png(items))
    else:  # no gain left to draw: a figure of records since replaced or removed would show what none says
        (dest / DYNRANGE_FIGURE).unlink(missing_ok=True)


def write_schedule_figure(dest: Path, seeds: list[int]) -> None:
    """The long-schedule study's validation curves and gaps (``dest/schedule/curves.png``), from the committed
    records."""
    curves = schedule_curves(dest, seeds)
    if curves:
        atomic_write_bytes(dest / CURVES_FIGURE, curves_figure_png(curves))
    else:
        (dest / CURVES_FIGURE).unlink(missing_ok=True)


def write_study_figures(results: Path) -> None:
    """Every study figure drawn from committed records (the dynamic-range gains, the long-schedule curves), for each
    profile under ``results``, redrawn from the records as they are now: a record replaced or copied in by hand
    (a retrained Table 3 run the study shares) never leaves a figure of the records before it."""
    for dest in sorted(p for p in Path(results).iterdir() if p.is_dir()) if Path(results).is_dir() else []:
        records = load_records(dest)  # read once for both figures (about 1 s for the cpu profile's records)
        write_dynrange_figure(dest, records=records)
        write_schedule_figure(dest, seeds_present(records))


def write_page(results: Path, page: Path, before: Any = None) -> str:
    """Rebuild ``page`` from the records under ``results`` under the page's lock (``before()`` first, inside it):
    a rebuild reads every record, so two commands committing runs at once must not interleave."""
    with exclusive_lock(page):
        if before is not None:
            before()
        text = results_markdown(results)
        atomic_write_text(page, text)
    return text


@dataclass
class Reproduction:
    """What to reproduce and where (``tofdenoise reproduce``'s options)."""

    target: Target | None  # None: only rebuild the page
    results: Path
    page: Path
    profile: str = "cpu"
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    out: Path | None = None  # run folders (default runs/reproduce/<profile>, set by the caller)
    extra: list[str] = field(default_factory=list)
    dry_run: bool = False
    executor: Any = None  # an executor of ``experiments.executors`` (None: sequential)
    skip_recorded: bool = False  # leave out the runs whose records are committed in ``dest`` (tables, studies)
    rerun_earlier: bool = False  # with skip_recorded: a record of the earlier test protocol does not count
    rerun_without_truth: bool = False  # with skip_recorded: a record without its real_vs_truth.json does not count
    #: minutes for the runs (a GPU allocation's limit): runs that would not fit are not started, a run still
    #: training at the end is stopped and resumes next time (``runner.TimeBudget``; estimates: ``recorded_seconds``)
    time_budget_min: float | None = None
    #: expected minutes of a run, by backbone or by run name, in place of ``recorded_seconds`` (``--run-minutes``)
    run_minutes: dict[str, float] = field(default_factory=dict)
    #: only build the stand-in set and prepare the data of the runs still to train (``--prepare-only``)
    prepare_only: bool = False

    @property
    def realset_dir(self) -> Path:
        return Path(self.out) / "realset"

    @property
    def dest(self) -> Path:
        return self.results / self.profile

    def overrides(self) -> list[str]:
        return profile_overrides(self.profile, self.realset_dir, self.extra)


def validation_figure(job: Reproduction, log: Log = _print) -> int:
    """Figure 6: the noise model validated on the second camera (its validation captures against the calibration
    estimated from its own calibration captures), committed to ``<results>/<profile>/fig6/``."""
    folder, captures = Path(job.out) / "fig6", job.realset_dir / "validation"
    calibration = job.realset_dir / "calibration.yaml"
    if job.dry_run:
        log(f"[reproduce] would validate the noise model: {calibration} against {captures} -> {folder}")
        return 0
    from tofdenoise.physics.calibration import resolve_calibration  # heavy (torch): not for a dry run
    from tofdenoise.physics.validation import VALIDATION_FILES, validate_to_folder

    log(f"[reproduce] figure 6 (noise-model validation on the second camera) -> {folder}")
    result, _, _ = validate_to_folder(resolve_calibration(calibration), folder, captures_dir=captures)
    pooled = result.pooled.get("proposed", {})
    log(f"[reproduce] figure 6: proposed pooled MAPE {pooled.get('mape_percent', float('nan')):.2f} %")
    for name in VALIDATION_FILES:
        atomic_write_bytes(job.dest / "fig6" / name, (folder / name).read_bytes())
    return 0


def qualitative_figure(job: Reproduction, record: Any, log: Log = _print) -> int:
    """Figures 7 / 8: the columns' runs for the first seed (trained when missing), then the rendered figure."""
    from tofdenoise.inference.denoise import CheckpointError  # heavy (torch)

    spec, seed = FIGURES[job.target.key], job.seeds[0]
    specs = figure_specs(spec, seed, job.overrides())
    warn_replaced_records(specs, job.out, job.dest, log)
    outcomes = run_all(
        specs, job.out, dry_run=job.dry_run, after_each=None if job.dry_run else record, executor=job.executor
    )
    if job.dry_run:
        log(f"[reproduce] would render {spec.key} from {', '.join(s.name for s in specs)}")
        return 0
    unfinished = [o.spec.name for o in outcomes if o.status not in ("done", "skipped")]
    if unfinished:
        log(f"[reproduce] {spec.key} not rendered: run(s) {', '.join(unfinished)} did not finish")
        return 1
    try:
        image, fig_record = build_figure(spec, seed, specs, job.out)
    except (FigureMismatch, CheckpointError) as exc:  # a figure that would not show what the tables scored
        log(f"[reproduce] {spec.key} not rendered: {exc}")
        return 1
    fig_record["profile"] = job.profile
    png, text = encode_png_palette(image), json.dumps(fig_record, indent=1) + "\n"
    for folder in (Path(job.out) / spec.key, job.dest / spec.key):
        atomic_write_bytes(folder / FIGURE_PNG, png)
        atomic_write_text(folder / FIGURE_JSON, text)
    log(f"[reproduce] {spec.key}: {job.dest / spec.key / FIGURE_PNG} ({len(png) // 1024} KiB)")
    return 0


def reproduce(job: Reproduction, log: Log = _print) -> int:
    """The steps of the module docstring for ``job``; 0 when every run of the target finished (1 otherwise). A dry
    run lists what would run and writes nothing. Errors: ``RecordError`` (a record that cannot be used),
    ``WriteError``, ``OutputPathError``, and the real set's ``ValueError``."""
    status = 0
    target = job.target
    budget = None  # counted from here: the stand-in set's build is part of the minutes
    if job.time_budget_min is not None:
        dest = job.dest
        budget = TimeBudget.minutes(
            job.time_budget_min, estimate=lambda spec: run_estimate(dest, spec, job.run_minutes)
        )
    if target is not None:
        ensure_realset(job.realset_dir, job.profile, dry_run=job.dry_run, log=log)

        dynrange_runs = {run_name(row, seed) for row in TABLES["dynrange"] for seed in job.seeds}

        def record(outcome) -> None:  # commit each finished run at once: an interrupted target keeps it
            write_truth_record(outcome.run_dir, job.realset_dir, log=log)
            write_regions_record(outcome.run_dir, log=log)
            if copy_records([outcome.run_dir], job.dest):
                figure = None
                if outcome.run_dir.name in dynrange_runs:  # a study run, or a Table 3 run the study shares
                    figure = lambda: write_dynrange_figure(job.dest)  # noqa: E731
                elif target.kind == "study" and target.name == "schedule":
                    figure = lambda: write_schedule_figure(job.dest, job.seeds)  # noqa: E731
                write_page(job.results, job.page, before=figure)

        if target.key == "fig6":
            status = validation_figure(job, log)
        elif target.kind == "figure":
            status = qualitative_figure(job, record, log)
        else:
            specs = table_specs(target.key, job.seeds, job.overrides())
            if job.skip_recorded:
                specs = without_recorded(
                    specs,
                    job.dest,
                    log,
                    rerun_earlier=job.rerun_earlier,
                    rerun_without_truth=job.rerun_without_truth,
                )
            # several runs at a time would each build the same data: it is prepared once first (or alone)
            if not job.dry_run and (job.prepare_only or getattr(job.executor, "workers", 1) > 1):
                prepared = prepare_grid_data([s for s in specs if not run_finished(Path(job.out) / s.name)], log=log)
                if job.prepare_only:
                    log(
                        f"[reproduce] --prepare-only: data of {len(prepared)} distinct config(s) prepared; nothing "
                        "trained"
                    )
                    return 0
            outcomes = run_all(
                specs,
                job.out,
                dry_run=job.dry_run,
                after_each=None if job.dry_run else record,
                executor=job.executor,
                budget=budget,
            )
            left = [o.spec.name for o in outcomes if o.status in ("deferred", "stopped")]
            if left:
                log(f"[reproduce] the time budget left {len(left)} run(s) for another call: {', '.join(left)}")
            if not job.dry_run:
                write_report(job.dest)
            status = 0 if all(o.status in ("done", "skipped", "planned") for o in outcomes) else 1
        if job.dry_run:  # a dry run writes nothing
            return status
    # the page alone (--page-only) redraws the study figures too: they are the records' as much as the page is
    write_page(job.results, job.page, before=(lambda: write_study_figures(job.results)) if target is None else None)
    log(f"[reproduce] wrote {job.page}")
    return status
