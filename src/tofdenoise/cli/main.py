"""``tofdenoise <verb>``: the one command of the project (docs/architecture.md, "The command line").

Each verb is one small module of ``tofdenoise.cli`` with a ``main``; this file only picks it. The grammar a verb
takes follows what it does:

- verbs that **train** (``train``, ``classic``) compose the Hydra configs: ``key=value`` overrides
  (``tofdenoise train experiment=smoke backbone=unet``), multirun with ``-m``;
- ``fit``, ``validate``, ``test``, ``predict`` are Lightning's own CLI (``--config configs/cli/default.yaml``,
  ``--model.optim.lr 1e-4``) for users who know it;
- every other verb works on files and takes ``--options`` (argparse); a camera's calibration (a file or a preset
  name) is ``--sensor`` in every one of them, as it is ``data.sensor`` in the configs.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import sys
from collections.abc import Sequence
from dataclasses import dataclass

from tofdenoise import allocator
from tofdenoise.cli import help_cache

__all__ = ["VERBS", "main"]


@dataclass(frozen=True)
class Verb:
    module: str  # ``tofdenoise.cli.<module>`` with a ``main``
    summary: str
    grammar: str  # "hydra" or "lightning" (both read sys.argv), or "options" (``main(argv)``)


VERBS: dict[str, Verb] = {
    "train": Verb("train", "train a backbone on synthetic pairs (Hydra overrides; make train)", "hydra"),
    "classic": Verb("classic", "tune and test the classical filter row (Hydra overrides)", "hydra"),
    "fit": Verb("lightning_cli", "Lightning's CLI: fit (--config configs/cli/default.yaml)", "lightning"),
    "validate": Verb("lightning_cli", "Lightning's CLI: validate a checkpoint", "lightning"),
    "test": Verb("lightning_cli", "Lightning's CLI: test a checkpoint", "lightning"),
    "predict": Verb("lightning_cli", "Lightning's CLI: predict (writes restored depth)", "lightning"),
    "denoise": Verb("denoise", "restore depth frames or recordings with a checkpoint or an ONNX model", "options"),
    "export": Verb("export", "export a checkpoint's restore path to ONNX", "options"),
    "evaluate": Verb("evaluate", "score predicted depth against references (the paper's metrics)", "options"),
    "report": Verb("report", "one HTML report and a Markdown table of run folders", "options"),
    "grid": Verb("grid", "the robustness grid: run it or render its table", "options"),
    "reproduce": Verb("reproduce", "the paper's tables, figures and studies, and docs/results.md", "options"),
    "sensor": Verb("sensor", "calibration, sigma_D maps, simulated and real capture sets (subcommands)", "options"),
}


def usage() -> str:
    width = max(len(v) for v in VERBS)
    lines = ["usage: tofdenoise <verb> [arguments]   (tofdenoise <verb> --help for a verb's arguments)", "", "verbs:"]
    lines += [f"  {name:<{width}}  {verb.summary}" for name, verb in VERBS.items()]
    return "\n".join(lines)


def _lightning_help(name: str, rest: list[str]) -> int:
    """``tofdenoise fit --help`` (or another Lightning verb's): the stored text when the code and the packages are
    those it was built from (``tofdenoise.cli.help_cache``), else LightningCLI's own, which is then stored."""
    text = help_cache.read_help(name, rest)
    if text is None:
        run = importlib.import_module(f"tofdenoise.cli.{VERBS[name].module}").main
        buffer, saved = io.StringIO(), sys.argv
        sys.argv = ["tofdenoise", name, *rest]
        try:
            with contextlib.redirect_stdout(buffer):
                run()
        except SystemExit as exc:  # argparse ends a help request with exit status 0
            if exc.code not in (0, None):
                sys.stdout.write(buffer.getvalue())
                raise
        finally:
            sys.argv = saved
        text = buffer.getvalue()
        help_cache.store_help(name, rest, text)
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except BrokenPipeError:  # `tofdenoise fit --help | head`
        sys.stdout = None
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``tofdenoise``: ``tofdenoise <verb> ...`` runs that verb's ``main``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        try:
            print(usage(), file=sys.stdout if args else sys.stderr, flush=True)
        except BrokenPipeError:  # `tofdenoise --help | head`: the reader went away
            sys.stdout = None
        return 0 if args else 2
    name, rest = args[0], args[1:]
    verb = VERBS.get(name)
    if verb is None:
        print(f"tofdenoise: error: unknown verb {name!r}; valid: {', '.join(VERBS)}", file=sys.stderr)
        return 2
    if verb.grammar == "lightning" and help_cache.is_bare_help(rest):
        return _lightning_help(name, rest)
    # freed tensors' pages kept for the next frame or step (and in the processes the verb starts);
    # TOFDENOISE_MALLOC=default turns it off
    try:
        allocator.keep_freed_memory()
    except ValueError as err:
        print(f"tofdenoise: error: {err}", file=sys.stderr)
        return 2
    run = importlib.import_module(f"tofdenoise.cli.{verb.module}").main
    if verb.grammar == "options":
        status = run(rest)
    else:  # Hydra and LightningCLI read sys.argv themselves (LightningCLI with its subcommand)
        saved = sys.argv
        sys.argv = [f"tofdenoise {name}", *rest] if verb.grammar == "hydra" else ["tofdenoise", name, *rest]
        try:
            status = run()
        finally:
            sys.argv = saved
    return int(status or 0) if isinstance(status, (int, type(None))) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
