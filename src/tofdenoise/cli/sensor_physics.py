"""`tofdenoise sensor` physics sub-commands: show-calib, sigma, calibrate, validate (docs/physics.md)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from tofdenoise.output_guard import refuse_overwrite
from tofdenoise.paths import CONFIG_DIR

#: depths beyond this many unambiguous ranges are refused by `sigma`: the phase 4 pi f D / c of such a depth
#: is a huge float whose fractional part (all an iToF camera measures) is no longer meaningful (float32
#: resolves it to ~2 mm at 1e4 ranges, float64 keeps digits only by accident), and no camera sees that far
MAX_UNAMBIGUOUS_RANGES: float = 1e6


def _presets() -> list[str]:
    return sorted(p.stem for p in (Path(CONFIG_DIR) / "sensor").glob("*.yaml"))


def _calib(args: argparse.Namespace) -> Any:
    from tofdenoise.physics.calibration import resolve_calibration

    spec = getattr(args, "sensor", None)
    if spec is not None and not Path(spec).suffix and not Path(spec).exists() and spec not in _presets():
        raise ValueError(
            f"--sensor {spec!r}: no such file and no preset of that name; presets: "
            f"{', '.join(_presets())} (configs/sensor/), or give a .yaml/.json calibration file"
        )
    return resolve_calibration(spec)


def _json_float(value: float) -> float | None:
    """A strict-JSON number: NaN and +-inf become null."""
    value = float(value)
    return value if math.isfinite(value) else None


def cmd_show_calib(args: argparse.Namespace) -> int:
    calib = _calib(args)
    if args.json:
        print(json.dumps(calib.to_dict(), indent=2))
        return 0
    tr = calib.tap_response
    print(f"calibration: {args.sensor or 'default (configs/sensor/default.yaml)'}")
    print(f"  fingerprint            {calib.fingerprint()[:16]}")
    print(f"  taps N                 {calib.num_taps}")
    print(
        f"  modulation frequency   {calib.modulation_frequency_hz / 1e6:g} MHz "
        f"(unambiguous range {calib.unambiguous_range_mm:.1f} mm)"
    )
    print(f"  tap response           c0={tr.c0:g} cos={list(tr.cos)} sin={list(tr.sin)} (contrast {tr.contrast:.3f})")
    print(f"  dark offset / std      {calib.dark_mean_e:g} e- / {calib.dark_std_e:g} e-")
    print(f"  signal interval        [{calib.signal_min_e:g}, {calib.signal_max_e:g}] e-")
    print(f"  full well              {calib.full_well_e:g} e-")
    print(
        f"  ADC gain               {calib.adc_gain_e_per_dn if calib.adc_gain_e_per_dn is not None else 'none'} e-/DN"
    )
    rs = calib.range_sigma_mm
    print(
        "  range-aware sigma(D)   "
        + ("none" if rs is None else f"{rs[0]:.4g} + {rs[1]:.4g} D + {rs[2]:.4g} D^2 mm (D in mm)")
    )
    return 0


def pair_lists(depth_mm: list[float], signal_e: list[float]) -> list[tuple[float, float]]:
    """Element-wise pairs; a list of length 1 is repeated to the other's length; other mismatches fail."""
    nd, ns = len(depth_mm), len(signal_e)
    if nd == ns:
        return list(zip(depth_mm, signal_e))
    if nd == 1:
        return [(depth_mm[0], s) for s in signal_e]
    if ns == 1:
        return [(d, signal_e[0]) for d in depth_mm]
    raise ValueError(
        f"--depth-mm has {nd} values and --signal-e has {ns}; give the same number (paired element by element) "
        f"or a single value for one of them"
    )


def cmd_sigma(args: argparse.Namespace) -> int:
    import numpy as np

    from tofdenoise.physics.uncertainty import sigma_depth_mm

    calib = _calib(args)
    pairs = pair_lists(args.depth_mm, args.signal_e)
    d = np.array([p[0] for p in pairs], dtype=np.float64)
    a = np.array([p[1] for p in pairs], dtype=np.float64)
    limit = MAX_UNAMBIGUOUS_RANGES * calib.unambiguous_range_mm
    too_far = np.isfinite(d) & (np.abs(d) > limit)
    if too_far.any():
        raise ValueError(
            f"--depth-mm {d[too_far][0]:g} is {abs(d[too_far][0]) / calib.unambiguous_range_mm:.3g} unambiguous "
            f"ranges ({calib.unambiguous_range_mm:.1f} mm at {calib.modulation_frequency_hz / 1e6:g} MHz); depths "
            f"beyond {MAX_UNAMBIGUOUS_RANGES:.0e} ranges ({limit:.4g} mm) have no meaningful phase and are refused"
        )
    s = sigma_depth_mm(d, a, calib)
    rows = [
        {"depth_mm": _json_float(di), "signal_e": _json_float(ai), "sigma_mm": _json_float(si)}
        for di, ai, si in zip(d, a, s)
    ]
    print(json.dumps(rows, indent=None if len(rows) > 20 else 2, allow_nan=False))
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from tofdenoise.physics.calibrate import calibrate_to_file

    # the calibration file may not replace a file of the capture folders it is computed from (their index.json)
    refuse_overwrite([args.out], [f for f in (args.sweep, args.dark, args.distances) if f is not None])
    lo, hi = args.signal_percentiles
    report, path = calibrate_to_file(
        args.sweep,
        args.dark,
        args.distances,
        args.out,
        num_harmonics=args.harmonics,
        full_well_e=args.full_well_e,
        lower_percentile=lo,
        upper_percentile=hi,
        sweep_amplitude=args.sweep_amplitude,
    )
    if report.clipped_samples:
        worst = sorted(report.clipped_by_file.items(), key=lambda kv: -kv[1])[:3]
        print(
            f"tofdenoise sensor calibrate: warning: {report.clipping_summary()} (most in "
            f"{', '.join(f'{f} ({n})' for f, n in worst)})",
            file=sys.stderr,
        )
    for warning in report.warnings:
        print(f"tofdenoise sensor calibrate: warning: {warning}", file=sys.stderr)
    print(f"wrote {path} (dark: {report.dark_frames} frames, sweep: {report.sweep_points} steps)")
    print(json.dumps(report.calibration.to_dict(), indent=2))
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    from tofdenoise.physics.validation import VALIDATION_FILES, ValidationSettings, validate_to_folder

    refuse_overwrite(
        [Path(args.out) / name for name in VALIDATION_FILES],
        [*input_files(args.sensor), *([args.captures] if args.captures else [])],
    )

    simulation = [
        name
        for name, given in (
            ("--quick", args.quick),
            ("--frames", args.frames is not None),
            ("--roi-px", args.roi_px is not None),
            ("--seed", args.seed is not None),
        )
        if given
    ]
    if args.captures and simulation:  # they set the simulated stacks; captured ones are measured as they are
        raise ValueError(
            f"{', '.join(simulation)}: settings of the simulated validation, which --captures replaces (the "
            "captured stacks are measured as recorded, every frame and pixel of the index)"
        )
    calib = _calib(args)
    settings = ValidationSettings.quick() if args.quick else ValidationSettings()
    if args.frames is not None:
        settings.num_frames = args.frames
    if args.roi_px is not None:
        settings.roi_px = args.roi_px
    if args.seed is not None:
        settings.seed = args.seed
    result, json_path, png = validate_to_folder(calib, args.out, settings, captures_dir=args.captures)
    print(f"source: {result.source}")
    print(
        f"range-aware baseline: sigma(D) = {result.range_sigma_mm[0]:.4g} + {result.range_sigma_mm[1]:.4g} D "
        f"+ {result.range_sigma_mm[2]:.4g} D^2 mm ({result.range_sigma_source})"
    )
    if result.left_out:
        names = [f"{c['group']} {c['distance_mm']:g} mm {c['surface']} x{c['exposure']:g}" for c in result.left_out]
        print(
            f"tofdenoise sensor validate: warning: {len(names)} condition(s) without a pixel valid in every frame "
            f"left out of the metrics and the range-aware fit: {', '.join(names)}",
            file=sys.stderr,
        )
    print(f"{'panel':<10}{'model':<16}{'MAPE %':>9}{'R^2':>9}{'n':>5}")
    for panel, metrics in [("pooled", result.pooled), *result.panels.items()]:
        for model, m in metrics.items():
            print(f"{panel:<10}{model:<16}{m['mape_percent']:>9.2f}{m['r2']:>9.3f}{m['n']:>5d}")
    print(f"wrote {json_path} and {png}")
    return 0


def input_files(spec: str | None) -> list[Path]:
    """A calibration given as a file (not a preset name or the default) as the input it is: what no output of the
    command may replace."""
    return [Path(spec)] if spec is not None and Path(spec).expanduser().exists() else []


def _float_list(name: str):
    def parse(text: str) -> float:
        try:
            return float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: expected a number, got {text!r}") from None

    return parse


def add_commands(subparsers: Any) -> None:
    calib_help = (
        "calibration file (.yaml/.json) or preset name in configs/sensor (default: configs/sensor/default.yaml)"
    )

    p = subparsers.add_parser(
        "show-calib",
        help="print the sensor calibration",
        description="Print the sensor calibration (as JSON with --json).",
    )
    p.add_argument("--sensor", default=None, help=calib_help)
    p.add_argument("--json", action="store_true", help="print JSON with the calibration's field names")
    p.set_defaults(func=cmd_show_calib)

    p = subparsers.add_parser(
        "sigma",
        help="per-pixel depth uncertainty sigma_D for (depth, signal) pairs",
        description="Print a JSON list of {depth_mm, signal_e, sigma_mm}. The two lists are paired element by "
        "element; if one has a single value it is used with every value of the other. Invalid "
        "inputs (<= 0, nan, inf) give sigma_mm null (non-finite inputs are printed as null too); "
        "depths beyond 1e6 unambiguous ranges are refused.",
    )
    p.add_argument("--depth-mm", nargs="+", type=_float_list("--depth-mm"), required=True, metavar="D")
    p.add_argument("--signal-e", nargs="+", type=_float_list("--signal-e"), required=True, metavar="A")
    p.add_argument("--sensor", default=None, help=calib_help)
    p.set_defaults(func=cmd_sigma)

    p = subparsers.add_parser(
        "calibrate",
        help="calibrate a sensor from capture folders",
        description="Fit the tap response (phase sweep), dark offset/noise (emitter-off frames), signal interval "
        "and, with --distances, the range-aware baseline. Folder format: docs/physics.md.",
    )
    p.add_argument("--sweep", required=True, help="phase-sweep capture folder (index.json kind 'sweep')")
    p.add_argument("--dark", required=True, help="emitter-off capture folder (index.json kind 'dark')")
    p.add_argument("--distances", default=None, help="planar distance sequence (index.json kind 'distances')")
    p.add_argument("--out", required=True, help="output calibration file (.yaml or .json)")
    p.add_argument("--harmonics", type=int, default=3, help="Fourier harmonics K of c(x) (default 3)")
    p.add_argument(
        "--full-well-e", type=float, default=None, help="full-well capacity [e-] (else from the sweep index)"
    )
    p.add_argument(
        "--signal-percentiles",
        type=float,
        nargs=2,
        default=(1.0, 99.0),
        metavar=("LO", "HI"),
        help="percentiles of the returned signal giving [signal_min_e, signal_max_e] (default 1 99)",
    )
    p.add_argument(
        "--sweep-amplitude",
        choices=("auto", "common", "per-step"),
        default="auto",
        help="tap-response fit over the sweep: common (a target at a fixed distance, the same signal at every step: "
        "every harmonic fitted), per-step (a moving target: each step normalised by its own level, harmonics at "
        "multiples of the tap count not recoverable); auto (default): common when every sweep entry gives "
        "phase_rad, per-step when an entry gives only distance_mm",
    )
    p.set_defaults(func=cmd_calibrate)

    p = subparsers.add_parser(
        "validate",
        help="noise-model validation (paper Sec. IV / Fig. 6)",
        description="Planar target 500..1500 mm and black/gray/white surfaces at 1500 mm under 4 exposures; "
        "proposed WLS model vs range-aware Gaussian; writes validation.json and validation.png.",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--sensor", default=None, help=calib_help)
    p.add_argument(
        "--captures", default=None, help="real capture folder (index.json kind 'validation'); default: simulate"
    )
    p.add_argument("--quick", action="store_true", help="50 frames, 16x16 ROI (instead of 200 frames, 32x32)")
    p.add_argument("--frames", type=int, default=None, help="repeated frames per condition (override)")
    p.add_argument("--roi-px", type=int, default=None, help="ROI side in pixels (override)")
    p.add_argument("--seed", type=int, default=None, help="random seed of the measured sequences")
    p.set_defaults(func=cmd_validate)
