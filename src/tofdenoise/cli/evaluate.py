"""``tofdenoise evaluate``: the unified depth metrics for depth maps produced by any method.

    tofdenoise evaluate --pred DIR --ref DIR [--mask DIR] --out FILE.json [--d-max-mm 1000]
    tofdenoise evaluate --ckpt best.ckpt --captures SCENES_DIR --sensor CALIBRATION [--min-count N] --out FILE.json
    tofdenoise evaluate --run RUN_DIR [--sets synthetic simulated real] [--precision P] --out FILE.json
    ... [--edge-jump-mm 50]   (any form: the edge and off-edge pixels scored apart too)

The second form restores every scene of a capture set with a checkpoint and scores it against each scene's
reference, as a run's ``real`` test set does, and, for a simulated set (``tofdenoise sensor realset``), against its
rendered truth too (``tofdenoise.inference.capture_eval``). A reference pixel needs ``--min-count`` valid
high-exposure frames (default: the checkpoint's run's ``data.real_min_count``, else half of each scene's frames).
Its JSON: ``{"checkpoint", "captures", "sensor", "min_count": {"value", "from"}, "scenes", "reference": RESULT,
"truth": RESULT or null, "input": {"reference", "truth"}, "reference_vs_truth"}`` (the input frames scored the same
way, and the references against the truth).

The third form scores a finished run's own test sets again, rebuilt from its ``config.yaml`` and restored with
its best checkpoint at the precision its test ran at (``trainer.precision``; ``--precision P`` for another;
``tofdenoise.inference.run_eval``): ``{"run", "checkpoint", "precision": {"value", "from"}, "sets": {name:
{"restored": R, "input": R}}}``; the whole-image means are the run's recorded test numbers. ``--edge-jump-mm T``
adds to every result ``regions``: the metrics over the pixels at a reference depth step > T mm (flying pixels, where
the camera mixes two surfaces) and over the rest (``tofdenoise.evaluation``).

Files are matched by stem; which files count, which pixels count, how non-finite predictions are counted and
the result's layout: :mod:`tofdenoise.evaluation` (``evaluate_dirs``). The result is written atomically as
strict JSON; non-finite predicted pixels are reported with a warning on stderr.

Errors (exit status 2) name the file: missing counterpart, shape mismatch, wrong dtype, unreadable file,
empty or missing folder, two files with the same stem, and an ``--out`` that is a folder, is not ``.json``,
or is one of the inputs (``tofdenoise.output_guard``).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from tofdenoise.atomic import WriteError, atomic_write_text
from tofdenoise.output_guard import OutputPathError, check_output_file

__all__ = ["build_parser", "main"]


def _input_files(*folders: Path | None) -> list[Path]:
    """Every file in the given (existing) input folders and their sub-folders (``evaluation.list_maps`` reads them
    all): what ``--out`` must never replace."""
    files: list[Path] = []
    for folder in folders:
        if folder is not None and Path(folder).is_dir():
            files += [p for p in Path(folder).rglob("*") if p.is_file()]
    return files


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tofdenoise evaluate",
        description="Unified depth metrics (PSNR with D_max, SSIM, MSE, MAE over valid pixels, per image then "
        "averaged) of predicted depth maps against references; files matched by name.",
    )
    p.add_argument("--pred", type=Path, default=None, help="folder of predicted depth maps (16-bit PNG mm or .npy)")
    p.add_argument("--ref", type=Path, default=None, help="folder of reference depth maps (same stems)")
    p.add_argument("--mask", type=Path, default=None, help="optional folder of masks (nonzero = evaluate)")
    p.add_argument("--ckpt", type=Path, default=None, help="a checkpoint to restore a capture set with (--captures)")
    p.add_argument("--captures", type=Path, default=None, help="a capture set (scene folders, docs/camera-tutorial.md)")
    p.add_argument("--sensor", default=None, help="the calibration of the camera that recorded --captures")
    p.add_argument(
        "--min-count",
        type=int,
        default=None,
        metavar="N",
        help="with --captures: valid high-exposure frames a reference pixel needs (default: the data.real_min_count "
        "of the checkpoint's run, as its real test set used it; else half of each scene's frames)",
    )
    p.add_argument(
        "--run",
        type=Path,
        default=None,
        help="a finished run's folder: score its own test sets again (its config.yaml, checkpoints/best.ckpt)",
    )
    p.add_argument(
        "--sets",
        nargs="+",
        default=None,
        metavar="SET",
        help="with --run: which test sets (synthetic, simulated, real; default: synthetic and simulated)",
    )
    p.add_argument("--device", default="auto", help="auto | cpu | cuda (with --ckpt or --run)")
    p.add_argument(
        "--precision",
        default=None,
        metavar="P",
        help="with --run: the precision to restore at, a Lightning name (32-true, bf16-mixed, 16-mixed, bf16-true, "
        "16-true, 64-true; default: the run's trainer.precision, as its test ran)",
    )
    p.add_argument("--out", required=True, type=Path, help="output JSON file")
    p.add_argument(
        "--d-max-mm",
        type=float,
        default=None,
        help="PSNR peak depth in mm (default: the paper's, tofdenoise.training.metrics.D_MAX_MM, 1000)",
    )
    p.add_argument(
        "--edge-jump-mm",
        type=float,
        default=None,
        metavar="MM",
        help="also score apart the pixels at a reference depth step above MM (flying pixels) and the rest "
        "(tofdenoise.training.metrics.EDGE_JUMP_MM is 50)",
    )
    return p


def _usage_error(args: argparse.Namespace) -> str:
    """What is wrong with the combination of options ("" when nothing): --pred/--ref or --ckpt/--captures/--sensor."""
    folders = {"--pred": args.pred, "--ref": args.ref, "--mask": args.mask}
    restore = {"--ckpt": args.ckpt, "--captures": args.captures, "--sensor": args.sensor}
    given = [k for k, v in {**folders, **restore, "--run": args.run}.items() if v is not None]
    if args.sets is not None and args.run is None:
        return "--sets goes with --run (a run's own test sets)"
    if args.precision is not None and args.run is None:
        return "--precision goes with --run (the precision a run's test sets are restored at)"
    if args.min_count is not None and args.captures is None:
        return "--min-count goes with --ckpt/--captures/--sensor (a capture set's references)"
    if args.min_count is not None and args.min_count < 1:
        return f"--min-count must be >= 1, got {args.min_count}"
    if args.run is not None:
        others = [k for k in given if k != "--run"]
        return f"give --run alone, without {' '.join(others)}" if others else ""
    if any(restore.values()):
        if any(folders.values()):
            return f"give --pred/--ref or --ckpt/--captures/--sensor, not both (got {' '.join(given)})"
        missing = [k for k, v in restore.items() if v is None]
        return f"--ckpt, --captures and --sensor go together; missing {', '.join(missing)}" if missing else ""
    if args.pred is None or args.ref is None:
        return "give --pred DIR --ref DIR (maps to score), --ckpt FILE --captures DIR --sensor CALIBRATION or --run DIR"
    return ""


def _evaluate_checkpoint(args: argparse.Namespace) -> dict:
    """The second form: a checkpoint restored on a capture set and scored (``inference.capture_eval``)."""
    from tofdenoise.evaluation import EvalInputError
    from tofdenoise.inference.capture_eval import evaluate_checkpoint  # heavy (torch, the model)

    try:
        return evaluate_checkpoint(
            args.ckpt,
            args.captures,
            args.sensor,
            args.device,
            args.d_max_mm,
            edge_jump_mm=args.edge_jump_mm,
            min_count=args.min_count,
        )
    except (FileNotFoundError, ValueError) as exc:  # CheckpointError and EvalInputError are ValueErrors
        raise EvalInputError(str(exc)) from exc


def _evaluate_run(args: argparse.Namespace) -> dict:
    """The third form: a run's own test sets rebuilt and scored again (``inference.run_eval``)."""
    from tofdenoise.evaluation import EvalInputError
    from tofdenoise.inference.run_eval import evaluate_run  # heavy (torch, hydra, the data module)

    try:
        return evaluate_run(
            args.run, args.sets, args.device, args.d_max_mm, args.edge_jump_mm, precision=args.precision
        )
    except (FileNotFoundError, ValueError) as exc:
        raise EvalInputError(str(exc)) from exc


def _fmt(v: float | str | None, digits: int) -> str:
    return "n/a" if v is None else (v if isinstance(v, str) else f"{v:.{digits}f}")


def _regions_line(result: dict) -> str:
    """`` (edge px 9.1 %: MAE 38.470 mm; off-edge MAE 2.291 mm)`` for a result with regions, else ""."""
    regions = result.get("regions")
    if not regions:
        return ""
    share = regions["edge_px_share"]
    edge, off_edge = regions["edge"]["mean"]["mae_mm"], regions["off_edge"]["mean"]["mae_mm"]
    return (
        f" (edge px {_fmt(None if share is None else 100 * share, 1)} %: MAE {_fmt(edge, 3)} mm; "
        f"off-edge MAE {_fmt(off_edge, 3)} mm)"
    )


def _print_run(result: dict, out: Path) -> None:
    used = result["precision"]
    print(f"precision {used['value']} (from {used['from']})")
    for name, scored in result["sets"].items():
        r, i = scored["restored"], scored["input"]
        print(
            f"{name}: {r['num_images']} images, MAE {_fmt(r['mean']['mae_mm'], 3)} mm, PSNR "
            f"{_fmt(r['mean']['psnr_db'], 2)} dB{_regions_line(r)}; input MAE {_fmt(i['mean']['mae_mm'], 3)} mm"
            f"{_regions_line(i)}"
        )
        if not scored["inputs_as_recorded"]:
            print(
                f"tofdenoise evaluate: warning: {name}: the rebuilt inputs do not score as the run's recorded raw "
                "numbers: this code rebuilds other test images than the run had (a run made by older data code), "
                "so these are not its record's numbers",
                file=sys.stderr,
            )
    print(f"-> {out}")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    usage = _usage_error(args)
    if usage:  # before the metrics (torch) are imported
        print(f"tofdenoise evaluate: error: {usage}", file=sys.stderr)
        return 2
    from tofdenoise.evaluation import EvalInputError, evaluate_dirs
    from tofdenoise.training.metrics import D_MAX_MM

    if args.d_max_mm is None:
        args.d_max_mm = D_MAX_MM
    try:
        if not args.d_max_mm > 0:
            raise EvalInputError(f"--d-max-mm must be > 0, got {args.d_max_mm}")
        if args.run is not None:
            check_output_file(args.out, (".json",), [p for p in Path(args.run).rglob("*") if p.is_file()])
            run_result = _evaluate_run(args)
        elif args.ckpt is not None:
            scene_dirs = [p for p in Path(args.captures).glob("*") if p.is_dir()] if args.captures.is_dir() else []
            inputs = [args.ckpt, Path(args.sensor), *_input_files(args.captures, *scene_dirs)]
            check_output_file(args.out, (".json",), inputs)
            captures = _evaluate_checkpoint(args)
            result = captures["reference"]
        else:
            check_output_file(args.out, (".json",), _input_files(args.pred, args.ref, args.mask))
            captures, result = None, evaluate_dirs(args.pred, args.ref, args.mask, args.d_max_mm, args.edge_jump_mm)
    except (EvalInputError, OutputPathError) as exc:
        print(f"tofdenoise evaluate: error: {exc}", file=sys.stderr)
        return 2
    if args.run is not None:
        try:
            atomic_write_text(args.out, json.dumps(run_result, indent=2, allow_nan=False) + "\n")
        except WriteError as exc:
            print(f"tofdenoise evaluate: error: {exc}", file=sys.stderr)
            return 2
        _print_run(run_result, args.out)
        return 0
    if result["nan_px"]:
        bad = [stem for stem, row in result["images"].items() if row["nan_px"]]
        failed = (
            f"; {len(result['failed'])} image(s) with no predicted depth at all (failed)" if result["failed"] else ""
        )
        print(
            f"tofdenoise evaluate: warning: {result['nan_px']} pixel(s) to evaluate hold no predicted depth "
            f"(0 = invalid, negative, NaN or inf) in {len(bad)} image(s) ({', '.join(bad[:5])}"
            f"{' ...' if len(bad) > 5 else ''}): failures, left out of the metrics and counted in nan_px{failed}",
            file=sys.stderr,
        )
    try:
        atomic_write_text(args.out, json.dumps(captures or result, indent=2, allow_nan=False) + "\n")
    except WriteError as exc:  # a full disk: one line naming the file, nothing half-written
        print(f"tofdenoise evaluate: error: {exc}", file=sys.stderr)
        return 2
    m = result["mean"]
    f = _fmt

    nan_note = f", {result['nan_px']} px without a predicted depth" if result["nan_px"] else ""
    against = ""
    if captures:
        used = captures["min_count"]
        need = "half of its frames" if used["value"] is None else f"{used['value']} frames"
        against = f" against the references (a reference pixel needs {need} valid; min_count from {used['from']})"
    print(
        f"{result['num_images']} images ({len(result['skipped'])} without valid pixels{nan_note}){against}: "
        f"PSNR {f(m['psnr_db'], 2)} dB, SSIM {f(m['ssim'], 4)}, MSE {f(m['mse_mm2'], 2)} mm^2, "
        f"MAE {f(m['mae_mm'], 3)} mm{_regions_line(result)} -> {args.out}"
    )
    if captures and captures["truth"] is not None:
        t = captures["truth"]["mean"]
        print(
            f"{captures['truth']['num_images']} images against the rendered truth (a simulated set): "
            f"PSNR {f(t['psnr_db'], 2)} dB, SSIM {f(t['ssim'], 4)}, MSE {f(t['mse_mm2'], 2)} mm^2, "
            f"MAE {f(t['mae_mm'], 3)} mm (the references themselves: "
            f"MAE {f(captures['reference_vs_truth']['mean']['mae_mm'], 3)} mm)"
        )
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
