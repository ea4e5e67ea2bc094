"""Shared fixtures: a tiny run configuration that simulates, reconstructs and reports in seconds.

Add fixtures below; keep them small.
"""

import copy
import os

import pytest
import yaml

# Estimated FFTW plans (the default) take no time to make and are the same on every run; a developer's own
# CCA_FFTW_PLANNING is kept out of the suite (tests/optics/test_planning.py covers the timed planning).
os.environ["CCA_FFTW_PLANNING"] = "estimate"

#: 96-px sensor (12 mm field, 125 µm object pixels), pupil radius 9.8 spectrum px, 5 x 5 grid at 61 %:
#: the centre image resolves 6-px bars, the recovery 2-px bars.
TINY_CONFIG = {
    "run": {"stages": ["simulate", "reconstruct", "report"]},
    "optics": {"wavelength_m": 550e-9, "focal_length_m": 0.8, "aperture_diameter_m": 45e-3,
               "pixel_pitch_m": 2e-6, "distance_m": 50.0},
    "scene": {"kind": "resolution_chart", "size_px": 96, "field_width_m": 12e-3, "widths_px": [6, 4, 3, 2, 1]},
    "array": {"grid": 5, "overlap": 0.61},
    "noise": {"model": "gaussian", "snr_db": 40.0, "seed": 1},
    "simulate": {"store": "sensor"},
    "reconstruct": {"engine": "altmin", "tau": 1e-3, "iterations": 30, "tol": 0.0},
    "report": {"mtf_threshold": 0.2, "figures": True},
}


@pytest.fixture
def tiny_config_data():
    """A fresh, mutable copy of :data:`TINY_CONFIG` (a dict as read from YAML)."""
    return copy.deepcopy(TINY_CONFIG)


@pytest.fixture
def write_config(tmp_path):
    """Write a config dict (default: the tiny config) as YAML under ``tmp_path`` and return its path."""

    def write(data=None, name="tiny.yaml"):
        path = tmp_path / name
        path.write_text(yaml.safe_dump(copy.deepcopy(TINY_CONFIG) if data is None else data, sort_keys=False))
        return path

    return write


@pytest.fixture(scope="session")
def tiny_run_config():
    """:data:`TINY_CONFIG` validated as a (frozen) RunConfig; derive variants with ``apply_overrides``."""
    from cca_cli.config.load import parse_config

    return parse_config(copy.deepcopy(TINY_CONFIG), source="tiny")


@pytest.fixture(scope="session")
def small_camera_array():
    """A simulated 3 x 3 array of cameras that each took one capture: ``make(first_id)`` gives its images and
    its geometry, the cameras numbered from ``first_id``."""
    import numpy as np

    import cca_cli as cca

    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, g, snr_db=40)

    def make(first_id: int = 0):
        array = cca.stage_scan(g.aperture_centres_yx_m, wavelength_m=550e-9, focal_length_m=0.8,
                               aperture_diameter_m=45e-3, pixel_pitch_m=2e-6, distance_m=50, image_pixels=64,
                               camera_index=np.arange(9) + first_id)
        return images, array

    return make
