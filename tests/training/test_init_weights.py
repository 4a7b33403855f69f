"""model.init_weights: weights only, all or nothing, one error naming the file and the layers."""

from __future__ import annotations

import pytest
import torch

from tofdenoise.models import build_backbone
from tofdenoise.training.init_weights import InitWeightsError, file_sha256, load_init_weights
from tofdenoise.training.module import DepthRestorer

TINY = {"width": 8, "stages": 2}


def _model(**kw) -> DepthRestorer:
    return DepthRestorer(backbone="unet", backbone_kwargs=dict(TINY), **kw)


def _perturbed(model: DepthRestorer, seed: int = 3) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return {k: v + torch.randn(v.shape, generator=gen) for k, v in model.backbone.state_dict().items()}


@pytest.mark.parametrize("layout", ["module", "backbone", "checkpoint"])
def test_every_weight_is_loaded_from_each_file_layout(tmp_path, layout):
    src = _model()
    src.backbone.load_state_dict(_perturbed(src))
    path = tmp_path / "w.pt"
    if layout == "module":
        torch.save(src.state_dict(), path)
    elif layout == "backbone":
        torch.save(src.backbone.state_dict(), path)
    else:
        torch.save({"state_dict": src.state_dict(), "hyper_parameters": dict(src.hparams)}, path)
    dst = _model(ema_decay=0.9)
    record = load_init_weights(dst, path)
    for k, v in src.backbone.state_dict().items():
        assert torch.equal(dst.backbone.state_dict()[k], v), k
        assert torch.equal(dst.ema.module.state_dict()[k], v), k  # the EMA starts from the loaded weights too
    assert record == {"path": str(path.resolve()), "sha256": file_sha256(path)}


def test_the_ema_weights_of_a_checkpoint_are_the_ones_loaded(tmp_path):
    src = _model(ema_decay=0.9)
    src.ema.module.load_state_dict(_perturbed(src, seed=5))
    path = tmp_path / "ema.ckpt"
    torch.save({"state_dict": src.state_dict(), "hyper_parameters": dict(src.hparams)}, path)
    dst = _model()
    load_init_weights(dst, path)
    for k, v in src.ema.module.state_dict().items():
        assert torch.equal(dst.backbone.state_dict()[k], v), k


def test_another_backbone_size_is_one_error_naming_file_and_layers_and_nothing_is_loaded(tmp_path):
    other = DepthRestorer(backbone="unet", backbone_kwargs={"width": 16, "stages": 3})
    path = tmp_path / "big.ckpt"
    torch.save({"state_dict": other.state_dict(), "hyper_parameters": dict(other.hparams)}, path)
    dst = _model()
    before = {k: v.clone() for k, v in dst.backbone.state_dict().items()}
    with pytest.raises(InitWeightsError) as info:
        load_init_weights(dst, path)
    msg = str(info.value)
    assert "\n" not in msg and str(path.resolve()) in msg and "does not fit backbone 'unet'" in msg
    assert "unexpected (" in msg and "shape mismatch(es) (" in msg and "more)" in msg
    assert ": file (16, " in msg and "vs model (8, " in msg
    assert "'width': 16" in msg  # what the file is
    for k, v in dst.backbone.state_dict().items():
        assert torch.equal(v, before[k]), k  # no partial load


def test_missing_layers_are_named(tmp_path):
    state = build_backbone("unet", in_channels=1, **TINY).state_dict()
    dropped = sorted(state)[:2]
    for k in dropped:
        del state[k]
    path = tmp_path / "partial.pt"
    torch.save(state, path)
    with pytest.raises(InitWeightsError, match=r"2 missing \(") as info:
        load_init_weights(_model(), path)
    assert all(k in str(info.value) for k in dropped)


def test_a_checkpoint_of_another_network_input_is_refused(tmp_path):
    src = _model(conditioning={"centering": "image"})
    path = tmp_path / "image.ckpt"
    torch.save({"state_dict": src.state_dict(), "hyper_parameters": dict(src.hparams)}, path)
    with pytest.raises(InitWeightsError, match="conditioning.centering: file 'image' vs this model 'gaussian'"):
        load_init_weights(_model(), path)


def test_a_checkpoint_without_the_conditioning_group_is_refused(tmp_path):
    """No fallback: hyper-parameters that do not say what the network saw are not guessed."""
    src = _model()
    hparams = {k: v for k, v in dict(src.hparams).items() if k != "conditioning"}
    path = tmp_path / "old.ckpt"
    torch.save({"state_dict": src.state_dict(), "hyper_parameters": hparams}, path)
    with pytest.raises(InitWeightsError, match="no 'conditioning' group"):
        load_init_weights(_model(), path)


@pytest.mark.parametrize("content", [b"", b"not a checkpoint at all", b"PK\x03\x04 truncated zip"])
def test_a_corrupt_file_is_one_line_naming_it(tmp_path, content):
    path = tmp_path / "broken.ckpt"
    path.write_bytes(content)
    with pytest.raises(InitWeightsError) as info:
        load_init_weights(_model(), path)
    msg = str(info.value)
    assert "\n" not in msg and str(path.resolve()) in msg and "weights_only=True" in msg
    assert "weights_only=False" not in msg


def test_a_truncated_checkpoint_and_a_missing_file(tmp_path):
    src = _model()
    path = tmp_path / "cut.ckpt"
    torch.save({"state_dict": src.state_dict()}, path)
    path.write_bytes(path.read_bytes()[:-200])
    with pytest.raises(InitWeightsError, match="not loadable by torch.load"):
        load_init_weights(_model(), path)
    with pytest.raises(InitWeightsError, match="does not exist"):
        load_init_weights(_model(), tmp_path / "nope.ckpt")
