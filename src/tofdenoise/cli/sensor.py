"""`tofdenoise-sensor`: sensor calibration, depth uncertainty, simulated and real capture sets.

Sub-commands are contributed by small modules, each with one job:
- `tofdenoise.cli.sensor_physics`: show-calib, sigma, calibrate, validate
- `tofdenoise.cli.sensor_captures`: simulate-captures, build-reference
Each module exposes `add_commands(subparsers)`; every sub-parser sets `func(args) -> int`.
"""

from __future__ import annotations

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    from tofdenoise.cli import sensor_captures, sensor_physics

    parser = argparse.ArgumentParser(
        prog="tofdenoise-sensor",
        description="iToF sensor tools: calibration, per-pixel depth uncertainty, capture sets.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sensor_physics.add_commands(sub)
    sensor_captures.add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (FileNotFoundError, ValueError, KeyError) as exc:
        print(f"tofdenoise-sensor {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
