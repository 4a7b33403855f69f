"""ToFDataModule: batch contract, fixed evaluation noise, fresh training noise, aligned crops, variance matching."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tofdenoise.data_modules import ToFDataModule

SCENES = dict(num_samples=10, height=48, width=64)  # data.source_kwargs of the procedural source
SMALL = dict(source_kwargs=SCENES, crop_size=16, batch_size=2)


def make_dm(tmp_path, scenes=None, **kw):
    """A prepared datamodule of SMALL procedural scenes; ``scenes`` updates their source_kwargs."""
    args = {**SMALL, "source_kwargs": {**SCENES, **(scenes or {})}, "cache_dir": str(tmp_path / "cache"), **kw}
    dm = ToFDataModule(**args)
    dm.prepare_data()
    dm.setup("fit")
    return dm


def test_batch_contract(tmp_path):
    dm = make_dm(tmp_path)
    batch = next(iter(dm.train_dataloader()))
    for key in ("noisy", "clean", "sigma", "mask", "amplitude"):
        assert batch[key].dtype == torch.float32 and batch[key].shape == (2, 1, 16, 16), key
    assert batch["index"].dtype == torch.int64 and batch["index"].shape == (2,)
    assert isinstance(batch["name"], list) and len(batch["name"]) == 2
    val = next(iter(dm.val_dataloader()))
    assert val["noisy"].shape == (1, 1, 48, 64)
    invalid = val["mask"] == 0
    assert torch.all(val["noisy"][invalid] == 0) and torch.all(val["clean"][invalid] == 0)
    assert set(torch.unique(val["mask"]).tolist()) <= {0.0, 1.0}
    # the paper's protocol (hetero-noised) first, then the simulator-noised split
    assert dm.test_set_names == ["synthetic", "simulated"] and len(dm.test_dataloader()) == 2
    test, sim = (next(iter(loader)) for loader in dm.test_dataloader())
    assert set(sim) == set(test) and sim["noisy"].shape == test["noisy"].shape and sim["name"] == test["name"]
    assert torch.all(sim["noisy"][sim["mask"] == 0] == 0) and torch.all(sim["clean"][sim["mask"] == 0] == 0)
    off = make_dm(tmp_path, simulated_test=False)
    assert off.test_set_names == ["synthetic"] and len(off.test_dataloader()) == 1
    assert len(dm.predict_dataloader().dataset) == len(dm.splits["test"])
    # split sizes 6:2:2 and the split file written next to the cache
    assert {k: len(v) for k, v in dm.splits.items()} == {"train": 6, "val": 2, "test": 2}
    assert json.loads(dm.split_path.read_text())["val"] == dm.splits["val"]
    assert dm.split_path.parent == dm.cache.folder.parent


def test_validation_noise_identical_across_epochs_runs_and_workers(tmp_path):
    dm = make_dm(tmp_path / "a")
    epoch1 = [b["noisy"].clone() for b in dm.val_dataloader()]
    epoch2 = [b["noisy"].clone() for b in dm.val_dataloader()]
    other_run = make_dm(tmp_path / "b", num_workers=2)  # fresh cache, another process layout
    epoch3 = [b["noisy"].clone() for b in other_run.val_dataloader()]
    for a, b, c in zip(epoch1, epoch2, epoch3):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
        torch.testing.assert_close(a, c, rtol=0, atol=0)
    test_noisy = [b["noisy"] for b in dm.test_dataloader()[0]]
    assert not torch.equal(test_noisy[0], epoch1[0])  # different samples / streams per split


def test_training_noise_is_fresh_and_workers_do_not_repeat(tmp_path):
    dm = make_dm(tmp_path, crop_size=None, flips=False, num_workers=2, batch_size=1, holes=False)
    ds = dm.datasets["train"]
    a, b = ds[0], ds[0]
    torch.testing.assert_close(a["clean"], b["clean"])
    assert not torch.equal(a["noisy"], b["noisy"])
    eps = []
    for batch in dm.train_dataloader():
        m = batch["mask"] > 0
        eps.append(((batch["noisy"] - batch["clean"])[m] / batch["sigma"][m])[:1000])
    eps = torch.stack(eps)
    corr = torch.corrcoef(eps)
    off_diag = corr[~torch.eye(len(eps), dtype=torch.bool)]
    assert off_diag.abs().max() < 0.2  # no two reads share a noise stream


def test_crops_keep_maps_aligned(tmp_path):
    dm = make_dm(tmp_path, holes=False)  # holes change the maps (tests/data_modules/test_holes.py)
    full = dm.cache.read
    ds = dm.datasets["train"]
    for index in range(len(ds)):
        item = ds[index]
        maps = full(item["name"])
        ref = {"clean": maps.depth_mm, "sigma": maps.sigma_mm, "amplitude": maps.amplitude, "mask": maps.mask}
        crop = item["clean"][0].numpy()
        found = False
        for flips in ((), (1,), (0,), (0, 1)):
            view = np.flip(crop, flips) if flips else crop
            for top in range(48 - 16 + 1):
                for left in range(64 - 16 + 1):
                    if np.array_equal(ref["clean"][top : top + 16, left : left + 16], view):
                        window = (slice(top, top + 16), slice(left, left + 16))
                        for key in ("sigma", "amplitude", "mask"):
                            got = np.flip(item[key][0].numpy(), flips) if flips else item[key][0].numpy()
                            np.testing.assert_array_equal(got, ref[key][window].astype(np.float32))
                        found = True
                        break
                if found:
                    break
            if found:
                break
        assert found, f"crop of {item['name']} not found in its full map"
        residual = (item["noisy"] - item["clean"])[item["mask"] > 0]
        assert torch.all(residual.abs() <= 6 * item["sigma"][item["mask"] > 0])


def test_hetero_noise_std_matches_sigma_map(tmp_path):
    dm = make_dm(tmp_path, scenes=dict(num_samples=20, height=64, width=96), holes=False)
    z = torch.cat([((b["noisy"] - b["clean"]) / b["sigma"])[b["mask"] > 0] for b in dm.val_dataloader()])
    assert z.numel() > 20000
    assert float(z.mean()) == pytest.approx(0.0, abs=0.03)
    assert float(z.std()) == pytest.approx(1.0, abs=0.03)


def _train_sigma2(dm):
    """Depth, sigma_D^2 and crop coverage over the training pixels: valid and not a hole (``TRAINING_PIXELS_RULE``),
    each pixel's share of the random training crops that cover it (``VARIANCE_MATCH_RULE``)."""
    from tofdenoise.data_modules.transforms import crop_coverage

    maps = {i: dm.cache.read(i) for i in dm.splits["train"]}
    keep = {i: dm.training_pixels(i, m) for i, m in maps.items()}
    depth = np.concatenate([m.depth_mm[keep[i]] for i, m in maps.items()]).astype(np.float64)
    sigma2 = np.concatenate([m.sigma_mm[keep[i]] for i, m in maps.items()]).astype(np.float64) ** 2
    weight = np.concatenate([crop_coverage(*m.depth_mm.shape, dm.crop)[keep[i]] for i, m in maps.items()])
    return depth, sigma2, weight


def test_variance_matching_equals_hetero_mean_variance(tmp_path, monkeypatch):
    dm = make_dm(tmp_path, noise="fixed", noise_kwargs={"sigma_mm": 2.0})
    depth, sigma2, w = _train_sigma2(dm)
    k = dm.summary()["variance_scale"]
    # matched on the pixels the network is trained on: after the holes, which remove the darkest, noisiest pixels,
    # each as often as a random 16 x 16 crop of the 48 x 64 maps covers it
    assert k == pytest.approx(np.sqrt(np.average(sigma2, weights=w)) / 2.0, rel=1e-6)
    record = dm.summary()["noise_record"]
    assert record["pixels"] == "after_holes" and record["sigma_mm"] == pytest.approx(2.0 * k, rel=1e-9)
    assert record["weights"] == "crop_coverage" and record["crop"] == [16, 16]
    all_valid = np.concatenate([dm.cache.read(i).sigma_mm[dm.cache.read(i).mask] for i in dm.splits["train"]])
    assert depth.size < 0.97 * all_valid.size  # the holes took a share of the valid pixels
    assert abs(np.sqrt((all_valid.astype(np.float64) ** 2).mean()) / 2.0 / k - 1) > 1e-3  # the rule moved k
    assert abs(np.sqrt(sigma2.mean()) / 2.0 / k - 1) > 1e-3  # and so did the coverage
    assert dm.noise_model.scale == pytest.approx(k)
    alpha = [1.0, 0.002, 1e-6]
    rng = make_dm(tmp_path, noise="range", noise_kwargs={"alpha_mm": alpha})
    base2 = (alpha[0] + alpha[1] * depth + alpha[2] * depth**2) ** 2
    k_range = rng.summary()["variance_scale"]
    assert k_range**2 * np.average(base2, weights=w) == pytest.approx(np.average(sigma2, weights=w), rel=1e-6)
    # stored next to the cache and reused when the keys match: no recomputation in a new instance
    records = list(rng.cache.folder.glob("variance_scale_range_*.json"))
    assert len(records) == 1 and json.loads(records[0].read_text())["scale"] == pytest.approx(k_range)
    import tofdenoise.physics.noise_models as nm

    monkeypatch.setattr(nm, "variance_matching_scale", lambda *a, **k: pytest.fail("recomputed"))
    again = make_dm(tmp_path, noise="range", noise_kwargs={"alpha_mm": alpha})
    assert again.summary()["variance_scale"] == pytest.approx(k_range)
    # the matched fixed model's perturbation variance over the training pixels, as crops draw them, equals hetero's
    model = dm.noise_model
    std = model.std_mm(torch.from_numpy(depth))
    assert float(np.average(std.double().numpy() ** 2, weights=w)) == pytest.approx(np.average(sigma2, weights=w))
    # another crop size is another match (not the stored one)
    monkeypatch.undo()
    full = make_dm(tmp_path, noise="fixed", noise_kwargs={"sigma_mm": 2.0}, crop_size=None)
    assert full.summary()["noise_record"]["crop"] is None
    assert full.summary()["variance_scale"] == pytest.approx(np.sqrt(sigma2.mean()) / 2.0, rel=1e-6)


def test_matched_baselines_put_the_hetero_variance_into_the_training_crops(tmp_path):
    """What the match is for: over the valid pixels of the crops the training loader draws, a matched baseline's
    perturbations (noisy - clean) have the mean square that hetero's sigma_D^2 has on the same pixels (Monte Carlo:
    600 / 1800 random 16 x 16 crops of 48 x 64 maps, a crop covering a map's border less often than its centre).
    Matched on whole maps instead, the baselines put 8.9 % more variance than hetero into these crops (13-32 % on
    the default worlds)."""
    for noise, epochs in (("fixed", 100), ("range", 300)):
        dm = make_dm(tmp_path, noise=noise, batch_size=6)
        power, hetero = 0.0, 0.0
        for _ in range(epochs):
            for batch in dm.train_dataloader():
                valid = batch["mask"] > 0
                power += float(((batch["noisy"] - batch["clean"])[valid].double() ** 2).sum())
                hetero += float((batch["sigma"][valid].double() ** 2).sum())
        assert power / hetero == pytest.approx(1.0, abs=0.03), noise


@pytest.mark.parametrize("noise", ["range", "blind"])
def test_training_pixel_statistics_are_the_same_read_in_loader_workers(tmp_path, noise):
    """The variance match and the blind range read the training samples in DataLoader workers (minutes in one
    process for a 480 x 640 world): the stored numbers equal one process's to the last bit."""
    one = make_dm(tmp_path / "one", noise=noise, num_workers=0).summary()["noise_record"]
    two = make_dm(tmp_path / "two", noise=noise, num_workers=2).summary()["noise_record"]
    keys = ("scale",) if noise == "range" else ("sigma_lo_mm", "sigma_hi_mm")
    assert all(isinstance(one[k], float) for k in keys) and {k: one[k] for k in keys} == {k: two[k] for k in keys}


@pytest.mark.parametrize("noise", ["range", "blind"])
def test_preparing_draws_the_same_from_the_global_generator_with_a_cold_or_a_warm_cache(tmp_path, noise):
    """The training stream starts from torch's global generator after the data are prepared: a run that computes
    the variance match (a fresh cache) and one that reads it must leave that generator in the same state, or the
    first run of a cache would not rerun bit for bit (a DataLoader's iterator draws its base seed from it)."""
    states = []
    for _ in range(2):  # the first computes the training-pixel statistics, the second reads them back
        torch.manual_seed(0)
        make_dm(tmp_path, noise=noise, num_workers=2)
        states.append(torch.get_rng_state())
    assert torch.equal(states[0], states[1])


def test_unmatched_baseline_and_none(tmp_path):
    dm = make_dm(tmp_path, noise="fixed", match_variance=False, noise_kwargs={"sigma_mm": 3.0})
    assert dm.summary()["variance_scale"] is None and dm.noise_model.scale == 1.0
    none = make_dm(tmp_path, noise="none", eval_noise="none")
    batch = next(iter(none.val_dataloader()))
    torch.testing.assert_close(batch["noisy"], batch["clean"])
    assert float(batch["sigma"].max()) > 0  # the hetero sigma_D map is carried whatever the noise model


def test_crop_larger_than_samples_is_a_config_error(tmp_path):
    with pytest.raises(ValueError, match="data.crop_size"):
        make_dm(tmp_path, crop_size=320)


def test_unknown_source_and_noise(tmp_path):
    with pytest.raises(ValueError, match="unknown data.source 'kinect'"):
        ToFDataModule(source="kinect")
    with pytest.raises(ValueError, match="unknown noise model"):
        make_dm(tmp_path, noise="pink")


def test_setup_loads_what_another_instance_prepared(tmp_path, monkeypatch):
    """Rank > 0: ``setup`` on an instance whose ``prepare_data`` never ran loads the split, the sample index
    and the variance scale that another instance (rank 0, maybe another process) wrote, recomputing nothing."""
    args = {**SMALL, "cache_dir": str(tmp_path / "cache"), "noise": "range"}
    rank0 = ToFDataModule(**args)
    rank0.prepare_data()
    assert rank0._prepared is None  # prepare_data only writes; nothing is kept on the instance
    import tofdenoise.data_modules.datasets as datasets
    import tofdenoise.physics.noise_models as nm

    monkeypatch.setattr(nm, "variance_matching_scale", lambda *a, **k: pytest.fail("variance scale recomputed"))
    monkeypatch.setattr(datasets, "compute_sample_maps", lambda *a, **k: pytest.fail("maps recomputed"))
    other = ToFDataModule(**args)
    other.setup("fit")
    rank0.setup("fit")
    assert other.splits == rank0.splits and other.split_path == rank0.split_path
    assert other.noise_model.scale == pytest.approx(rank0.noise_model.scale) and other.noise_model.scale != 1.0
    for name in ("train", "val", "test"):
        assert len(other.datasets[name]) == len(rank0.datasets[name])
    a, b = next(iter(other.val_dataloader())), next(iter(rank0.val_dataloader()))
    torch.testing.assert_close(a["noisy"], b["noisy"], rtol=0, atol=0)
    torch.testing.assert_close(a["clean"], b["clean"], rtol=0, atol=0)


def test_evaluation_inputs_do_not_depend_on_the_training_noise(tmp_path):
    """data.eval_noise (default hetero) synthesises val/test/predict inputs whatever data.noise is: runs trained
    with fixed and hetero noise are validated and tested on bit-identical inputs; their training inputs differ."""
    fixed = make_dm(tmp_path, noise="fixed", flips=False, crop_size=None)
    hetero = make_dm(tmp_path, noise="hetero", flips=False, crop_size=None)
    assert fixed.noise_model.name != hetero.noise_model.name
    for loaders in (
        lambda dm: [dm.val_dataloader()],
        lambda dm: dm.test_dataloader(),
        lambda dm: [dm.predict_dataloader()],
    ):
        a = [b for loader in loaders(fixed) for b in loader]
        b = [b for loader in loaders(hetero) for b in loader]
        assert len(a) == len(b) > 0
        for x, y in zip(a, b):
            assert x["name"] == y["name"]
            torch.testing.assert_close(x["noisy"], y["noisy"], rtol=0, atol=0)
            torch.testing.assert_close(x["mask"], y["mask"], rtol=0, atol=0)
            assert not torch.equal(x["noisy"], x["clean"])
    # the evaluation inputs are the hetero synthesis: residual / sigma_D is standard normal
    z = torch.cat([((v["noisy"] - v["clean"]) / v["sigma"])[v["mask"] > 0] for v in fixed.val_dataloader()])
    assert float(z.std()) == pytest.approx(1.0, abs=0.05)
    # training inputs follow each run's own noise: fixed noise has one std for every pixel, hetero does not
    ta, tb = fixed.datasets["train"][0], hetero.datasets["train"][0]
    torch.testing.assert_close(ta["clean"], tb["clean"], rtol=0, atol=0)
    assert not torch.equal(ta["noisy"], tb["noisy"])
    # eval_noise=fixed: the evaluation inputs follow it (variance-matched like the training baseline)
    fixed_eval = make_dm(tmp_path, noise="hetero", eval_noise="fixed")
    fv, hv = next(iter(fixed_eval.val_dataloader())), next(iter(hetero.val_dataloader()))
    assert not torch.equal(fv["noisy"], hv["noisy"])
    with pytest.raises(ValueError, match="unknown data.eval_noise 'pink'"):
        ToFDataModule(eval_noise="pink")


def test_blind_range_is_the_training_pixels_sigma_percentiles(tmp_path):
    dm = make_dm(tmp_path, noise="blind", noise_kwargs={"percentiles": [5, 95]})
    _, sigma2, _ = _train_sigma2(dm)
    lo, hi = np.percentile(np.sqrt(sigma2), [5, 95])
    model = dm.noise_model
    assert model.name == "blind"
    assert model.sigma_lo_mm == pytest.approx(lo, rel=1e-5) and model.sigma_hi_mm == pytest.approx(hi, rel=1e-5)
    assert dm.summary()["noise_record"]["pixels"] == "after_holes"
    # a training item's noise: one sigma in [lo, hi], the same at every pixel (independent of sigma_D)
    train = dm.datasets["train"]
    for i in range(4):
        item = train[i]
        noise = (item["noisy"] - item["clean"])[item["mask"] > 0].double()
        assert lo * 0.6 < float(noise.std()) < hi * 1.4
    # evaluation stays the paper's hetero synthesis
    assert dm.prepared.eval_noise_model.name == "hetero"
    given = make_dm(tmp_path, noise="blind", noise_kwargs={"sigma_lo_mm": 2.0, "sigma_hi_mm": 9.0})
    assert (given.noise_model.sigma_lo_mm, given.noise_model.sigma_hi_mm) == (2.0, 9.0)
    with pytest.raises(ValueError, match="percentiles"):
        make_dm(tmp_path, noise="blind", noise_kwargs={"percentiles": [95, 5]})
