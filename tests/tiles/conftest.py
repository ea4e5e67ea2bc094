"""Shared fixtures of the tiled-reconstruction tests: one 2-worker LocalCluster and a small wide-ish frame."""

from __future__ import annotations

import copy

import pytest

#: A 160-px frame of a natural scene (20 mm at 125 µm), pupil radius 16 spectrum px, 5 x 5 grid at 60 %.
FRAME_CONFIG = {
    "optics": {"wavelength_m": 550e-9, "focal_length_m": 0.8, "aperture_diameter_m": 44e-3,
               "pixel_pitch_m": 2e-6, "distance_m": 50.0},
    "scene": {"kind": "natural", "size_px": 160, "field_width_m": 20e-3},
    "array": {"grid": 5, "overlap": 0.6},
    "noise": {"model": "gaussian", "snr_db": 40.0, "seed": 3},
    "reconstruct": {"engine": "momentum", "iterations": 40, "tol": 0.0,
                    "options": {"pupil_recovery": "shared", "pupil_model": "zernike", "pupil_estimate": False},
                    "tiles": {"size_px": 96, "overlap_px": 32}},
}


@pytest.fixture(scope="session")
def client():
    from cca_cli.workflows.cluster import open_client

    with open_client(workers=2) as c:
        yield c


@pytest.fixture(scope="session")
def frame_config():
    from cca_cli.config.load import parse_config

    return parse_config(copy.deepcopy(FRAME_CONFIG), source="frame")


@pytest.fixture(scope="session")
def frame_captures(tmp_path_factory, frame_config):
    """captures.h5 of :data:`FRAME_CONFIG`."""
    from cca_cli.io.h5 import Provenance
    from cca_cli.stages import simulate

    path = tmp_path_factory.mktemp("frame") / "captures.h5"
    simulate.run(frame_config, path, provenance=Provenance.make("simulate", "", ""))
    return path
