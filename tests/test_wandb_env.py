"""tofdenoise.wandb_env: the one place that keeps wandb quiet and local, names its run and finishes it."""

from __future__ import annotations

import sys
import types

from tofdenoise.wandb_env import QUIET_ENV, WANDB_ID_FILE, finish_wandb, quiet_wandb, setup_wandb_env, wandb_run_id

DIR_VARS = ("WANDB_DIR", "WANDB_CACHE_DIR", "WANDB_CONFIG_DIR", "WANDB_DATA_DIR")


def test_setup_puts_wandb_under_the_run_folder_and_keeps_what_the_user_set(tmp_path, monkeypatch):
    import os

    for var in (*DIR_VARS, *QUIET_ENV, "WANDB_MODE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("WANDB_SILENT", "false")  # the user's choice wins
    setup_wandb_env(tmp_path / "run")
    assert os.environ["WANDB_DIR"] == str(tmp_path / "run")
    assert os.environ["WANDB_CACHE_DIR"] == str(tmp_path / "run" / "wandb" / ".cache")
    assert os.environ["WANDB_CONFIG_DIR"] == str(tmp_path / "run" / "wandb" / ".config")
    assert os.environ["WANDB_DATA_DIR"] == str(tmp_path / "run" / "wandb" / ".data")
    assert os.environ["WANDB_SILENT"] == "false" and os.environ["WANDB_ERROR_REPORTING"] == "false"
    assert "WANDB_MODE" not in os.environ  # offline or not is the logger's choice
    setup_wandb_env(tmp_path / "other")  # set once: a second run folder does not move the first's files
    assert os.environ["WANDB_DIR"] == str(tmp_path / "run")
    quiet_wandb(offline=True)
    assert os.environ["WANDB_MODE"] == "offline"


def test_run_id_is_kept_per_run_folder(tmp_path):
    first = wandb_run_id(tmp_path / "a")
    assert len(first) == 12 and (tmp_path / "a" / WANDB_ID_FILE).read_text() == first + "\n"
    assert wandb_run_id(tmp_path / "a") == first  # a resume reuses it
    assert wandb_run_id(tmp_path / "b") != first


def test_finish_closes_only_an_open_run(monkeypatch):
    calls = []
    fake = types.SimpleNamespace(run=None, finish=lambda: calls.append("finish"))
    monkeypatch.setitem(sys.modules, "wandb", fake)
    finish_wandb()
    assert calls == []
    fake.run = object()
    finish_wandb()
    assert calls == ["finish"]
    monkeypatch.delitem(sys.modules, "wandb")
    finish_wandb()  # wandb never imported: nothing to do, nothing imported
    assert "wandb" not in sys.modules
