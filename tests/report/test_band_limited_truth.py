"""The band-limited truth: what the synthetic aperture can see of the object."""

import numpy as np

from cca_cli.optics import fft
from cca_cli.report.summary import band_limited_truth
from cca_cli.sampling.geometry import camera_scan_geometry


def _geometry(grid, overlap):
    geometry, _ = camera_scan_geometry(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3,
                                       pixel_pitch_m=2e-6, distance_m=50, field_width_m=16e-3, grid=grid,
                                       overlap=overlap)
    return geometry


def test_keeps_what_the_apertures_pass_and_removes_the_rest():
    geometry = _geometry(5, 0.61)
    size = 128
    rng = np.random.default_rng(0)
    field = (rng.random((size, size)) + 0.5).astype(np.complex64)
    band = band_limited_truth(field, geometry)
    spectrum = fft.fft2c(np.sqrt(band).astype(np.complex64))
    assert band.shape == (size, size)
    # A constant object lies entirely inside the band: it is returned unchanged.
    flat = band_limited_truth(np.ones((size, size), np.complex64), geometry)
    np.testing.assert_allclose(flat, 1.0, atol=1e-4)
    # Detail beyond the synthetic aperture is removed: the band-limited intensity is smoother.
    assert np.std(np.diff(band, axis=1)) < np.std(np.diff(np.abs(field) ** 2, axis=1))
    assert np.isfinite(spectrum).all()


def test_wider_synthetic_aperture_keeps_more_of_the_object():
    size = 128
    y, x = np.mgrid[:size, :size]
    bars = ((x // 4) % 2).astype(np.complex64)  # 16 cycles across: beyond a 3x3 band, inside a 9x9 one
    narrow = band_limited_truth(bars, _geometry(3, 0.61))
    wide = band_limited_truth(bars, _geometry(9, 0.61))
    error = lambda image: float(np.sqrt(np.mean((image - np.abs(bars) ** 2) ** 2)))  # noqa: E731
    assert error(wide) < error(narrow)
