"""Images scaled each on its own (``frame_scale: per_frame``): the recovery fits each capture's brightness."""

from dataclasses import replace

import numpy as np
import pytest

import cca_cli as cca
from cca_cli.engines.registry import resolve


@pytest.fixture(scope="module")
def rescaled_frames():
    """Recorded-like LED-array frames, each multiplied by its own factor (as frames scaled to their own maximum)."""
    geometry = cca.led_array(cca.led_grid_sines(5, pitch_m=4e-3, height_m=60e-3), wavelength_m=532e-9,
                             numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6, image_pixels=48)
    chart = cca.resolution_chart(48 * 3, widths=(6, 4, 3, 2)).image
    images = cca.simulate(chart, geometry, snr_db=40)
    factors = np.random.default_rng(4).uniform(0.7, 1.4, len(images))
    scaled = (images * factors[:, None, None]).astype(np.float32)
    return cca.CaptureSet(scaled, geometry, units="counts/s", boundary="open", frame_scale="per_frame"), factors


def test_each_capture_s_brightness_is_found_when_the_frames_were_scaled_on_their_own(rescaled_frames):
    captures, factors = rescaled_frames
    fitted = cca.reconstruct(captures, threads=1)
    assumed = cca.reconstruct(replace(captures, frame_scale="shared"), threads=1)
    assert fitted.options["brightness"] is True and assumed.options["brightness"] is False
    found = fitted.calibration.brightness / factors
    found /= np.median(found)   # one common factor is the object's
    # each bright-field capture's own factor to a few percent (a dark-field one is held nearer 1 by the prior)
    bright = fitted.fit.bright_field_mask
    assert np.abs(found[bright] - 1).max() < 0.04
    assert np.corrcoef(fitted.calibration.brightness, factors)[0, 1] > 0.95
    assert fitted.fit.all < 0.8 * assumed.fit.all
    told = cca.reconstruct(captures, threads=1, brightness=False, max_iterations=2)
    assert told.options["brightness"] is False


def test_the_frame_scale_is_kept_by_files_and_holds_for_simulations_too(rescaled_frames, tmp_path):
    captures, _ = rescaled_frames
    cca.save(captures, tmp_path / "raw.h5")
    assert cca.load(tmp_path / "raw.h5").frame_scale == "per_frame"
    cca.save(replace(captures, frame_scale="shared"), tmp_path / "shared.h5")
    assert cca.load(tmp_path / "shared.h5").frame_scale == "shared"
    assert resolve("momentum", "simulation", {}, frame_scale="per_frame")[1].brightness is True
    with pytest.raises(ValueError, match="frame_scale must be"):
        cca.CaptureSet(captures.intensity, captures.geometry, frame_scale="each")


def test_frames_scaled_to_their_own_maximum_come_back_as_the_recorded_ones():
    """Dark-field frames scaled up by tens of times: without a pull towards brightness 1 the object is the one the
    unscaled frames give; with it, the dark field's detail comes back too strong."""
    geometry = cca.led_array(cca.led_grid_sines(7, pitch_m=4e-3, height_m=60e-3), wavelength_m=530e-9,
                             numerical_aperture=0.1, pixel_pitch_object_m=1e-6, image_pixels=64)
    chart = cca.resolution_chart(64 * 3, widths=(6, 4, 3, 2)).image
    images = cca.simulate(chart, geometry, snr_db=40).astype(np.float32)
    peaks = images.reshape(len(images), -1).max(axis=1)
    assert peaks.max() / peaks.min() > 20
    scaled = cca.CaptureSet(images / peaks[:, None, None], geometry, units="counts/s", boundary="open",
                            frame_scale="per_frame")
    recorded = cca.reconstruct(replace(scaled, intensity=images, frame_scale="shared"), threads=1).object
    free = cca.reconstruct(scaled, threads=1)
    pulled = cca.reconstruct(scaled, threads=1, brightness_prior=0.05).object
    assert free.options["brightness_prior"] == 0.0

    def likeness(obj):
        return np.corrcoef(np.abs(obj).ravel(), np.abs(recorded).ravel())[0, 1]

    assert likeness(free.object) > 0.99 and likeness(free.object) > likeness(pulled) + 0.02   # 0.994, 0.954
