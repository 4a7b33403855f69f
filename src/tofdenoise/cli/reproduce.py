"""``tofdenoise-reproduce``: run one of the paper's tables (resumable) and rebuild ``docs/results.md``.

    tofdenoise-reproduce --table 3 --profile cpu --seeds 0 1 2      # make reproduce TABLE=3 PROFILE=cpu SEEDS=0,1,2
    tofdenoise-reproduce --table fig6 --profile cpu                  # the noise-model validation figure
    tofdenoise-reproduce --table fig7                                # qualitative figures (fig7 synthetic, fig8 real)
    tofdenoise-reproduce --table 1 --dry-run                         # list what would run
    tofdenoise-reproduce --page-only                                 # rebuild docs/results.md from docs/results/
    tofdenoise-reproduce --table 3 --executor local --workers 2      # two runs at a time on this machine
    tofdenoise-reproduce --table 3 --profile gpu --executor slurm --slurm-partition gpu \
        --extra data.source_kwargs.root=...                          # a SLURM job array (docs/cluster.md)

Steps: (1) the stand-in real set, once per profile: a second simulated camera (other frequency, contrast,
harmonics, dark level, gain, mixed pixels at depth edges) writes its calibration captures and its capture set,
and ``tofdenoise-sensor calibrate`` estimates its calibration (``<out>/realset``; docs/camera-tutorial.md);
(2) every run of the table, trained with that calibration and tested on the synthetic split and on that capture
set (finished runs are skipped, interrupted ones resume, a failing run does not stop the others and is listed);
(3) each finished run's ``metrics.json`` and ``run_info.json`` copied to ``docs/results/<profile>/<run>/``;
(4) ``docs/results.md`` rebuilt from those records. Where the runs of step (2) go is ``--executor`` (sequential, local
workers, a SLURM array: ``tofdenoise.experiments.executors``); the records and the page are the same whichever ran
them, and each run is committed by this command as it ends. The page is rebuilt under a lock
(``atomic.exclusive_lock``), so two commands committing runs at once cannot drop one's run from it.
Exit status 0 when every run of the table finished; 2 when
``--page`` would replace what the page is built from (the discussion, a record: ``tofdenoise.output_guard``,
checked before anything runs) or when a record cannot be used (``reporting.results_page.RecordError``, naming the
file; a run without a record is listed on the page as missing).
``fig7`` / ``fig8`` (the qualitative figures) train the runs of their columns for the first seed when missing,
then render the figure from those runs' best checkpoints (``tofdenoise.experiments.figures``), check it against
the runs' per-image records and commit ``figure.png`` and ``figure.json`` to ``docs/results/<profile>/<fig>/``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from tofdenoise.atomic import WriteError, atomic_write_bytes, atomic_write_text, exclusive_lock
from tofdenoise.cli.executor_args import add_executor_arguments, executor_from_args
from tofdenoise.paths import REPO_ROOT
from tofdenoise.records import METRICS_NAME, PER_IMAGE_DIR, RUN_INFO_NAME

__all__ = ["main", "build_parser", "PROFILES", "profile_needs", "profile_overrides"]

#: profile -> Hydra overrides shared by every training run of a table
PROFILES: dict[str, tuple[str, ...]] = {
    "cpu": ("experiment=reproduce_cpu",),
    # the paper's settings (Sec. V-A): ToF-FlyingThings3D (data.source_kwargs.root=...), 320 crops, batch 4, 300
    # epochs, one GPU
    "gpu": ("experiment=paper", "logger=csv"),
}
#: the stand-in real set of each profile: capture-set size (scenes, height, width)
REALSET_SIZES: dict[str, tuple[int, int, int]] = {"cpu": (24, 128, 160), "gpu": (200, 480, 640)}


def profile_overrides(profile: str, realset_dir: Path, extra: list[str]) -> list[str]:
    """The overrides of every run: the profile's experiment, the second camera's calibration and capture set."""
    return [
        *PROFILES[profile],
        f"++data.sensor={realset_dir / 'calibration.yaml'}",
        f"++data.real_dir={realset_dir / 'captures'}",
        *extra,
    ]


def profile_needs(profile: str, extra: list[str], cuda_available: bool | None = None) -> str:
    """What ``profile`` needs that is missing ("" when nothing): the GPU profile trains on ToF-FlyingThings3D
    (``--extra data.source_kwargs.root=FOLDER``, an existing folder) on a CUDA GPU (``experiment=paper`` sets
    ``trainer=gpu``)."""
    if profile != "gpu":
        return ""
    import torch

    roots = [e.split("=", 1)[1] for e in extra if e.lstrip("+").startswith("data.source_kwargs.root=")]
    if not roots:
        return "the ToF-FlyingThings3D folder: --extra data.source_kwargs.root=/path/to/ToF-FlyingThings3D"
    if not Path(roots[-1]).expanduser().is_dir():
        return f"an existing data.source_kwargs.root folder (ToF-FlyingThings3D), got {roots[-1]}"
    if not (torch.cuda.is_available() if cuda_available is None else cuda_available):
        return "a CUDA GPU (experiment=paper trains with trainer=gpu); torch.cuda.is_available() is False here"
    return ""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tofdenoise-reproduce",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--table",
        choices=["1", "2", "3", "dynrange", "fig6", "fig7", "fig8"],
        help="which table (dynrange: the dynamic-range study, beyond the paper), or figure (fig6: noise-model "
        "validation; fig7 / fig8: qualitative, synthetic / real)",
    )
    p.add_argument("--profile", choices=sorted(PROFILES), default="cpu")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--out", type=Path, default=None, help="run folders (default runs/reproduce/<profile>)")
    p.add_argument(
        "--results",
        type=Path,
        default=REPO_ROOT / "docs" / "results",
        help="where the run records are committed (default docs/results)",
    )
    p.add_argument("--page", type=Path, default=REPO_ROOT / "docs" / "results.md", help="the results page")
    p.add_argument(
        "--extra", nargs="*", default=[], help="extra Hydra overrides for every run (e.g. data.source_kwargs.root=...)"
    )
    p.add_argument("--dry-run", action="store_true", help="print what would run, run nothing")
    p.add_argument("--page-only", action="store_true", help="only rebuild the results page from the records")
    add_executor_arguments(p)
    return p


def _run(cmd: list[str], what: str) -> None:
    print(f"[reproduce] {what}: {' '.join(cmd)}", flush=True)
    proc = subprocess.run(cmd, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"tofdenoise-reproduce: {what} failed (exit {proc.returncode}): {' '.join(cmd)}")


def realset_command(realset_dir: Path, profile: str) -> list[str]:
    """``tofdenoise-sensor realset``: the second camera's calibration captures, their calibration and its capture
    set (docs/camera-tutorial.md); finished steps and complete scenes are skipped, so it is cheap to repeat."""
    scenes, height, width = REALSET_SIZES[profile]
    return [
        sys.executable,
        "-m",
        "tofdenoise.cli.sensor",
        "realset",
        "--out",
        str(realset_dir),
        "--scenes",
        str(scenes),
        "--height",
        str(height),
        "--width",
        str(width),
    ]


def ensure_realset(realset_dir: Path, profile: str, dry_run: bool = False) -> None:
    cmd = realset_command(realset_dir, profile)
    if dry_run:
        print(f"[reproduce] would run the stand-in real set: {' '.join(cmd)}")
    else:
        _run(cmd, "the stand-in real set (second camera)")


#: what a finished run leaves in docs/results/<profile>/<run>/ (small files; checkpoints and panels stay in runs/)
RECORD_FILES = (
    METRICS_NAME,
    RUN_INFO_NAME,
    "config.yaml",
    "csv/metrics.csv",
    f"{PER_IMAGE_DIR}/synthetic.csv",
    f"{PER_IMAGE_DIR}/real.csv",
)


def copy_records(run_dirs: list[Path], dest: Path) -> list[str]:
    """Copy each finished run's records (``RECORD_FILES`` that exist) to ``dest/<run>/`` atomically; the names."""
    from tofdenoise.records import run_finished

    copied = []
    for run_dir in run_dirs:
        if not run_finished(run_dir):
            continue
        for name in RECORD_FILES:
            if (run_dir / name).is_file():
                atomic_write_bytes(dest / run_dir.name / name, (run_dir / name).read_bytes())
        copied.append(run_dir.name)
    return copied


def write_report(dest: Path) -> None:
    """The offline HTML report of the recorded runs (``dest/report.html``), when there are any."""
    if any(dest.glob(f"*/{METRICS_NAME}")):
        _run(
            [
                sys.executable,
                "-m",
                "tofdenoise.cli.report",
                str(dest),
                "--out",
                str(dest / "report.html"),
                "--title",
                f"tofdenoise: paper tables, {dest.name} profile",
            ],
            "HTML report",
        )


def write_dynrange_figure(dest: Path, seeds: list[int]) -> None:
    """The dynamic-range study's gain figure from the committed records (``dest/dynrange/gains.png``)."""
    from tofdenoise.experiments.dynrange import gain_figure_png, gains
    from tofdenoise.reporting.results_page import DYNRANGE_FIGURE, load_records

    records = load_records(dest)
    items = gains(lambda name: (records.get(name) or {}).get("metrics"), seeds)
    if items:
        atomic_write_bytes(dest / DYNRANGE_FIGURE, gain_figure_png(items))


def _fig6(args: argparse.Namespace, realset_dir: Path, dest: Path) -> int:
    cmd = [
        sys.executable,
        "-m",
        "tofdenoise.cli.sensor",
        "validate",
        "--out",
        str(args.out / "fig6"),
        "--sensor",
        str(realset_dir / "calibration.yaml"),
        "--captures",
        str(realset_dir / "validation"),
    ]
    if args.dry_run:
        print(f"[reproduce] would run fig6: {' '.join(cmd)}")
        return 0
    _run(cmd, "fig6 (noise-model validation on the second camera)")
    for name in ("validation.json", "validation.png"):
        atomic_write_bytes(dest / "fig6" / name, (args.out / "fig6" / name).read_bytes())
    return 0


def write_page(results: Path, page: Path, before: Any = None) -> str:
    """Rebuild ``page`` from the records under ``results`` under the page's lock (``before()`` first, inside it):
    a rebuild reads every record, so two commands committing runs at once must not interleave."""
    from tofdenoise.reporting.results_page import results_markdown

    with exclusive_lock(page):
        if before is not None:
            before()
        text = results_markdown(results)
        atomic_write_text(page, text)
    return text


def _qualitative(args: argparse.Namespace, realset_dir: Path, dest: Path, record: Any) -> int:
    """Fig. 7 / Fig. 8: the columns' runs for the first seed (trained when missing), then the rendered figure."""
    from tofdenoise.experiments.figures import (
        FIGURE_JSON,
        FIGURE_PNG,
        FIGURES,
        FigureMismatch,
        build_figure,
        encode_png_palette,
        figure_specs,
    )
    from tofdenoise.experiments.runner import run_all
    from tofdenoise.inference.denoise import CheckpointError

    spec, seed = FIGURES[args.table], args.seeds[0]
    specs = figure_specs(spec, seed, profile_overrides(args.profile, realset_dir, args.extra))
    outcomes = run_all(
        specs, args.out, dry_run=args.dry_run, after_each=None if args.dry_run else record, executor=args.executor_obj
    )
    if args.dry_run:
        print(f"[reproduce] would render {spec.key} from {', '.join(s.name for s in specs)}")
        return 0
    unfinished = [o.spec.name for o in outcomes if o.status not in ("done", "skipped")]
    if unfinished:
        print(f"[reproduce] {spec.key} not rendered: run(s) {', '.join(unfinished)} did not finish", flush=True)
        return 1
    try:
        image, fig_record = build_figure(spec, seed, specs, args.out)
    except (FigureMismatch, CheckpointError) as exc:  # a figure that would not show what the tables scored
        print(f"[reproduce] {spec.key} not rendered: {exc}", flush=True)
        return 1
    fig_record["profile"] = args.profile
    png, text = encode_png_palette(image), json.dumps(fig_record, indent=1) + "\n"
    for folder in (args.out / spec.key, dest / spec.key):
        atomic_write_bytes(folder / FIGURE_PNG, png)
        atomic_write_text(folder / FIGURE_JSON, text)
    print(f"[reproduce] {spec.key}: {dest / spec.key / FIGURE_PNG} ({len(png) // 1024} KiB)", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    from tofdenoise.output_guard import OutputPathError, check_output_file
    from tofdenoise.reporting.results_page import RecordError, page_inputs

    args = build_parser().parse_args(argv)
    if not args.page_only and args.table is None:  # a usage error: exit 2, as argparse's own
        print(
            "tofdenoise-reproduce: error: give --table 1|2|3|dynrange|fig6|fig7|fig8 (or --page-only)", file=sys.stderr
        )
        return 2
    try:
        args.executor_obj = executor_from_args(args)
    except (ValueError, RuntimeError) as exc:
        print(f"tofdenoise-reproduce: error: {exc}", file=sys.stderr)
        return 2
    try:
        # the page is rebuilt from the discussion and the records: it may never replace one of them
        check_output_file(args.page, (".md",), page_inputs(args.results), what="--page", shadow=False)
        return _reproduce(args)
    except (OutputPathError, RecordError, WriteError) as exc:
        print(f"tofdenoise-reproduce: error: {exc}", file=sys.stderr)
        return 2


def _reproduce(args: argparse.Namespace) -> int:
    from tofdenoise.experiments.runner import run_all
    from tofdenoise.experiments.tables import table_specs

    status = 0
    if not args.page_only:
        # a SLURM array trains on the cluster's GPUs: the submitting machine needs none
        missing = profile_needs(args.profile, args.extra, cuda_available=True if args.executor == "slurm" else None)
        if missing:  # before the real set is built or any run starts, in a dry run too
            print(f"tofdenoise-reproduce: error: --profile {args.profile} needs {missing}", file=sys.stderr)
            return 2
        args.out = (args.out or REPO_ROOT / "runs" / "reproduce" / args.profile).expanduser().resolve()
        realset_dir = args.out / "realset"
        dest = args.results / args.profile
        ensure_realset(realset_dir, args.profile, dry_run=args.dry_run)

        def record(outcome) -> None:  # commit each finished run at once: an interrupted table keeps it
            if copy_records([outcome.run_dir], dest):
                figure = (lambda: write_dynrange_figure(dest, args.seeds)) if args.table == "dynrange" else None
                write_page(args.results, args.page, before=figure)

        if args.table == "fig6":
            status = _fig6(args, realset_dir, dest)
        elif args.table in ("fig7", "fig8"):
            status = _qualitative(args, realset_dir, dest, record)
        else:
            specs = table_specs(args.table, args.seeds, profile_overrides(args.profile, realset_dir, args.extra))
            outcomes = run_all(
                specs,
                args.out,
                dry_run=args.dry_run,
                after_each=None if args.dry_run else record,
                executor=args.executor_obj,
            )
            if not args.dry_run:
                write_report(dest)
            status = 0 if all(o.status in ("done", "skipped", "planned") for o in outcomes) else 1
        if args.dry_run:  # a dry run writes nothing
            return status
    write_page(args.results, args.page)
    print(f"[reproduce] wrote {args.page}", flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
