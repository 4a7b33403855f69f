"""tofdenoise.output_guard: the one check that an output never replaces an input."""

from __future__ import annotations

import os

import pytest

from tofdenoise.output_guard import OutputPathError, check_output_file, refuse_overwrite


@pytest.fixture
def inputs(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.npy").write_bytes(b"a")
    (folder / "index.json").write_text("{}")
    return folder


def test_an_output_that_is_an_input_through_a_symlink_or_a_hard_link_is_refused(inputs, tmp_path):
    (tmp_path / "link").symlink_to(inputs)
    with pytest.raises(OutputPathError, match="would replace the input"):
        refuse_overwrite([tmp_path / "link" / "a.npy"], [inputs / "a.npy"])
    os.link(inputs / "a.npy", tmp_path / "hard.npy")
    with pytest.raises(OutputPathError, match=f"--out {tmp_path / 'hard.npy'} would replace the input"):
        refuse_overwrite([tmp_path / "hard.npy"], [inputs / "a.npy"])


def test_an_existing_file_of_an_input_folder_is_refused_a_new_name_is_not(inputs):
    with pytest.raises(OutputPathError, match="would replace index.json of the input folder"):
        refuse_overwrite([inputs / "index.json"], [inputs])
    refuse_overwrite([inputs / "calibration.yaml"], [inputs])  # a new file beside the captures


def test_an_output_folder_that_holds_an_input_is_refused(inputs, tmp_path):
    with pytest.raises(OutputPathError, match="holds the input"):
        refuse_overwrite([], [inputs / "a.npy"], "--out", output_folders=[inputs])
    refuse_overwrite([], [inputs / "a.npy"], "--out", output_folders=[tmp_path / "elsewhere"])


def test_shadow_names_and_suffixes(inputs):
    with pytest.raises(OutputPathError, match="next to the input a.npy"):
        check_output_file(inputs / "a.json", (".json",), [inputs / "a.npy"])
    refuse_overwrite([inputs / "a.json"], [inputs / "a.npy"])  # without shadow: a new name is fine
    with pytest.raises(OutputPathError, match="expected a .json file"):
        check_output_file(inputs / "b.txt", (".json",))
    with pytest.raises(OutputPathError, match="is a folder"):
        check_output_file(inputs, (".json",))
