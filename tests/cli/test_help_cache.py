"""The help cache of Lightning's verbs (``tofdenoise.cli.help_cache``): what its key covers, and that it stays a
cache (off when asked, passed over when its folder cannot be written, never used for anything but a bare help)."""

from __future__ import annotations

import os

import pytest

from tofdenoise.cli import help_cache


@pytest.fixture
def package(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "a.py").write_text("def f(x):\n    '''x.'''\n")
    (pkg / "sub" / "b.py").write_text("")
    return pkg


def test_the_key_changes_with_the_code_the_arguments_and_the_width(package, monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    key = help_cache.cache_key("fit", ["--help"], package)
    assert help_cache.cache_key("fit", ["--help"], package) == key  # stable
    assert help_cache.cache_key("validate", ["--help"], package) != key
    assert help_cache.cache_key("fit", ["-h"], package) != key
    monkeypatch.setenv("COLUMNS", "80")
    assert help_cache.cache_key("fit", ["--help"], package) != key
    monkeypatch.setenv("COLUMNS", "100")
    (package / "a.py").write_text("def f(x, y):\n    '''x, y.'''\n")  # a parameter added
    edited = help_cache.cache_key("fit", ["--help"], package)
    assert edited != key
    os.utime(package / "sub" / "b.py", ns=(1, 1))  # same size, another modification time
    assert help_cache.cache_key("fit", ["--help"], package) != edited
    (package / "c.py").write_text("")  # a new module
    assert help_cache.cache_key("fit", ["--help"], package) not in (key, edited)


def test_the_key_changes_when_a_package_is_installed(tmp_path, monkeypatch, package):
    site = tmp_path / "site-packages"
    site.mkdir()
    monkeypatch.setattr("sys.path", [str(tmp_path), str(site)])
    key = help_cache.cache_key("fit", ["--help"], package)
    (site / "lightning-9.9.dist-info").mkdir()
    os.utime(site, ns=(10**18, 10**18))  # the folder's time moves as an entry is added
    assert help_cache.cache_key("fit", ["--help"], package) != key
    key = help_cache.cache_key("fit", ["--help"], package)
    (tmp_path / "scratch").mkdir()  # a working folder on sys.path changes without any package changing
    os.utime(tmp_path, ns=(10**18, 10**18))
    assert help_cache.cache_key("fit", ["--help"], package) == key


def test_store_then_read_and_only_for_a_bare_help(tmp_path, monkeypatch):
    monkeypatch.setenv("TOFDENOISE_CACHE_DIR", str(tmp_path))
    assert help_cache.read_help("fit", ["--help"]) is None
    path = help_cache.store_help("fit", ["--help"], "usage: tofdenoise fit\n")
    assert path is not None and path.parent == tmp_path / "cli-help"
    assert help_cache.read_help("fit", ["--help"]) == "usage: tofdenoise fit\n"
    assert help_cache.read_help("fit", ["-h"]) is None  # stored under its own key
    assert help_cache.store_help("fit", ["--config", "a.yaml", "--help"], "x") is None
    assert help_cache.read_help("fit", ["--config", "a.yaml", "--help"]) is None


def test_old_texts_are_pruned(tmp_path, monkeypatch):
    monkeypatch.setenv("TOFDENOISE_CACHE_DIR", str(tmp_path))
    for columns in range(60, 60 + help_cache.KEEP + 3):
        monkeypatch.setenv("COLUMNS", str(columns))
        help_cache.store_help("fit", ["--help"], f"width {columns}\n")
    stored = list((tmp_path / "cli-help").glob("fit-*.txt"))
    assert len(stored) == help_cache.KEEP
    assert help_cache.read_help("fit", ["--help"]) == f"width {columns}\n"  # the newest stays


def test_cache_off_and_an_unwritable_folder_are_passed_over(tmp_path, monkeypatch):
    monkeypatch.setenv("TOFDENOISE_CACHE_DIR", "")
    assert help_cache.cache_dir() is None
    assert help_cache.store_help("fit", ["--help"], "x") is None and help_cache.read_help("fit", ["--help"]) is None
    blocker = tmp_path / "file"
    blocker.write_text("a file where the folder would be")
    monkeypatch.setenv("TOFDENOISE_CACHE_DIR", str(blocker))
    assert help_cache.store_help("fit", ["--help"], "x") is None


def test_the_default_folder_follows_xdg(tmp_path, monkeypatch):
    monkeypatch.delenv("TOFDENOISE_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert help_cache.cache_dir() == tmp_path / "tofdenoise" / "cli-help"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert help_cache.cache_dir() == tmp_path / "home" / ".cache" / "tofdenoise" / "cli-help"
