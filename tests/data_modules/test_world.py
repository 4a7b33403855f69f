"""The built-in world is as uneven as a real camera's (issue 22's targets), measured on the default recipe.

- sigma_D on the default synthetic test split (``make train``'s data: 300 procedural scenes of 144 x 192, the
  physical signal route of the default camera) spans p95/p5 >= 8, as in real frames (shared notes: 7-10 where
  shot noise dominates, more where read noise does); the paper's linear mapping into the old chosen interval
  [3000, 50000] e- gave 4.75.
- Holes come from the scene and the camera: the test split's inputs lose some pixels in every scene.
- The signal route is checked before any work: a source without a radiometric amplitude or a camera without a
  photometric gain is refused with a line naming data.signal_route.
"""

from __future__ import annotations

import hydra
import numpy as np
import pytest

from tofdenoise.config import compose_config
from tofdenoise.data_modules import ToFDataModule


@pytest.fixture(scope="module")
def default_test_split(tmp_path_factory):
    cfg = compose_config([f"++data.cache_dir={tmp_path_factory.mktemp('cache')}"])
    dm = hydra.utils.instantiate(cfg.data, _convert_="all")
    assert dm.signal_route == "physical"
    dm.prepare_data()
    dm.setup("test")
    return dm.datasets["test"]


def test_default_test_split_sigma_spans_a_real_cameras_range(default_test_split):
    sigmas, invalid = [], []
    for i in range(len(default_test_split)):
        item = default_test_split[i]
        mask = item["mask"][0] > 0.5
        sigmas.append(item["sigma"][0][mask].numpy())
        invalid.append(1.0 - float(mask.double().mean()))
    p5, p95 = np.percentile(np.concatenate(sigmas), [5, 95])
    assert p95 / p5 >= 8.0, f"sigma_D p95/p5 = {p95 / p5:.2f} ({p5:.2f} .. {p95:.2f} mm)"
    assert min(invalid) > 0.0 and 0.03 <= float(np.mean(invalid)) <= 0.25


def test_signal_route_is_checked_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="data.signal_route=physical needs the calibration field 'signal_at_1m_e'"):
        ToFDataModule(
            signal_route="physical",
            sensor={**_default_dict(), "signal_at_1m_e": None},
            cache_dir=str(tmp_path),
        )
    with pytest.raises(ValueError, match="unknown data.signal_route 'photons'"):
        ToFDataModule(signal_route="photons", cache_dir=str(tmp_path))


def test_physical_route_refuses_a_source_without_radiometric_amplitude(tmp_path):
    (tmp_path / "list.txt").write_text("a\n")
    with pytest.raises(ValueError, match="radiometric amplitude"):
        ToFDataModule(
            source="folder", source_kwargs={"root": str(tmp_path)}, signal_route="physical", cache_dir=str(tmp_path)
        )


def _default_dict() -> dict:
    from tofdenoise.physics.calibration import resolve_calibration

    return resolve_calibration("default").to_dict()


def test_stand_in_capture_set_loses_pixels_like_a_real_camera(tmp_path):
    """The stand-in real set (cam75, its realset seed and size): 3-25 % of the input pixels are invalid on average
    (real frames lose 6-24 %), from the scene (absorbers, specular highlights, openings) and the camera
    (threshold, full well, mixed pixels), never all of a frame."""
    import json

    from tofdenoise.data_modules.capture_simulation import simulate_capture_set
    from tofdenoise.data_modules.realset import REALSET_CAMERA, REALSET_SEED
    from tofdenoise.physics.calibration import resolve_calibration

    simulate_capture_set(
        tmp_path, scenes=16, frames=4, height=144, width=192, seed=REALSET_SEED,
        calib=resolve_calibration(REALSET_CAMERA), mixed_pixels=3,
    )  # fmt: skip
    infos = [json.loads(p.read_text()) for p in sorted(tmp_path.glob("scene_*/scene.json"))]
    invalid = np.array([1.0 - i["input_valid_fraction"] for i in infos])
    assert len(invalid) == 16 and 0.03 <= invalid.mean() <= 0.25 and invalid.max() < 0.9
    assert all(i["reference_exposure"] >= 1.0 for i in infos)


def test_physical_maps_hold_only_what_the_camera_can_measure():
    """A pixel below the camera's threshold or saturated is a hole in every frame: it is not in the maps, so its
    sigma_D (hundreds of mm) never enters the hetero mean variance the Gaussian baselines are matched to."""
    from tofdenoise.data_modules.maps import compute_sample_maps
    from tofdenoise.data_modules.sources.procedural import ProceduralSource
    from tofdenoise.physics.calibration import resolve_calibration
    from tofdenoise.physics.noise_models import FixedNoise, variance_matching_scale
    from tofdenoise.physics.photometry import field_cosine, physical_signal_e, saturated
    from tofdenoise.physics.simulator import default_min_amplitude_e

    calib = resolve_calibration("default")
    c1, thr = calib.tap_response.first_harmonic_amplitude, default_min_amplitude_e(calib)
    src = ProceduralSource(num_samples=12, height=72, width=96, max_depth_mm=0.8 * calib.unambiguous_range_mm)
    cos_field = field_cosine(72, 96, src.hfov_deg)
    dropped = 0
    samples = []
    for sid in src.sample_ids():
        raw = src.load(sid)
        maps = compute_sample_maps(raw, calib, signal_route="physical", cos_field=cos_field)
        m = maps.mask
        assert (maps.signal_e[m] * c1 >= thr).all() and not saturated(maps.depth_mm[m], maps.signal_e[m], calib).any()
        signal = physical_signal_e(raw.amplitude, calib, cos_field)
        dropped += int((raw.valid & ~m).sum())
        assert ((signal[raw.valid & ~m] * c1 < thr) | saturated(raw.depth_mm, signal, calib)[raw.valid & ~m]).all()
        samples.append((maps.depth_mm, maps.sigma_mm, m))
    assert dropped > 0  # the scenes do have unmeasurable surfaces
    sigma_max = max(float(s[m].max()) for _, s, m in samples)
    assert sigma_max < 200.0  # near the threshold sigma_D is ~100 mm; below it, it ran to thousands
    fixed_std = variance_matching_scale(FixedNoise(), samples) * FixedNoise().sigma_mm  # scale x its 5 mm
    rms = float(np.sqrt(np.mean(np.concatenate([(s[m] ** 2) for _, s, m in samples]))))
    assert fixed_std == pytest.approx(rms, rel=1e-6)
