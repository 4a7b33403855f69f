"""The physical signal route: inverse-square law, incidence, exposure, vignetting and saturation in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tofdenoise.physics.calibration import resolve_calibration
from tofdenoise.physics.photometry import (
    field_cosine,
    inverse_square_signal_e,
    peak_tap_e,
    physical_signal_e,
    saturated,
    vignetting,
)
from tofdenoise.physics.uncertainty import tap_responses

CALIB = resolve_calibration("default")


def test_inverse_square_law_incidence_and_exposure():
    k = 15000.0
    assert inverse_square_signal_e(1.0, 1.0, 1000.0, k) == pytest.approx(k)
    # half the distance: four times the signal; twice: a quarter
    a = inverse_square_signal_e(0.5, 1.0, np.array([500.0, 1000.0, 2000.0]), k)
    np.testing.assert_allclose(a, [4 * 0.5 * k, 0.5 * k, 0.25 * 0.5 * k], rtol=1e-12)
    # Lambert: cos 60 deg halves it; exposure scales it
    assert inverse_square_signal_e(0.2, math.cos(math.pi / 3), 1500.0, k, exposure=3.0) == pytest.approx(
        k * 3.0 * 0.2 * 0.5 / 1.5**2
    )


def test_field_cosine_and_vignetting_closed_form():
    h, w, hfov = 4, 6, 90.0
    c = field_cosine(h, w, hfov)
    f = (w / 2) / math.tan(math.radians(hfov / 2))  # 3 px
    x, y = (0.5 - 3) / f, (0.5 - 2) / f  # top-left pixel centre
    assert c[0, 0] == pytest.approx(1 / math.sqrt(1 + x * x + y * y))
    assert c.shape == (h, w) and np.all(c <= 1) and c[1:3, 2:4].min() > c[0, 0]
    np.testing.assert_allclose(vignetting(c, 4.0), c**4)
    np.testing.assert_allclose(vignetting(c, None), 1.0)
    np.testing.assert_allclose(vignetting(c, 0.0), 1.0)


def test_physical_signal_is_k_times_amplitude_times_vignetting():
    amp = np.array([[1.0, 0.25], [np.nan, -1.0]])
    cos_field = np.array([[1.0, 0.8], [1.0, 1.0]])
    a = physical_signal_e(amp, CALIB, cos_field, exposure=2.0)
    k, p = CALIB.signal_at_1m_e, CALIB.vignetting_cos_power
    np.testing.assert_allclose(a, [[2 * k, 2 * k * 0.25 * 0.8**p], [0.0, 0.0]])
    with pytest.raises(ValueError, match="signal_at_1m_e"):
        physical_signal_e(amp, CALIB.replace(signal_at_1m_e=None))


def test_saturation_is_the_brightest_expected_tap_at_the_full_well():
    depth = np.full(5, 1234.0)
    r, _ = tap_responses(depth[:1], CALIB)
    r_max = float(np.asarray(r).max())
    a_sat = (CALIB.full_well_e - CALIB.dark_mean_e) / r_max
    signal = a_sat * np.array([0.5, 0.999, 1.0001, 1.001, 2.0])
    np.testing.assert_allclose(peak_tap_e(depth, signal, CALIB), signal * r_max + CALIB.dark_mean_e)
    np.testing.assert_array_equal(saturated(depth, signal, CALIB), [False, False, True, True, True])
    assert not saturated(np.array([0.0]), np.array([1e9]), CALIB).any()  # invalid depth: no decision


def test_the_default_calibrations_saturation_distances_stated_in_the_docs():
    """docs/physics.md (``signal_at_1m_e`` row): K = 120 ke-, full well 100 ke-, dark 2 ke-. A white frontal target at
    1 m returns a = 120 ke-; its brightest tap, hand-computed from c(x) = 1 + 0.5 cos x + 0.01 cos 3x at the four
    taps, is 173.9 ke-, far above the full well. White (rho = 1) saturates at every distance from 0.3 m out to
    1346 mm, rho = 0.9 out to 1259 mm (the docs said "white at 0.9 m and nearer"); a 5 % surface at 2.4 m returns
    1042 e-."""
    k = CALIB.signal_at_1m_e
    assert (k, CALIB.full_well_e, CALIB.dark_mean_e) == (120000.0, 100000.0, 2000.0)
    psi = 4 * math.pi * CALIB.modulation_frequency_hz * 1000.0 / 299792458e3
    x = psi - 2 * math.pi * np.arange(4) / 4
    peak = 120000.0 * float(np.max(1 + 0.5 * np.cos(x) + 0.01 * np.cos(3 * x))) + 2000.0
    assert peak == pytest.approx(173.9e3, abs=50)
    assert float(peak_tap_e(1000.0, inverse_square_signal_e(1.0, 1.0, 1000.0, k), CALIB)) == pytest.approx(peak)
    d = np.arange(300.0, 2000.0, 1.0)
    for rho, last in ((1.0, 1346.0), (0.9, 1259.0)):
        sat = saturated(d, inverse_square_signal_e(rho, 1.0, d, k), CALIB)
        np.testing.assert_array_equal(sat, d <= last)
    assert float(inverse_square_signal_e(0.05, 1.0, 2400.0, k)) == pytest.approx(1042, abs=1)
