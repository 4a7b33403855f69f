"""Procedural scenes: determinism, depth range, analytic depth/amplitude, render speed."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from tofdenoise.data_modules.sources.procedural import (
    Box,
    Cylinder,
    InverseDepthPlane,
    ProceduralSource,
    SceneSpec,
    Sphere,
    Texture,
    focal_length_px,
    generate_scene,
    pixel_rays,
    render_scene,
)

UNIFORM = Texture(
    base=0.5, kind="uniform", contrast=0.0, period_mm=100.0, direction=(1.0, 0.0, 0.0), phases=(0.0, 0.0, 0.0)
)


def _spec(*prims, h=48, w=64):
    return SceneSpec(h, w, 63.5, 100.0, 5000.0, tuple(prims))


def test_scene_is_deterministic_per_seed_and_index():
    src = ProceduralSource(num_samples=3, height=60, width=80, seed=7)
    a, b = src.load("scene_000001"), src.load("scene_000001")
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    np.testing.assert_array_equal(a.amplitude, b.amplitude)
    other_index = src.load("scene_000002")
    other_seed = ProceduralSource(num_samples=3, height=60, width=80, seed=8).load("scene_000001")
    assert not np.array_equal(a.depth_mm, other_index.depth_mm)
    assert not np.array_equal(a.depth_mm, other_seed.depth_mm)


def test_depth_stays_in_configured_range_and_scenes_have_structure():
    src = ProceduralSource(num_samples=12, height=96, width=128, seed=0, min_depth_mm=300, max_depth_mm=2400)
    for sid in src.sample_ids():
        s = src.load(sid)
        assert s.valid.mean() > 0.6  # only an opening in the back wall (open background) leaves no surface
        d, amp = s.depth_mm[s.valid], s.amplitude[s.valid]
        assert d.min() >= 300 * 0.999 and d.max() <= 2400 * 1.001
        assert np.all(amp > 0) and np.all(s.depth_mm[~s.valid] == 0)
        # depth discontinuities: some neighbouring pixels jump by more than 50 mm
        assert np.abs(np.diff(s.depth_mm, axis=1)).max() > 50
    kinds = {type(p).__name__ for i in range(12) for p in generate_scene(0, i, 96, 128, 300, 2400).primitives}
    assert kinds == {"InverseDepthPlane", "Sphere", "Box", "Cylinder"}


def test_fronto_parallel_plane_depth_and_inverse_square_amplitude():
    # plane z = 1000 mm: g = (0, 0, 1/1000); z-depth 1000 everywhere; amplitude = rho cos / r_m^2 = rho / |d|^3
    depth, amp, valid = render_scene(_spec(InverseDepthPlane((0.0, 0.0, 1e-3), UNIFORM)))
    assert valid.all()
    np.testing.assert_allclose(depth, 1000.0, rtol=1e-5)
    x, y = pixel_rays(48, 64)
    norm = np.sqrt(x * x + y * y + 1.0)
    np.testing.assert_allclose(amp, 0.5 / norm**3, rtol=1e-4)


def test_sphere_box_cylinder_analytic_depths():
    f = focal_length_px(64)
    assert f == pytest.approx(32.0 / math.tan(math.radians(63.5 / 2)))
    # centre pixels (31/32) see nearly along the optical axis: depth = centre z - radius (sphere)
    wall = InverseDepthPlane((0.0, 0.0, 1.0 / 4000.0), UNIFORM)
    depth, _, _ = render_scene(_spec(wall, Sphere((0.0, 0.0, 1500.0), 200.0, UNIFORM)))
    assert depth[23:25, 31:33].mean() == pytest.approx(1300.0, abs=1.0)
    assert depth[0, 0] == pytest.approx(4000.0, rel=1e-5)  # corner: the wall
    eye = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    depth, _, _ = render_scene(_spec(wall, Box((0.0, 0.0, 1000.0), eye, (100.0, 100.0, 50.0), UNIFORM)))
    assert depth[23:25, 31:33] == pytest.approx(950.0, abs=1e-2)
    # cylinder along the optical axis: the near cap is hit at z = 1000 - 100
    depth, _, _ = render_scene(_spec(wall, Cylinder((0.0, 0.0, 1000.0), (0.0, 0.0, 1.0), 80.0, 100.0, UNIFORM)))
    assert depth[23:25, 31:33] == pytest.approx(900.0, abs=1e-2)
    # a vertical cylinder seen from the side: nearest surface at z = 1000 - radius
    depth, _, _ = render_scene(_spec(wall, Cylinder((0.0, 0.0, 1000.0), (0.0, 1.0, 0.0), 80.0, 300.0, UNIFORM)))
    assert depth[23:25, 31:33].min() == pytest.approx(920.0, abs=1.5)


def test_render_640x480_is_fast():
    src = ProceduralSource(num_samples=3)
    src.load("scene_000000")  # warm-up
    times = []
    for i in range(3):
        start = time.perf_counter()
        src.load(f"scene_{i:06d}")
        times.append(time.perf_counter() - start)
    assert sorted(times)[1] < 0.5


def test_bad_depth_range_is_rejected():
    with pytest.raises(ValueError, match="min_depth_mm"):
        ProceduralSource(min_depth_mm=500, max_depth_mm=400)


# ---------------------------------------------------------------- surfaces with no usable return (renderer 2)
def test_specular_lobe_peaks_at_normal_incidence_and_adds_to_the_lambertian_return():
    glossy = Texture(0.05, "uniform", 0.0, 100.0, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), specular=20.0, shininess=100.0)
    wall = InverseDepthPlane((0.0, 0.0, 1.0 / 1000.0), glossy)  # frontal wall at z = 1 m
    depth, amplitude, valid = render_scene(_spec(wall, h=48, w=64))
    x, y = pixel_rays(48, 64)
    cos_inc = 1.0 / np.sqrt(1 + x * x + y * y)
    range_m = depth * np.sqrt(1 + x * x + y * y) / 1000.0
    expected = (0.05 * cos_inc + 20.0 * cos_inc**100.0) / range_m**2
    np.testing.assert_allclose(amplitude, expected, rtol=1e-4)
    assert amplitude[24, 32] > 100 * amplitude[0, 0]  # a highlight in the centre, dim at glancing angles


def test_an_opening_in_the_back_wall_is_invalid_and_absorbers_return_almost_nothing():
    from tofdenoise.data_modules.sources.procedural import Opening, absorber_texture

    wall = InverseDepthPlane((0.0, 0.0, 1.0 / 2000.0), UNIFORM, Opening(-0.2, 0.2, -0.1, 0.1))
    depth, amplitude, valid = render_scene(_spec(wall))
    x, y = pixel_rays(48, 64)
    inside = (np.abs(x) <= 0.2) & (np.abs(y) <= 0.1)
    assert inside.any() and not valid[inside].any() and valid[~inside].all()
    assert (depth[inside] == 0).all() and (amplitude[inside] == 0).all()
    black = absorber_texture(np.random.default_rng(0))
    assert black.albedo(np.zeros(3), np.zeros(3), np.zeros(3)).max() <= 0.015


def test_scenes_have_absorbers_specular_surfaces_and_openings_from_their_own_stream():
    """Materials come from default_rng([seed, index, 2]): the geometry of every scene is what renderer 1 drew."""
    absorbers = specular = openings = 0
    for i in range(40):
        spec = generate_scene(0, i, 48, 64, 300.0, 2400.0)
        openings += spec.primitives[0].opening is not None
        for p in spec.primitives:
            absorbers += p.texture.base < 0.016 and p.texture.min_albedo < 0.002
            specular += p.texture.specular > 0
    assert openings >= 6 and absorbers >= 10 and specular >= 10
    assert 0.2 <= openings / 40 <= 0.5
