"""Shared fixtures of the entry-point tests: one data cache per session, a camera file of the user's own (the tiny
run settings, ``tiny``, are in tests/conftest.py: the training and reliability tests use them too)."""

from __future__ import annotations

import pytest


@pytest.fixture
def own_camera_file():
    """A factory: ``own_camera_file(folder)`` writes a camera of the user's own as a calibration file (the
    default with another dark noise), what ``++data.sensor=<file>`` points at, and returns
    ``(calibration, path)``."""
    from tofdenoise.physics.calibration import SensorCalibration, resolve_calibration, save_calibration

    def write(folder):
        own = SensorCalibration.from_dict({**resolve_calibration(None).to_dict(), "dark_std_e": 55.0})
        return own, save_calibration(own, folder / "mycam" / "calibration.yaml")

    return write


@pytest.fixture(scope="session")
def data_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("data-cache")
