"""``tofdenoise <verb>``: every command is a verb of one console script, routed to its module's ``main``."""

from __future__ import annotations

import importlib

import pytest
import tomllib

from tofdenoise.cli.main import VERBS, main
from tofdenoise.paths import REPO_ROOT


def test_the_one_console_script_is_the_dispatcher_and_every_command_is_a_verb():
    """One grammar for the user (issue 24 point 4): ``tofdenoise`` is the only console script; every command is one
    of its verbs, each a module of ``tofdenoise.cli`` with a ``main``."""
    scripts = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"tofdenoise": "tofdenoise.cli.main:main"}
    for verb in VERBS.values():
        assert callable(importlib.import_module(f"tofdenoise.cli.{verb.module}").main)
        assert verb.grammar in ("hydra", "lightning", "options")


def test_every_options_verb_names_itself_as_the_user_types_it(capsys):
    """``tofdenoise <verb> --help`` shows ``usage: tofdenoise <verb>`` (argparse's ``prog``), never a former
    ``tofdenoise-<name>`` script."""
    for name, verb in VERBS.items():
        if verb.grammar != "options":
            continue
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        assert capsys.readouterr().out.startswith(f"usage: tofdenoise {name} "), name


def test_usage_lists_the_verbs_and_a_wrong_verb_is_a_usage_error(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert all(f"  {name} " in out for name in VERBS)
    assert main([]) == 2
    assert main(["trian"]) == 2
    assert "unknown verb 'trian'; valid: train, classic" in capsys.readouterr().err


def test_an_options_verb_gets_its_arguments(capsys, tmp_path):
    assert main(["sensor", "show-calib"]) == 0
    assert "signal" in capsys.readouterr().out.lower()
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--help"])
    assert exc.value.code == 0
    assert "tofdenoise" in capsys.readouterr().out


def test_a_lightning_verb_keeps_its_subcommand(monkeypatch):
    import sys

    import tofdenoise.cli.lightning_cli as lightning_cli

    seen = {}
    monkeypatch.setattr(lightning_cli, "main", lambda args=None: seen.setdefault("argv", list(sys.argv)) and 0)
    assert main(["fit", "--config", "configs/cli/default.yaml"]) == 0
    assert seen["argv"] == ["tofdenoise", "fit", "--config", "configs/cli/default.yaml"]


def test_a_hydra_verb_reads_its_overrides_from_argv(monkeypatch):
    import sys

    import tofdenoise.cli.train as train

    seen = {}
    monkeypatch.setattr(train, "main", lambda: seen.setdefault("argv", list(sys.argv)) and None)
    before = list(sys.argv)
    assert main(["train", "experiment=smoke", "seed=3"]) == 0
    assert seen["argv"] == ["tofdenoise train", "experiment=smoke", "seed=3"]
    assert sys.argv == before


def test_every_verb_runs_with_the_allocator_keeping_freed_memory(monkeypatch, capsys):
    from tofdenoise import allocator

    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(1) or True)
    assert main(["sensor", "show-calib"]) == 0
    assert calls == [1]


def test_a_bad_allocator_setting_is_a_usage_error(monkeypatch, capsys):
    monkeypatch.setenv("TOFDENOISE_MALLOC", "fast")
    assert main(["sensor", "show-calib"]) == 2
    assert "TOFDENOISE_MALLOC='fast': expected 'keep' (the default) or 'default'" in capsys.readouterr().err
