"""``docs/results.md`` from the committed run records under ``docs/results/<profile>/`` (one function, one page).

Every finished run of ``tofdenoise reproduce`` leaves its ``metrics.json`` and ``run_info.json`` in
``docs/results/<profile>/<run>/``. :func:`results_markdown` rebuilds the whole page from those files (and the
hand-written discussion ``docs/results/discussion.md``), so the page can always be checked against the records:
``tofdenoise reproduce --page-only`` rewrites it, and a test checks that the committed page equals the output.

Per table: one line per row with the paper's number next to our mean ± standard deviation over the seeds that
finished (``n``), the runs of the table that have no record yet (listed, never dropped silently), then the paper's
orderings with the seeds in which each holds.

A record that exists but cannot be used is a :class:`RecordError` naming the file, never a run that quietly
leaves the page: a truncated or non-JSON ``metrics.json`` / ``run_info.json`` (or ``validation.json``,
``figure.json``), one that breaks the ``metrics.json`` schema, one without its ``synthetic`` set, or a ``null`` or
NaN metric. ``page_inputs(results_dir)`` names what the page is built from, so the page never replaces it
(``tofdenoise.output_guard``).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from tofdenoise.experiments.dynrange import Gain, gains
from tofdenoise.experiments.figures import FIGURES, stale_columns
from tofdenoise.experiments.schedule import CURVES_FIGURE, SHORT_EPOCHS, gap_table, schedule_curves
from tofdenoise.experiments.tables import (
    CLAIMS,
    DATA_SEED,
    DYNRANGE_BACKBONES,
    REGION_PREFIXES,
    SCHEDULE_EPOCHS,
    SIM_SET,
    TABLE_COLUMNS,
    TABLE_PROFILES,
    TABLE_TITLES,
    TABLES,
    TRUTH_SET,
    Claim,
    Row,
    chain_units,
    claim_holds,
    claim_steps,
    column_metric,
    column_source,
    pooled_steps,
    region_set,
    row_values,
    run_name,
)
from tofdenoise.experiments.targets import target_of_key
from tofdenoise.records import (
    EDGE_JUMP_MM,
    METRIC_KEYS,
    METRICS_NAME,
    PER_IMAGE_DIR,
    REGIONS_NAME,
    RUN_INFO_NAME,
    TRUTH_NAME,
    RecordError,
    cpu_label,
    learned_status,
    load_scored_metrics,
    matched_on_whole_maps,
    read_per_image_csv,
    read_record,
    record_commit,
    record_machine,
    run_fields,
)
from tofdenoise.reporting.intervals import BOOTSTRAP_SEED, LEVEL, RESAMPLES, StepInterval, step_interval
from tofdenoise.reporting.numbers import format_number
from tofdenoise.reporting.table import LEARNED_FLAGS

__all__ = [
    "DISCUSSION_NAME",
    "comparable_metrics",
    "gains_markdown",
    "record_protocol",
    "PROFILE_SEEDS",
    "load_records",
    "page_inputs",
    "results_markdown",
    "run_minutes",
    "seeds_present",
]

#: the seeds each profile's tables are produced with (quoted on the page: ``Target.make_command``)
PROFILE_SEEDS = {"cpu": "0,1,2", "gpu": "0,1,2", "gpu-short": "0"}
RUN_FILES = (METRICS_NAME, RUN_INFO_NAME)


#: the hand-written discussion, read from the results folder and placed above the tables
DISCUSSION_NAME = "discussion.md"


def _truth_set(path: Path) -> dict[str, Any] | None:
    """The ``truth_`` columns' metric set from a run's ``real_vs_truth.json`` (None without the file): the restored
    maps' mean against the truth, ``raw`` the input frames'. A file without them is a RecordError naming it."""
    data = read_record(path)
    if data is None:
        return None
    try:
        truth, raw = data["truth"]["mean"], data["input"]["truth"]["mean"]
        return {**{k: truth[k] for k in METRIC_KEYS}, "raw": {k: raw[k] for k in METRIC_KEYS}}
    except (KeyError, TypeError) as exc:
        raise RecordError(
            f"{path}: expected the truth scores of tofdenoise evaluate --ckpt on a simulated capture set "
            f"('truth.mean' and 'input.truth.mean' with {', '.join(METRIC_KEYS)}); missing {exc}"
        ) from None


def _truth_units(path: Path) -> dict[str, dict[str, float]] | None:
    """Per scene of a run's ``real_vs_truth.json``: ``{key: {scene: value}}`` for the restored maps against the
    truth and ``raw_<key>`` for the input frames (None without the file or without per-scene scores; scores that
    are there but cannot be read are a RecordError naming the file)."""
    data = read_record(path)
    if data is None or "images" not in (data.get("truth") or {}):
        return None  # no per-scene scores: the run's steps get no interval over scenes
    try:
        restored, raw = data["truth"]["images"], data["input"]["truth"]["images"]
        out = {k: {u: float(v[k]) for u, v in restored.items()} for k in METRIC_KEYS}
        out.update({f"raw_{k}": {u: float(v[k]) for u, v in raw.items()} for k in METRIC_KEYS})
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise RecordError(
            f"{path}: expected per-scene truth scores ('truth.images' and 'input.truth.images', each scene with "
            f"{', '.join(METRIC_KEYS)}); {type(exc).__name__}: {exc}"
        ) from None
    return out


def _region_records(path: Path) -> tuple[dict[str, Any], dict[str, dict[str, dict[str, float]]]]:
    """A run's ``regions.json`` as metric sets and per-image units (both empty without the file): for each scored
    set and region, ``{"<set>/<region>": {key..., "raw": {key...}}}`` (the restored maps' means and the input's) and
    ``{"<set>/<region>": {key or raw_<key>: {image: value}}}``. A set whose rebuilt inputs did not score as the
    run's record (``inputs_as_recorded`` false: other test images) is left out. A file without the expected layout
    is a RecordError naming it."""
    data = read_record(path)
    sets: dict[str, Any] = {}
    units: dict[str, dict[str, dict[str, float]]] = {}
    if data is None:
        return sets, units
    try:
        for set_name, scored in data["sets"].items():
            if not scored.get("inputs_as_recorded"):
                continue
            for region in REGION_PREFIXES.values():
                restored, raw = scored["restored"]["regions"][region], scored["input"]["regions"][region]
                name = region_set(set_name, region)
                sets[name] = {
                    **{k: restored["mean"][k] for k in METRIC_KEYS},
                    "raw": {k: raw["mean"][k] for k in METRIC_KEYS},
                }
                per: dict[str, dict[str, float]] = {}
                for prefix, result in (("", restored), ("raw_", raw)):
                    for k in METRIC_KEYS:
                        values = {u: v[k] for u, v in result["images"].items()}
                        if values and all(isinstance(v, float) and math.isfinite(v) for v in values.values()):
                            per[prefix + k] = values
                units[name] = per
    except (KeyError, TypeError, AttributeError) as exc:
        raise RecordError(
            f"{path}: expected tofdenoise evaluate --run --edge-jump-mm's result ('sets' -> set -> 'restored' and "
            f"'input' with 'regions' {', '.join(REGION_PREFIXES.values())}); {type(exc).__name__}: {exc}"
        ) from None
    return sets, units


def _csv_units(path: Path) -> dict[str, dict[str, float]] | None:
    """Per image of a run's ``per_image/<set>.csv``: ``{column: {image name: value}}`` for every metric column
    (``raw_<key>`` too), None without the file; a file that cannot be read is a RecordError naming it."""
    if not path.is_file():
        return None
    try:
        rows = read_per_image_csv(path)
    except (OSError, ValueError) as exc:
        raise RecordError(f"{path}: the per-image record cannot be read ({exc})") from None
    keys = [*METRIC_KEYS, *(f"raw_{k}" for k in METRIC_KEYS)]
    out: dict[str, dict[str, float]] = {}
    for key in keys:
        values = {r["name"]: r.get(key) for r in rows if r.get("name")}
        if values and all(isinstance(v, float) and math.isfinite(v) for v in values.values()):
            out[key] = values
    return out


def _per_image_units(
    run_dir: Path, region_units: dict[str, dict[str, dict[str, float]]] | None = None
) -> dict[str, dict[str, dict[str, float]]]:
    """A run's per-unit records by set: ``{set: {key: {image or scene: value}}}`` (synthetic, simulator-noised and
    real from ``per_image/``, the real set against its truth from ``real_vs_truth.json``, the regions from
    ``region_units``, :func:`_region_records`'s); sets without a record left out."""
    found = {name: _csv_units(run_dir / PER_IMAGE_DIR / f"{name}.csv") for name in ("synthetic", SIM_SET, "real")}
    found[TRUTH_SET] = _truth_units(run_dir / TRUTH_NAME)
    found.update(region_units or {})  # read with the region metric sets (load_records): the file is read once
    return {name: units for name, units in found.items() if units}


def load_records(profile_dir: Path | str) -> dict[str, dict[str, Any]]:
    """``{run name: {"metrics": dict, "run_info": dict, "per_image": {set: {key: {unit: value}}}}}`` for every run
    folder holding both files (``per_image``: :func:`_per_image_units`). A folder without both (an interrupted
    copy: ``metrics.json`` is copied first) is no record: its run is listed as missing on the page. A file that is
    there but cannot be used is a RecordError naming it (module docstring)."""
    profile_dir = Path(profile_dir)
    records: dict[str, dict[str, Any]] = {}
    if not profile_dir.is_dir():
        return records
    for run_dir in sorted(p for p in profile_dir.iterdir() if p.is_dir()):
        metrics_path, info_path = run_dir / METRICS_NAME, run_dir / RUN_INFO_NAME
        if not (metrics_path.exists() and info_path.exists()):
            continue  # not a run (fig6/, fig7/, ...) or an incomplete copy: missing
        info = read_record(info_path)
        metrics = load_scored_metrics(metrics_path)
        truth = _truth_set(run_dir / TRUTH_NAME)
        if truth is not None:
            metrics[TRUTH_SET] = truth
        region_sets, region_units = _region_records(run_dir / REGIONS_NAME)
        metrics.update(region_sets)
        per_image = _per_image_units(run_dir, region_units)
        records[run_dir.name] = {"metrics": metrics, "run_info": info, "per_image": per_image}
    return records


def page_inputs(results_dir: Path | str) -> list[Path]:
    """What :func:`results_markdown` reads: the discussion (whether it exists or not) and every profile folder."""
    results_dir = Path(results_dir)
    return [results_dir / DISCUSSION_NAME, *(results_dir / profile for profile in PROFILE_SEEDS)]


def seeds_present(records: dict[str, dict[str, Any]]) -> list[int]:
    """The seeds of the recorded runs, sorted."""
    seeds = set()
    for name in records:
        stem, _, tail = name.rpartition("-s")
        if stem and tail.isdigit():
            seeds.add(int(tail))
    return sorted(seeds)


def run_minutes(run_info: dict[str, Any]) -> float:
    """Wall-clock minutes from ``started`` to ``finished`` (NaN when either is missing or unparsable, and for a
    resumed run: its span includes the time it was stopped, and nothing records how long that was)."""
    if run_info.get("resumed"):
        return math.nan
    try:
        t0 = datetime.strptime(run_info["started"], "%Y-%m-%dT%H:%M:%S%z")
        t1 = datetime.strptime(run_info["finished"], "%Y-%m-%dT%H:%M:%S%z")
    except (KeyError, TypeError, ValueError):
        return math.nan
    return (t1 - t0).total_seconds() / 60.0


def _row_cell(row: Row, values: Sequence[float], decimals: int) -> str:
    """A row's value: one number for a seed-independent row whose seeds agree (the same inputs or the same run,
    not n independent results), else the mean ± std over the seeds."""
    finite = [v for v in values if math.isfinite(v)]
    if row.seed_independent and finite and all(math.isclose(v, finite[0], rel_tol=1e-9) for v in finite):
        return f"{finite[0]:.{decimals}f} (seed-independent)"
    return _mean_std(values, decimals)


def _mean_std(values: Sequence[float], decimals: int) -> str:
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return "-"
    if len(finite) == 1:
        return f"{finite[0]:.{decimals}f} (n=1)"
    return f"{statistics.fmean(finite):.{decimals}f} ± {statistics.stdev(finite):.{decimals}f} (n={len(finite)})"


def _steps_text(claim: Claim, seeds: list[int], metrics_of: Any, complete: int) -> str:
    """The chain's steps (``claim_steps``) over its ``complete`` seeds (those with a verdict) as text, e.g.
    ``+0.100 ± 0.020, -0.020 ± 0.030 mm (n=3)``: each step's mean over the seeds ± the standard deviation of its
    per-seed difference; a step within that spread is seed noise, whatever its sign."""
    steps = claim_steps(claim, seeds, metrics_of)
    if not steps:
        return "-"
    unit = " mm" if claim.metric.endswith("_mm") else ""
    if complete == 1:
        return ", ".join(f"{d:+.3f}" for d, _ in steps) + unit + " (one seed)"
    return ", ".join(f"{d:+.3f} ± {sd:.3f}" for d, sd in steps) + unit + f" (n={complete})"


#: what a set's test units are called on the page
UNIT_WORDS = {"synthetic": "images", SIM_SET: "images", "real": "scenes", TRUTH_SET: "scenes"}

#: the test protocol of a record: ``CURRENT`` (the simulator-noised test split scored beside the paper's hetero-
#: noised one, the 200-scene stand-in set, the Gaussians' variance matched on the training pixels as the training
#: crops cover them, Gaussian centring and harmonic hole fill) or ``EARLIER``: every record without a simulator-noised
#: split (commits 10fd18c and a9fec53, 24 stand-in scenes), and a Gaussian baseline whose variance was matched on
#: whole maps (records before 2026-11-29: a random crop covers a map's border, darker and noisier, less often than its
#: centre, so those baselines trained on 13-32 % more variance than hetero). Records of two protocols are never
#: compared.
CURRENT, EARLIER = "current", "earlier"
#: how the page marks a row whose records are of the earlier protocol
EARLIER_MARK = "†"


def record_protocol(record: dict[str, Any]) -> str:
    """:data:`CURRENT` when the record scored the simulator-noised split and, for a variance-matched Gaussian
    baseline, was matched over the training crops' coverage; else :data:`EARLIER`."""
    if SIM_SET not in record["metrics"] or matched_on_whole_maps(record.get("run_info")):
        return EARLIER
    return CURRENT


def _protocol_filter(
    table: str, seeds: list[int], records: dict[str, dict[str, Any]]
) -> tuple[dict[str, dict[str, Any]], set[str]]:
    """The records a table shows: per row, only its current-protocol runs when it has any (a row never averages
    two protocols over its seeds), and the names of the runs left out."""
    shown = dict(records)
    left_out: set[str] = set()
    for row in TABLES[table]:
        names = [run_name(row, s) for s in seeds]
        present = [n for n in names if n in records]
        if any(record_protocol(records[n]) == CURRENT for n in present):
            for n in present:
                if record_protocol(records[n]) == EARLIER:
                    shown.pop(n, None)
                    left_out.add(n)
    return shown, left_out


def comparable_metrics(tables: Sequence[str], seeds: list[int], records: dict[str, dict[str, Any]]) -> Any:
    """``metrics_of(run name)`` over the records that ``tables``' rows show (:func:`_protocol_filter`), less the
    runs of any of their orderings whose seed mixes two protocols (:func:`_chain_comparable`)."""
    shown = dict(records)
    for table in tables:
        kept, _ = _protocol_filter(table, seeds, records)
        shown = {name: rec for name, rec in shown.items() if name in kept}
    excluded: set[str] = set()
    for claim in CLAIMS:
        if claim.table in tables:
            excluded |= _chain_comparable(claim, seeds, shown)[0]

    def metrics_of(name: str) -> dict[str, Any] | None:
        rec = shown.get(name)
        return rec["metrics"] if rec and name not in excluded else None

    return metrics_of


def _chain_comparable(claim: Claim, seeds: list[int], records: dict[str, dict[str, Any]]) -> tuple[set[str], list]:
    """The runs of ``claim``'s chain to leave out because, within their seed, the chain's records are of two
    protocols (that seed is then no evidence either way), and those seeds."""
    rows = {r.key: r for r in TABLES[claim.table]}
    excluded: set[str] = set()
    mixed = []
    for s in seeds:
        names = {run_name(rows[k], s) for k in claim.chain}
        names = {n for n in names if n in records}
        if len({record_protocol(records[n]) for n in names}) > 1:
            excluded |= names
            mixed.append(s)
    return excluded, mixed


def claim_intervals(claim: Claim, seeds: list[int], metrics_of: Any, units_of: Any) -> list[StepInterval | None]:
    """Per step of ``claim``'s chain, the step over the test images or scenes (``reporting.intervals``: each unit's
    step averaged over the seeds that :func:`claim_steps` pairs, its bootstrap interval and the share of units where
    it holds); ``[]`` when a run of those seeds has no per-image record."""
    chain = chain_units(claim, seeds, metrics_of, units_of)
    if chain is None:
        return []
    return [step_interval(a, b) for a, b in zip(chain, chain[1:])]


def _intervals_text(claim: Claim, intervals: list[StepInterval | None]) -> tuple[str, str]:
    """The ordering's two test-set cells: each step's bootstrap interval (``[+0.21, +0.45] mm``) and the share of
    units where it holds (``79 %, 60 % of 48 images``)."""
    if not intervals or any(i is None for i in intervals):
        return "-", "-"
    unit = " mm" if claim.metric.endswith("_mm") else ""
    spans = ", ".join(f"[{i.low:+.3f}, {i.high:+.3f}]" for i in intervals) + unit
    counts = {i.units for i in intervals}
    word = UNIT_WORDS[column_source(claim.metric)[0].partition("/")[0]]
    shares = ", ".join(f"{100 * i.share:.0f} %" for i in intervals)
    return spans, f"{shares} of {'/'.join(str(n) for n in sorted(counts))} {word}"


def _column_header(column: str) -> str:
    """A table column's header: the metric's, prefixed ``real`` for the real set (``real MAE (mm)↓``), ``real
    vs truth`` for the real set scored against its rendered truth and ``simulator-noised`` for the synthetic test
    split captured by the tap-level simulator (the unprefixed synthetic columns are the paper's protocol)."""
    set_name, _ = column_source(column)
    base, _, region = set_name.partition("/")
    prefix = {"real": "real ", TRUTH_SET: "real vs truth ", SIM_SET: "simulator-noised "}.get(base, "")
    where = {"off_edge": "off-edge ", "edge": "edge "}.get(region, "")
    return prefix + where + column_metric(column).text


def _table_section(table: str, profile: str, all_records: dict[str, dict[str, Any]], seeds: list[int]) -> list[str]:
    records, left_out = _protocol_filter(table, seeds, all_records)
    excluded: set[str] = set()  # runs of a chain whose seed mixes protocols (set per claim below)

    def metrics_of(name: str) -> dict[str, Any] | None:
        rec = records.get(name)
        return rec["metrics"] if rec and name not in excluded else None

    def units_of(name: str, set_name: str, key: str) -> dict[str, float] | None:
        rec = records.get(name)
        if not rec or name in excluded:
            return None
        return ((rec.get("per_image") or {}).get(set_name) or {}).get(key)

    cols = TABLE_COLUMNS[table]
    lines = [
        f"## {TABLE_TITLES[table]}",
        "",
        f"Command: `{target_of_key(table).make_command(profile, PROFILE_SEEDS[profile])}` (profile `{profile}`).",
        "",
    ]
    head = ["method"] + [f"{_column_header(c)} paper / ours" for c in cols]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    earlier_rows = 0
    for row in TABLES[table]:
        present = [records[n] for n in (run_name(row, s) for s in seeds) if n in records]
        earlier = bool(present) and all(record_protocol(r) == EARLIER for r in present)
        earlier_rows += earlier
        cells = [f"{row.label} {EARLIER_MARK}" if earlier else row.label]
        for c in cols:
            decimals = column_metric(c).decimals
            paper = row.paper.get(c)
            ours = _row_cell(row, row_values(row, seeds, metrics_of, c), decimals)
            cells.append(f"{'-' if paper is None else format(paper, f'.{decimals}f')} / {ours}")
        lines.append("| " + " | ".join(cells) + " |")
    missing = sorted({run_name(row, s) for row in TABLES[table] for s in seeds} - set(all_records))
    if missing:
        lines += ["", f"Missing runs (no record in `results/{profile}/`): {', '.join(missing)}."]
    if earlier_rows:
        lines += [
            "",
            f"{EARLIER_MARK} Records of an earlier protocol (no simulator-noised split, 24 stand-in scenes, the "
            "Gaussians matched on all valid pixels, local centring and pull-push fill; or a Gaussian baseline "
            "variance-matched on whole maps, not as the training crops cover them): not comparable with the "
            "unmarked rows, and no ordering below compares the two.",
        ]
    if left_out:
        lines += [
            "",
            f"Not shown: earlier-protocol records of rows that have current ones: {', '.join(sorted(left_out))}.",
        ]
    claims = [c for c in CLAIMS if c.table == table]
    lines += [
        "",
        "| the paper's ordering | holds in seeds | verdict | steps along it: mean ± std of the per-seed difference "
        f"| {100 * LEVEL:.0f} % interval of each step over the test images / scenes | share of images / scenes where "
        "each step holds |",
        "|---|---|---|---|---|---|",
    ]
    for claim in claims:
        excluded, mixed = _chain_comparable(claim, seeds, records)
        verdicts = {s: claim_holds(claim, s, metrics_of) for s in seeds}
        known = {s: v for s, v in verdicts.items() if v is not None}
        held = [s for s, v in known.items() if v]
        if not known and mixed:
            verdict = "not compared (two protocols)"
        elif not known:
            verdict = "not run"
        elif len(held) == len(known):
            verdict = "holds in every seed" + ("" if len(known) == len(seeds) and len(known) >= 3 else " run so far")
        elif held:
            verdict = "mixed"
        else:
            verdict = "does not hold"
        seeds_text = ", ".join(
            [f"{s}: {'yes' if v else 'no'}" for s, v in known.items()] + [f"{s}: two protocols" for s in mixed]
        )
        seeds_text = seeds_text or "-"
        steps_text = _steps_text(claim, seeds, metrics_of, len(known))
        spans, shares = _intervals_text(claim, claim_intervals(claim, seeds, metrics_of, units_of))
        lines.append(f"| {claim.text} | {seeds_text} | {verdict} | {steps_text} | {spans} | {shares} |")
    lines.append("")
    return lines


DYNRANGE_FIGURE = "dynrange/gains.png"


def _dynrange_section(profile_dir: Path, records: dict[str, dict[str, Any]], seeds: list[int]) -> list[str]:
    """The dynamic-range study's paired gains (``tofdenoise.experiments.dynrange``) and its figure; a seed whose
    runs of one world are of two protocols is left out of that world's gains."""
    metrics_of = comparable_metrics(["dynrange"], seeds, records)

    lines = [
        "### Hetero's gain over the Gaussian baselines across the dynamic range",
        "",
        "Paired by seed: MAE(fixed or range) - MAE(hetero) in mm on the world's own synthetic test split (> 0: hetero "
        "is better), mean ± std over the seeds in which all three runs of the world finished; the real columns are "
        "the same on the stand-in capture set (a camera with fixed-pattern noise and vignetting that the training "
        "world lacks).",
        "",
        *gains_markdown(gains(metrics_of, seeds)),
    ]
    if (profile_dir / DYNRANGE_FIGURE).is_file():
        lines += [f"![hetero's gain against the dynamic range](results/{profile_dir.name}/{DYNRANGE_FIGURE})", ""]
    return lines


def _schedule_section(profile_dir: Path, seeds: list[int]) -> list[str]:
    """The long-schedule study's gaps along training (``tofdenoise.experiments.schedule``) and its figure."""
    curves = schedule_curves(profile_dir, seeds)
    lines = [
        "### Does the gap between the training noises open, hold or close with training length?",
        "",
        "Paired by seed on identical validation inputs: MAE(fixed or range) - MAE(hetero) of the validation MAE "
        f"(mm; > 0: hetero better) at the end of the short schedule ({SHORT_EPOCHS} epochs, the profile's own) and "
        f"at the end of the long one ({SCHEDULE_EPOCHS} epochs), from each run's `csv/metrics.csv`.",
        "",
    ]
    rows = gap_table(curves, SCHEDULE_EPOCHS)
    if not rows:
        return lines + ["No seed has all of its curves yet.", ""]
    lines += ["| seed | baseline | gap at short end (step) | gap at long end (step) |", "|---|---|---|---|"]
    for r in rows:
        short = "-" if r["short_gap_mm"] is None else f"{r['short_gap_mm']:+.3f} ({r['short_step']})"
        lines.append(f"| {r['seed']} | {r['baseline']} | {short} | {r['end_gap_mm']:+.3f} ({r['end_step']}) |")
    lines.append("")
    if (profile_dir / CURVES_FIGURE).is_file():
        lines += [f"![validation curves of the long schedule](results/{profile_dir.name}/{CURVES_FIGURE})", ""]
    return lines


def _pooled_text(steps: list[tuple[float, float | None]], n: int, unit: str) -> str:
    """Pooled steps (``tables.pooled_steps``) as ``+m ± sd, ... unit (n=N)``; ``-`` when there are none."""
    if not steps:
        return "-"
    return ", ".join(f"{m:+.3f}" + ("" if sd is None else f" ± {sd:.3f}") for m, sd in steps) + f"{unit} (n={n})"


def _dataseed_section(records: dict[str, dict[str, Any]], seeds: list[int]) -> list[str]:
    """Table III's orderings on each data seed and pooled over both (``tables.pooled_steps``): the spread over every
    (data seed, training seed) pair covers the world, the split and the test inputs as well as the training. A
    seed whose runs of an ordering are of two protocols is left out of it, and the two data seeds pool the records
    of one protocol (the current one once any record has it)."""
    metrics_of = comparable_metrics(["3", "dataseed"], seeds, records)
    names = {run_name(row, s) for table in ("3", "dataseed") for row in TABLES[table] for s in seeds}
    present = [records[n] for n in names if n in records and metrics_of(n) is not None]
    use = CURRENT if any(record_protocol(r) == CURRENT for r in present) else EARLIER

    def pooled_metrics_of(name: str) -> dict[str, Any] | None:  # the two data seeds pool one protocol
        rec = records.get(name)
        return metrics_of(name) if rec and record_protocol(rec) == use else None

    pairs = [
        (first, second)
        for first in CLAIMS
        if first.table == "3"
        for second in CLAIMS
        if second.table == "dataseed" and second.text == first.text
    ]
    lines = [
        f"### Table III's orderings over both data seeds (data.seed = 0 and {DATA_SEED})",
        "",
        "Each step: mean ± standard deviation of the paired difference (a step > 0 holds) over the training seeds of "
        "one data seed, then over every (data seed, training seed) pair of both; the last column counts the pairs "
        "in which the whole ordering holds.",
        "",
        f"| ordering | data seed 0 | data seed {DATA_SEED} | both data seeds | holds in pairs |",
        "|---|---|---|---|---|",
    ]
    for first, second in pairs:
        unit = " mm" if first.metric.endswith("_mm") else ""
        cells = []
        for claim in (first, second):
            steps, n, _ = pooled_steps([claim], seeds, metrics_of)
            cells.append(_pooled_text(steps, n, unit))
        steps, n, holds = pooled_steps([first, second], seeds, pooled_metrics_of)
        held = f"{holds} of {n}" if n else "-"
        lines.append(f"| {first.text} | {cells[0]} | {cells[1]} | {_pooled_text(steps, n, unit)} | {held} |")
    return lines + [""]


#: the profiles whose Table III the page sets side by side: the CPU's small crops and the paper's crop size
PROFILE_COMPARISON = ("cpu", "gpu-short")


def _profiles_section(records_of: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    """Table III's orderings at the CPU profile and at the paper's crop size (``gpu-short``), side by side: per
    profile the mean ± standard deviation over its training seeds of each step's paired difference, and in how many
    seeds the whole ordering holds; nothing when the GPU profile has no Table III record. Each profile's cell is
    what its own section's ordering table says; the two are never pooled (other crops, steps, precision and test
    split). ``records_of``: each profile's records (``load_records``)."""
    columns = []
    for profile in PROFILE_COMPARISON:
        records = records_of.get(profile, {})
        seeds = seeds_present(records) or [0, 1, 2]
        columns.append((profile, seeds, comparable_metrics(["3"], seeds, records)))
    claims = [claim for claim in CLAIMS if claim.table == "3"]
    if not any(pooled_steps([claim], columns[-1][1], columns[-1][2])[1] for claim in claims):
        return []
    lines = [
        "# Table III at both profiles",
        "",
        "The paper's orderings of Table III at the `cpu` profile (64 x 64 crops, 432 steps, float32, data seed 0) and "
        "at `gpu-short` (the paper's 320 x 320 crops, batch, optimiser and bf16, 450 steps): per step, the mean ± "
        "standard deviation over the profile's training seeds of the paired difference (> 0: the step holds), and "
        "in how many of those seeds the whole ordering holds. The per-image intervals are in each profile's own "
        "section below.",
        "",
        f"| ordering | `{PROFILE_COMPARISON[0]}` | holds in seeds | `{PROFILE_COMPARISON[1]}` | holds in seeds |",
        "|---|---|---|---|---|",
    ]
    for claim in claims:
        unit = " mm" if claim.metric.endswith("_mm") else ""
        cells = []
        for _, seeds, metrics_of in columns:
            steps, n, holds = pooled_steps([claim], seeds, metrics_of)
            cells += [_pooled_text(steps, n, unit), f"{holds} of {n}" if n else "-"]
        lines.append(f"| {claim.text} | {' | '.join(cells)} |")
    return lines + [""]


def _pm(ms: tuple[float, float]) -> str:
    mean, std = ms
    if not math.isfinite(mean):
        return "-"
    return f"{mean:+.3f}" + (f" ± {std:.3f}" if math.isfinite(std) else "")


def gains_markdown(items: list[Gain]) -> list[str]:
    """A Markdown table of the dynamic-range study's gains (one line per backbone and world)."""
    if not items:
        return ["No complete seed of any world yet.", ""]
    lines = [
        "| backbone | world | n | hetero MAE (mm) | gain over fixed (mm) | gain over range (mm) "
        "| real: over fixed | real: over range |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for g in items:
        lines.append(
            f"| {DYNRANGE_BACKBONES[g.backbone]} | {g.label} | {g.n} | {g.hetero_mae:.3f} | {_pm(g.over_fixed)} "
            f"| {_pm(g.over_range)} | {_pm(g.real_over_fixed)} | {_pm(g.real_over_range)} |"
        )
    return [*lines, ""]


#: the paper's recipe in optimiser steps: 300 epochs of its 3,750 training crops (6,250 ToF-FlyingThings3D samples split
#: 6:2:2) in batches of 4, the last partial batch of an epoch dropped as the training loader does (937 steps an epoch)
PAPER_RECIPE_STEPS = 300 * (3750 // 4)
#: the profiles that train the paper's recipe per step (320 crops, batch 4, one GPU): their runs' rate prices it
RECIPE_PROFILES = ("gpu", "gpu-short")


def recipe_hours(train_seconds: Any, trained_steps: Any) -> float | None:
    """Hours of training for ``PAPER_RECIPE_STEPS`` at a run's measured rate (its training seconds per optimiser
    step; validation not included); None when either is unknown."""
    try:
        rate = float(train_seconds) / float(trained_steps)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return rate * PAPER_RECIPE_STEPS / 3600.0 if math.isfinite(rate) and rate > 0 else None


def machine_label(run_info: dict[str, Any]) -> str:
    """A record's machine in a few words: the GPU's name, or the CPU's model with its vendor family/model, the
    intra-op threads (``2 thr``) and, where the executor trained several runs at a time on it, its worker count (``up
    to 3 runs at once``: the run's rate is a shared machine's; fewer may have run beside it at the end of a time
    budget); "-" for a record without ``machine``."""
    machine = record_machine(run_info)
    if machine is None:
        return "-"
    head = str(machine["gpu"]) if machine.get("gpu") else cpu_label(machine)
    threads, at_once = machine.get("torch_threads"), machine.get("runs_at_once")
    shared = f", up to {at_once} runs at once" if isinstance(at_once, int) and at_once > 1 else ""
    return (head or "unnamed") + (f", {threads} thr" if threads else "") + shared


def _runs_section(records: dict[str, dict[str, Any]], profile: str = "cpu") -> list[str]:
    recipe = profile in RECIPE_PROFILES
    lines = [
        "## Runs",
        "",
        "Wall minutes: from start to finish (validation and test included). Not shown for a resumed run: its span "
        "includes the stop, and its data order differs from an uninterrupted run after the stop (docs/training.md, "
        "resuming), so a fresh run of it is not bit-identical. Training minutes, images/s and peak memory (GPU / "
        "process, GiB) come from the `TrainingCost` callback: the training epochs only, summed over resumes "
        "(records written before it existed show -). Protocol: the test protocol the run was scored under "
        "(current: with the simulator-noised split; earlier: before it, see the tables' † notes). Machine: what the "
        "run trained on (its `run_info.json`'s `machine`: CPU or GPU, intra-op threads, and how many runs shared it "
        "where an executor trained several at a time; - for records made before it was recorded): minutes and "
        "images/s compare only on one machine not shared with other runs, and CPU training reruns bit for bit only "
        "on the same CPU kind and thread count."
        + (
            f" Paper's recipe: hours of training for its 300 epochs ({PAPER_RECIPE_STEPS:,} optimiser steps of 4 "
            "crops of 320 x 320) at the run's measured rate (training seconds per step), validation not included."
            if recipe
            else ""
        ),
        "",
        "| run | protocol | learned | trained steps | best val MAE (mm) | raw val MAE (mm) | wall minutes | training "
        "minutes | images/s | peak memory GiB (GPU / process) | machine |"
        + (" paper's recipe (h) |" if recipe else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if recipe else ""),
    ]
    for name, rec in records.items():
        m, info = rec["metrics"], rec["run_info"]
        # the learned guard's verdict: "yes", "classical" (a tuned filter, nothing to learn) or a red flag
        status = learned_status(run_fields(m))
        shown = f"{name} (resumed)" if info.get("resumed") else name
        train_s = info.get("train_seconds")
        memory = (
            f"{format_number(info.get('peak_gpu_memory_gib'), 1)} / {format_number(info.get('peak_rss_gib'), 1)}"
            if "peak_rss_gib" in info
            else "-"
        )
        lines.append(
            f"| {shown} | {record_protocol(rec)} | {LEARNED_FLAGS[status]} | "
            f"{m.get('trained_steps', '-')} | {format_number(m.get('best_val_mae_mm') or math.nan, 2)} | "
            f"{format_number(m.get('raw_val_mae_mm') or math.nan, 2)} | {format_number(run_minutes(info), 1)} | "
            f"{format_number(None if train_s is None else float(train_s) / 60.0, 1)} | "
            f"{format_number(info.get('train_images_per_second'), 1)} | {memory} | {machine_label(info)} |"
            + (f" {format_number(recipe_hours(train_s, m.get('trained_steps')), 1)} |" if recipe else "")
        )
    lines.append("")
    return lines


def written_line(provenance: Any) -> str:
    """A figure record's provenance in one sentence (``validation.json``'s ``provenance``: when, at which commit,
    on which machine), or that the record is older than its provenance."""
    if not isinstance(provenance, dict):
        return "Written before figure records named their commit and machine."
    commit = record_commit(provenance)
    written = str(provenance.get("written") or "-")[:10]
    code = (
        f"commit {commit[:7]}" + (" with uncommitted changes" if provenance.get("commit_dirty") else "")
        if commit
        else f"package version {provenance.get('version') or 'unknown'}"
    )
    return f"Written {written}, {code}, on {machine_label(provenance)}."


def _fig6_section(profile_dir: Path) -> list[str]:
    data = read_record(profile_dir / "fig6" / "validation.json")
    lines = ["## Fig. 6: noise-model validation on the second camera", ""]
    if data is None:
        return lines + [f"Not run yet (`{target_of_key('fig6').make_command()}`).", ""]
    lines += [
        "Measured: the second camera's validation captures (`tofdenoise sensor simulate-validation --sensor "
        "cam75`); predicted: the calibration `tofdenoise sensor calibrate` estimated from that camera's own "
        "calibration captures; range-aware Gaussian: fitted on the independent range-fit sequence. Paper (its "
        "camera): proposed MAPE 7.7 %, R² 0.93 (pooled). " + written_line(data.get("provenance")),
        "",
        "| panel | model | MAPE % | R² | n |",
        "|---|---|---|---|---|",
    ]
    pooled = data.get("pooled") or {}
    for model in ("proposed", "range_gaussian"):
        p = pooled.get(model) or {}
        lines.append(
            f"| pooled | {model} | {format_number(p.get('mape_percent'), 2)} | "
            f"{format_number(p.get('r2'), 3)} | {p.get('n', '-')} |"
        )
    for panel, entry in (data.get("panels") or {}).items():
        for model in ("proposed", "range_gaussian"):
            p = (entry or {}).get(model) or {}
            lines.append(
                f"| {panel} | {model} | {format_number(p.get('mape_percent'), 2)} | "
                f"{format_number(p.get('r2'), 3)} | {p.get('n', '-')} |"
            )
    if (profile_dir / "fig6" / "validation.png").is_file():
        lines += ["", f"![Fig. 6: {profile_dir.name} profile](results/{profile_dir.name}/fig6/validation.png)"]
    lines.append("")
    return lines


def _qualitative_section(profile_dir: Path, key: str) -> list[str]:
    """A qualitative figure (``tofdenoise.experiments.figures``): its per-scene MAE table and the image."""
    data = read_record(profile_dir / key / "figure.json")
    if data is None:
        return [f"## {FIGURES[key].title}", "", f"Not run yet (`{target_of_key(key).make_command()}`).", ""]
    columns = [data["input"], *data["columns"]]
    runs = ", ".join(f"{label} = `{name}`" for label, name in data["runs"].items())
    lines = [
        f"## {data['title']}",
        "",
        f"Runs of seed {data['seed']}: {runs}. Ours is DVSS trained on the hetero synthesis with L_full, the "
        "paper's configuration. The scenes are evenly spaced through the test set, not chosen by result. Each "
        "prediction is the one the run's test scored: the figure is checked against every run's per-image "
        "record. Per scene, the top row is depth on one scale and the bottom row |map − "
        f"{data['reference']}| on one millimetre scale; grey pixels are invalid (holes, outside the scoring "
        f"region). {data.get('note', '')} {written_line(data.get('provenance'))}",
        "",
        f"| scene (MAE, mm) | {' | '.join(columns)} |",
        "|---|" + "---|" * len(columns),
    ]
    for scene in data["scenes"]:
        values = " | ".join(format_number(scene["mae_mm"][c], 2) for c in columns)
        lines.append(f"| {scene['name']} (index {scene['index']}) | {values} |")
    stale = stale_columns(data, {label: profile_dir / name for label, name in data["runs"].items()})
    if stale:
        named = ", ".join(f"{label} (`{data['runs'][label]}`)" for label in stale)
        lines += [
            "",
            f"**Out of date:** {named} trained again after this figure was drawn; the figure shows the earlier "
            "training's predictions, which that run's record no longer holds (the tables score the new training). "
            f"Drawn again by `{target_of_key(key).make_command()}` once every column's checkpoint is at hand.",
        ]
    if (profile_dir / key / "figure.png").is_file():
        lines += ["", f"![{data['title']}: {profile_dir.name} profile](results/{profile_dir.name}/{key}/figure.png)"]
    lines.append("")
    return lines


def _profile_sections(profile_dir: Path, records: dict[str, dict[str, Any]]) -> list[str]:
    profile = profile_dir.name
    seeds = seeds_present(records) or [0, 1, 2]
    lines = [
        f"# Profile `{profile}`",
        "",
        f"Seeds with records: {', '.join(map(str, seeds_present(records))) or 'none'}.",
        "",
    ]
    for table in TABLES:
        if profile not in TABLE_PROFILES.get(table, (profile,)):
            continue
        lines += _table_section(table, profile, records, seeds)
        if table == "dynrange":
            lines += _dynrange_section(profile_dir, records, seeds)
        if table == "schedule":
            lines += _schedule_section(profile_dir, seeds)
        if table == "dataseed":
            lines += _dataseed_section(records, seeds)
    lines += _fig6_section(profile_dir)
    for key in FIGURES:
        lines += _qualitative_section(profile_dir, key)
    return lines + _runs_section(records, profile)


def results_markdown(results_dir: Path | str) -> str:
    """The whole ``docs/results.md`` from ``results_dir`` (``docs/results``): the CPU profile always, the GPU
    profile when it has records, then the hand-written ``discussion.md``."""
    results_dir = Path(results_dir)
    lines = [
        "# Reproducing the paper's tables",
        "",
        "<!-- generated by `tofdenoise reproduce --page-only` from docs/results/; do not edit by hand "
        "(edit docs/results/discussion.md) -->",
        "",
        "Each cell: the paper's number / ours as mean ± standard deviation over the seeds (n = seeds that "
        "finished). Every run of a seed is validated and tested on identical inputs (`data.eval_noise=hetero`, "
        "synthesised from the data seed, not the run's seed); the real set is the second camera's capture set "
        "(docs/camera-tutorial.md). Rows that the training seed cannot change (the raw input, the classical "
        "filter: one run) show one value, marked seed-independent. Below each table, every ordering the paper "
        "reports is checked per seed. Its steps are paired by seed: the mean over the seeds of the per-seed "
        "difference from one row of the ordering to the next (positive = that step holds), ± the standard "
        "deviation of that difference. A step within that spread is seed noise, whatever its sign. That spread is "
        "over training seeds only: every run of a table shares one data seed, one split, one synthetic test split "
        "and one capture set; the data-seed study repeats Table III on a second data seed and pools both. Every "
        "record is of one test protocol (the runs table's protocol column): current (scored on the "
        "simulator-noised split too, with the 200-scene stand-in set) or earlier; a row whose records are all "
        f"earlier is marked {EARLIER_MARK}, and records of two protocols are never averaged or compared. The "
        "next two columns count the test set's side: per test image (synthetic) or scene (real "
        "set, and real set against its truth), the step on that image within a seed (the same image in both runs "
        "of the seed, from the runs' per-image records), averaged over the seeds; then the "
        f"{100 * LEVEL:.0f} % percentile interval of the mean of those per-image steps when the images or scenes "
        f"are resampled with replacement ({RESAMPLES:,} resamples, generator seed {BOOTSTRAP_SEED}: a paired "
        "bootstrap of the step's mean above), and the share of images or scenes whose seed-averaged step is "
        "positive. An interval that holds 0 is a step this test set cannot tell from none. "
        '"real vs truth": the same real-set predictions scored against the stand-in camera\'s rendered truth '
        "instead of "
        "its reference (the mean of its high-exposure frames, which keeps the camera's static errors), on the same "
        "pixels (each learned run's `real_vs_truth.json`, written by `tofdenoise reproduce` as it commits the run, "
        "the same as `tofdenoise evaluate --ckpt ... --captures ...`, or by the classical filter's own job; "
        "docs/evaluation.md); a real camera's set has no truth. The unprefixed synthetic columns are the paper's "
        "protocol: test inputs noised by the hetero model (the proposed method's own training generator). "
        '"simulator-noised": the same test scenes and targets, each captured once by the tap-level simulator '
        "(Poisson, dark and read noise, ADC, fixed-pattern noise, mixed pixels, atan2 demodulation; "
        "docs/data.md), a noise no training model generated; a run recorded before that split existed shows no "
        'value there. "off-edge": the same test images scored only on the pixels away from the target\'s depth '
        f"steps (no valid 8-neighbour more than {EDGE_JUMP_MM:.0f} mm away; each learned run's `regions.json`, "
        f"written by `tofdenoise reproduce` as it commits the run, the same as `tofdenoise evaluate --run RUN "
        f"--edge-jump-mm {EDGE_JUMP_MM:.0f}`; docs/evaluation.md): at a step the simulator's pixel mixes two "
        "surfaces (a flying pixel), an error no training noise model here describes, and a few such pixels carry "
        "most of an image's squared error.",
        "",
    ]
    discussion = results_dir / DISCUSSION_NAME
    if discussion.is_file():
        lines += [discussion.read_text().rstrip(), ""]
    records_of = {profile: load_records(results_dir / profile) for profile in PROFILE_SEEDS}
    lines += _profiles_section(records_of)
    for profile, records in records_of.items():
        if profile == "cpu" or records:
            lines += _profile_sections(results_dir / profile, records)
    return "\n".join(lines).rstrip() + "\n"
