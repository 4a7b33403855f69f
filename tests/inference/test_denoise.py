"""The Python API: denoise() on arrays/tensors, checkpoint errors, the sigma_D map of the input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import tofdenoise
from tofdenoise.inference.denoise import CheckpointError, load_restorer, sigma_map_mm
from tofdenoise.physics.calibration import resolve_calibration
from tofdenoise.physics.uncertainty import amplitude_to_signal_e, sigma_depth_mm


def frame(h: int = 40, w: int = 56) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    d = (900 + 3 * x + 2 * y).astype(np.float32)
    d[10:16, 20:30] = 0
    d[30, 5] = np.nan
    d[31, 6] = -3
    return d


def test_denoise_matches_restore_mm_and_masks_holes(restorer_ckpt):
    model = load_restorer(restorer_ckpt)
    d = frame()
    valid = np.isfinite(d) & (d > 0)
    out = tofdenoise.denoise(d, model)
    assert out.dtype == np.float32 and out.shape == d.shape
    batch = {
        "noisy": torch.from_numpy(np.where(valid, d, 0).astype(np.float32))[None, None],
        "mask": torch.from_numpy(valid.astype(np.float32))[None, None],
    }
    with torch.no_grad():
        expected = model.restore_mm(batch, tile=model.tiling.predict_tile_px)[0, 0].numpy()
    np.testing.assert_array_equal(out[valid], expected[valid])
    assert np.all(out[~valid] == 0)
    filled = tofdenoise.denoise(torch.from_numpy(d), str(restorer_ckpt), fill_holes=True, device="cpu")
    np.testing.assert_array_equal(filled, expected)
    np.testing.assert_array_equal(tofdenoise.denoise(d[None], model), out)  # (1, H, W) accepted
    with pytest.raises(ValueError, match="amplitude has shape"):
        tofdenoise.denoise(d, model, amplitude=np.ones((3, 3)))


def test_a_frame_in_metres_is_refused_as_the_command_refuses_it_unless_its_scale_is_given(restorer_ckpt):
    """The API returned a metres frame restored as a scene 1 mm away, without a word, where ``tofdenoise denoise``
    refuses it; now the same check, naming depth_scale_mm, and depth_scale_mm=1000 gives the mm frame's result."""
    model = load_restorer(restorer_ckpt)
    d = frame()
    with pytest.raises(ValueError, match=r"implausible in millimetres.*looks like metres: pass depth_scale_mm=1000"):
        tofdenoise.denoise(d / 1000, model)
    np.testing.assert_allclose(tofdenoise.denoise(d / 1000, model, depth_scale_mm=1000), tofdenoise.denoise(d, model))
    with pytest.raises(ValueError, match="depth_scale_mm must be a positive number"):
        tofdenoise.denoise(d, model, depth_scale_mm=0)


def test_signal_channel_model_needs_amplitude(tmp_path, make_restorer_ckpt):
    ckpt = make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True})
    model = load_restorer(ckpt)
    d = frame()
    with pytest.raises(ValueError, match="amplitude"):
        tofdenoise.denoise(d, model)
    out = tofdenoise.denoise(d, model, amplitude=np.full(d.shape, 100.0))
    assert out.shape == d.shape and np.isfinite(out).all()


def test_an_amplitude_without_a_finite_value_where_the_depth_is_valid_is_refused_as_in_the_command(
    tmp_path, make_restorer_ckpt
):
    """The API restored a frame from an all-NaN amplitude (read as 0 everywhere: a signal channel of nothing) where
    the command refuses that amplitude; now the same check (``frames.checked_amplitude``), and a NaN block is 0."""
    model = load_restorer(make_restorer_ckpt(tmp_path / "sig.ckpt", conditioning={"use_signal_channel": True}))
    d = frame()
    with pytest.raises(ValueError, match=r"denoise: amplitude \(for depth_mm\) holds no finite value where the depth"):
        tofdenoise.denoise(d, model, amplitude=np.full(d.shape, np.nan))
    amp = np.full(d.shape, 100.0)
    amp[:4] = np.nan
    np.testing.assert_array_equal(
        tofdenoise.denoise(d, model, amplitude=amp), tofdenoise.denoise(d, model, amplitude=np.nan_to_num(amp))
    )


def test_not_a_depthrestorer_checkpoint_is_named(tmp_path):
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"not a checkpoint")
    other = tmp_path / "other.ckpt"
    torch.save({"state_dict": {"layer.weight": torch.ones(2)}, "hyper_parameters": {"hidden": 3}}, other)
    weights = tmp_path / "weights.pt"
    torch.save({"conv.weight": torch.ones(2)}, weights)
    for path in (junk, other, weights, tmp_path / "missing.ckpt"):
        with pytest.raises(CheckpointError) as info:
            load_restorer(path)
        assert path.name in str(info.value)
        if path.name != "missing.ckpt":
            assert "expected a DepthRestorer checkpoint" in str(info.value)
    with pytest.raises(TypeError, match="DepthRestorer or a checkpoint path"):
        tofdenoise.denoise(frame(), 42)


def test_sigma_map_equals_sigma_depth_mm_with_the_training_signal_mapping():
    calib = resolve_calibration(None)
    rng = np.random.default_rng(0)
    d = rng.uniform(400, 2000, (30, 40)).astype(np.float32)
    amp = rng.uniform(50, 3000, d.shape).astype(np.float32)
    valid = np.ones(d.shape, bool)
    valid[:5] = False
    sigma = sigma_map_mm(np.where(valid, d, 0), valid, amp, calib)
    signal = np.asarray(amplitude_to_signal_e(amp, calib, valid=valid))
    expected = np.asarray(sigma_depth_mm(d[valid], signal[valid], calib), dtype=np.float32)
    np.testing.assert_allclose(sigma[valid], expected, rtol=1e-6)
    assert np.isnan(sigma[~valid]).all()
    # brighter pixels are more certain at the same depth (paper Eq. 15)
    flat = sigma_map_mm(np.full((1, 2), 1000.0), np.ones((1, 2), bool), np.array([[100.0, 2000.0]]), calib)
    assert flat[0, 0] > flat[0, 1] > 0


def test_a_file_that_is_not_a_checkpoint_never_gets_torchs_weights_only_false_advice(tmp_path):
    """A pickled object (or a file that is not a zip of tensors) is refused in one line naming the file, and the
    line never advises weights_only=False (loading so would run the file's pickled code)."""
    import functools

    import pytest
    import torch

    from tofdenoise.inference.denoise import CheckpointError, load_restorer

    pickled = tmp_path / "pickled.ckpt"
    torch.save({"state_dict": {}, "factory": functools.partial(max, 1)}, pickled)
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a checkpoint at all")
    for path, reason in ((pickled, "pickled Python objects"), (garbage, "")):
        with pytest.raises(CheckpointError) as info:
            load_restorer(path)
        message = str(info.value)
        assert str(path) in message and reason in message and "\n" not in message
        assert "weights_only" not in message and "Re-running" not in message
