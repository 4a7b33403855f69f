"""The commit a record names (tofdenoise.records.provenance): clean and dirty checkouts, no checkout, old records."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from tofdenoise.records import code_commit, is_ancestor, record_commit

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def _git(folder, *args):
    subprocess.run(["git", "-C", str(folder), *args], check=True, capture_output=True)


@pytest.fixture
def checkout(tmp_path):
    repo = tmp_path / "repo"
    (repo / "src").mkdir(parents=True)
    (repo / "src" / "a.py").write_text("x = 1\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "first")
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True).stdout
    return repo, head.strip()


def test_a_clean_checkout_is_its_commit_not_dirty(checkout):
    repo, head = checkout
    got = code_commit(repo / "src")
    assert got["commit"] == head and got["commit_dirty"] is False
    assert got["commit_describe"] == head[:12]


def test_an_edited_tracked_file_is_dirty(checkout):
    repo, head = checkout
    (repo / "src" / "a.py").write_text("x = 2\n")
    got = code_commit(repo / "src")
    assert got["commit"] == head and got["commit_dirty"] is True
    assert got["commit_describe"] == f"{head[:12]}-dirty"


def test_records_and_the_page_written_into_the_checkout_are_not_dirty(checkout):
    """tofdenoise reproduce commits each finished run into docs/results/ and rebuilds docs/results.md: the next
    run's record must not read as made by uncommitted code; a config edited beside them still does."""
    repo, head = checkout
    record = repo / "docs" / "results" / "cpu" / "unet-hetero-l1-s0"
    record.mkdir(parents=True)
    (record / "metrics.json").write_text("{}\n")
    (repo / "docs" / "results.md").write_text("# page\n")
    _git(repo, "add", "docs")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "records")
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    (record / "metrics.json").write_text('{"mae_mm": 1}\n')
    (record.parent / "unet-hetero-l1-s1").mkdir()
    (repo / "docs" / "results.md").write_text("# page, rebuilt\n")
    got = code_commit(repo / "src")
    assert got["commit"] == head and got["commit_dirty"] is False and got["commit_describe"] == head[:12]
    (repo / "src" / "a.py").write_text("x = 3\n")
    from tofdenoise.records import provenance

    provenance._commit_of.cache_clear()  # read once per process and folder
    got = code_commit(repo / "src")
    assert got["commit_dirty"] is True and got["commit_describe"] == f"{head[:12]}-dirty"


def test_outside_a_checkout_the_commit_is_none(tmp_path):
    folder = tmp_path / "not-a-checkout"
    folder.mkdir()
    got = code_commit(folder)
    assert got["commit"] is None and got["commit_dirty"] is None and "version" in got


def test_records_without_a_commit_read_as_none():
    assert record_commit({"backbone": "unet"}) is None
    assert record_commit(None) is None
    assert record_commit({"commit": "ab" * 20}) == "ab" * 20


def test_is_ancestor_orders_two_commits_and_says_when_git_cannot_tell(checkout, tmp_path):
    repo, first = checkout
    (repo / "src" / "a.py").write_text("x = 3\n")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-am", "second")
    second = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True).stdout
    second = second.strip()
    assert is_ancestor(first, second, repo) is True
    assert is_ancestor(first, first, repo) is True
    assert is_ancestor(second, first, repo) is False
    assert is_ancestor("ab" * 20, second, repo) is None  # a commit the checkout does not have
    assert is_ancestor(first, second, tmp_path / "nowhere") is None  # no checkout


def test_the_code_digest_names_the_code_by_its_content(tmp_path):
    """``code_digest``: the same files give the same digest wherever they lie; a changed byte, a renamed or an added
    source file changes it; caches and files of other kinds do not; the default covers the package and configs."""
    from tofdenoise.records import code_digest

    def tree(root, text="x = 1\n"):
        (root / "pkg" / "sub").mkdir(parents=True)
        (root / "pkg" / "a.py").write_text(text)
        (root / "pkg" / "sub" / "k.cpp").write_text("int f();\n")
        (root / "conf").mkdir()
        (root / "conf" / "c.yaml").write_text("lr: 2e-4\n")
        return root / "pkg", root / "conf"

    first, second = tree(tmp_path / "one"), tree(tmp_path / "two")
    digest = code_digest(*first)
    assert digest.startswith("sha256:") and len(digest) == 7 + 64
    assert code_digest(*second) == digest  # another place, the same code
    assert code_digest(*tree(tmp_path / "three", "x = 2\n")) != digest  # one byte
    assert code_digest(second[1], second[0]) != digest  # the folders' roles swapped
    (second[0] / "__pycache__").mkdir()
    (second[0] / "__pycache__" / "a.cpython-311.pyc").write_bytes(b"\0")
    (second[0] / "notes.txt").write_text("not code")
    from tofdenoise.records.provenance import _digest

    _digest.cache_clear()
    assert code_digest(*second) == digest  # caches and other kinds left out
    (second[0] / "sub" / "k.cpp").rename(second[0] / "sub" / "k2.cpp")
    _digest.cache_clear()
    assert code_digest(*second) != digest  # a renamed file
    assert code_digest(tmp_path / "missing") == code_digest(tmp_path / "also-missing")
    assert code_digest() == code_digest()  # the package and the checkout's configs
