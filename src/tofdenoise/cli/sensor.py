"""`tofdenoise sensor`: sensor calibration, depth uncertainty, simulated and real capture sets.

Sub-commands are contributed by small modules, each with one job:
- `tofdenoise.cli.sensor_physics`: show-calib, sigma, calibrate, validate
- `tofdenoise.cli.sensor_captures`: simulate-calibration, simulate-captures, simulate-validation, realset
  (`tofdenoise.data_modules.realset`), build-reference
Each module exposes `add_commands(subparsers)`; every sub-parser sets `func(args) -> int`.
"""

from __future__ import annotations

import argparse
import os
import sys

from tofdenoise.atomic import WriteError
from tofdenoise.cli import sensor_captures, sensor_physics


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tofdenoise sensor",
        description="iToF sensor tools: calibration, per-pixel depth uncertainty, capture sets.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sensor_physics.add_commands(sub)
    sensor_captures.add_commands(sub)
    return parser


#: exit status when the reader of stdout went away (`tofdenoise sensor show-calib | head`): 128 + SIGPIPE,
#: what a shell reports for a process killed by a broken pipe
EXIT_BROKEN_PIPE = 141


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()
        return status
    except BrokenPipeError:
        # the reader closed the pipe: stop quietly; stdout goes to devnull so the interpreter's final flush of
        # the unwritten output does not fail again at exit
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return EXIT_BROKEN_PIPE
    except (FileNotFoundError, ValueError, KeyError, WriteError) as exc:
        print(f"tofdenoise sensor {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
