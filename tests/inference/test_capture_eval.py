"""``inference.capture_eval``'s file handling: a scene's truth map (``read_truth``) and whether a capture set holds
truth (``has_truth``). The scoring itself is tested end to end in tests/cli/test_evaluate.py."""

from __future__ import annotations

import numpy as np
import pytest

from tofdenoise.evaluation import EvalInputError
from tofdenoise.inference.capture_eval import has_truth, read_truth


def test_read_truth_returns_float64_and_names_the_file_once_on_errors(tmp_path):
    scene = tmp_path / "scene_0000"
    scene.mkdir()
    path = scene / "ground_truth_depth_mm.npy"
    np.save(path, np.full((3, 4), 1200.0, dtype=np.float32))
    truth = read_truth(scene, (3, 4))
    assert truth.dtype == np.float64 and truth.shape == (3, 4) and float(truth[0, 0]) == 1200.0
    with pytest.raises(EvalInputError, match=r"has shape \(3, 4\); expected \(4, 3\)"):
        read_truth(scene, (4, 3))
    path.write_bytes(b"not an npy file")
    with pytest.raises(EvalInputError) as err:
        read_truth(scene, (3, 4))
    assert str(err.value).count(str(path)) == 1
    path.unlink()
    with pytest.raises(EvalInputError) as err:
        read_truth(scene, (3, 4))
    assert str(err.value).count(str(path)) == 1


def test_has_truth_is_true_for_a_set_with_a_truth_map_only(tmp_path):
    assert not has_truth(tmp_path / "missing")
    assert not has_truth(tmp_path)
    (tmp_path / "README.md").write_text("a capture set")
    (tmp_path / "scene_0000").mkdir()
    assert not has_truth(tmp_path)
    np.save(tmp_path / "scene_0000" / "ground_truth_depth_mm.npy", np.ones((2, 2)))
    assert has_truth(tmp_path)
