"""Seeded 6:2:2 splits: sizes (paper: 3,750/1,250/1,250 of 6,250), determinism, the stored file."""

from __future__ import annotations

import json
import re

import pytest

from tofdenoise.data_modules.splits import load_or_make_split, make_split, split_sizes


def test_paper_split_sizes():
    assert split_sizes(6250) == (3750, 1250, 1250)
    assert split_sizes(48) == (28, 10, 10)  # round(9.6) = 10
    assert split_sizes(10) == (6, 2, 2)
    assert split_sizes(3) == (1, 1, 1)


def test_split_partitions_all_ids_and_is_deterministic():
    ids = [f"s{i:05d}" for i in range(6250)]
    a = make_split(ids, seed=3)
    b = make_split(ids, seed=3)
    c = make_split(ids, seed=4)
    assert a == b
    assert a != c
    assert [len(a[k]) for k in ("train", "val", "test")] == [3750, 1250, 1250]
    together = a["train"] + a["val"] + a["test"]
    assert sorted(together) == ids and len(set(together)) == len(ids)
    # a random permutation, not a contiguous block: val ids spread over the whole range
    positions = sorted(int(s[1:]) for s in a["val"])
    assert positions[0] < 100 and positions[-1] > 6150


def test_split_file_is_written_and_reused(tmp_path):
    ids = [f"x{i}" for i in range(20)]
    path = tmp_path / "split.json"
    first = load_or_make_split(path, ids, seed=1, ratios=(6, 2, 2), source={"source": "t"})
    stored = json.loads(path.read_text())
    assert stored["sizes"] == {"train": 12, "val": 4, "test": 4} and stored["val"] == first["val"]
    # a hand-edited split with the same ids/seed/ratios is reused as it is
    stored["train"], stored["val"] = stored["train"][1:] + stored["val"][:1], stored["val"][1:] + stored["train"][:1]
    path.write_text(json.dumps(stored))
    again = load_or_make_split(path, ids, seed=1, ratios=(6, 2, 2), source={"source": "t"})
    assert again["val"] == stored["val"]
    # another seed makes (and stores) a new split
    other = load_or_make_split(path, ids, seed=2, ratios=(6, 2, 2), source={"source": "t"})
    assert other == make_split(ids, 2)
    assert json.loads(path.read_text())["seed"] == 2


def test_bad_ratios_and_too_few_samples():
    with pytest.raises(ValueError, match="split_ratios"):
        split_sizes(10, (6, 2))
    with pytest.raises(ValueError, match="too few"):
        split_sizes(2, (1, 5, 5))  # val 1 + test 1 leave no training sample


@pytest.mark.parametrize(
    "edit",
    [
        '{"train": ["x0", "x1",], "val": []}',  # trailing comma: not JSON
        '{"train": ["x0"], "val": ["x1"]}',  # no "test"
        '["x0"]',
    ],
)
def test_edited_split_that_does_not_parse_is_an_error_naming_the_file(tmp_path, edit):
    ids = [f"x{i}" for i in range(10)]
    path = tmp_path / "split_seed0_6-2-2.json"
    path.write_text(edit)
    with pytest.raises(ValueError, match=rf"split file {re.escape(str(path))}.*delete it"):
        load_or_make_split(path, ids, seed=0, ratios=(6, 2, 2), source={})
    assert path.read_text() == edit  # the user's file is kept


def test_split_with_an_id_in_two_parts_is_an_error(tmp_path):
    ids = [f"x{i}" for i in range(10)]
    path = tmp_path / "split.json"
    split = load_or_make_split(path, ids, seed=0, ratios=(6, 2, 2), source={})
    stored = json.loads(path.read_text())
    stored["val"].append(split["train"][0])
    path.write_text(json.dumps(stored))
    with pytest.raises(ValueError, match=f"sample '{split['train'][0]}' is in both 'train' and 'val'"):
        load_or_make_split(path, ids, seed=0, ratios=(6, 2, 2), source={})
