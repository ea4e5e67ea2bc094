"""Which way the positions run (library.orientation): a short trial of the axes as given, swapped and flipped."""

from __future__ import annotations

import numpy as np
import pytest

import cca_cli as cca
from cca_cli.library.data import CaptureSet
from cca_cli.library.orientation import advice, arranged, orientation_trial, recorded_orientation_advice


@pytest.fixture(scope="module")
def scan():
    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    return g, cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, g, snr_db=40)


@pytest.mark.parametrize("given", ["as given", "x and y swapped", "x flipped", "x and y swapped, then x flipped"])
def test_the_trial_finds_the_arrangement_that_undoes_a_swap_or_a_flip(scan, given):
    """Each arrangement undoes itself, up to flipping both axes (which the intensities cannot tell)."""
    g, images = scan
    trial = orientation_trial(arranged(CaptureSet(images, g), given))
    assert trial.best == given
    assert trial.residuals[given] < 0.05 and min(v for k, v in trial.residuals.items() if k != given) > 0.1
    assert trial.clearly_other == (None if given == "as given" else given)
    text = advice(trial)
    assert (text is None) is (given == "as given")
    if text is not None:
        assert text.startswith(f"the captures fit far better with their positions' {given} (data residual 0.0")


def test_flipping_both_axes_is_no_other_arrangement(scan):
    g, images = scan
    twice = arranged(arranged(CaptureSet(images, g), "x and y swapped, then x flipped"), "x and y swapped, then x flipped")
    np.testing.assert_allclose(twice.geometry.spectrum_centres_yx_px, -np.asarray(g.spectrum_centres_yx_px))
    trial = orientation_trial(twice)
    assert trial.best == "as given" and trial.clearly_other is None


def test_frames_scaled_each_on_their_own_or_few_captures_are_not_tried(scan):
    g, images = scan
    assert recorded_orientation_advice(images, None, g, "per_frame") is None
    assert recorded_orientation_advice(images[:3], None, g.select([0, 1, 2])) is None
