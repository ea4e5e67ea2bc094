"""The imaging chain against a closed form: a point source seen through one aperture is the Airy pattern."""

import numpy as np
import pytest
from scipy.special import j1

import cca_cli as cca
from cca_cli.optics import fft

#: A camera whose aperture passes a disc of about 11.6 spectrum pixels; 3 x 3 positions, the centre one on axis.
OPTICS = dict(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=40e-3, pixel_pitch_m=2e-6, distance_m=50)


def _airy(v):
    v = np.asarray(v, np.float64)
    safe = np.where(v == 0, 1.0, v)
    return np.where(v == 0, 1.0, (2 * j1(safe) / safe) ** 2)


@pytest.fixture(scope="module")
def point_image():
    geometry = cca.camera_scan(**OPTICS, field_width_m=16e-3, grid=3, overlap=0.6)
    n = int(round(geometry.field_width_m / (OPTICS["pixel_pitch_m"] * OPTICS["distance_m"] / OPTICS["focal_length_m"])))
    point = np.zeros((n, n), np.complex64)
    point[n // 2, n // 2] = 1.0
    images = cca.simulate(point, geometry, snr_db=None)
    return geometry, point, images[geometry.centre_index]


def test_a_point_source_images_as_the_airy_pattern(point_image):
    geometry, point, image = point_image
    n = image.shape[-1]
    radius = geometry.pupil_radius_px
    y, x = np.mgrid[:n, :n] - n // 2
    v = 2 * np.pi * radius * np.hypot(y, x) / n      # the Airy argument in sensor pixels of the object plane
    airy = _airy(v)
    inner = v < 10.2                                 # the central lobe and two rings
    peak = float(image[n // 2, n // 2])
    np.testing.assert_allclose(image[inner] / peak, airy[inner], atol=0.01)
    # A unit point on an n-pixel field has the flat spectrum 1/n, so the peak is (ΣP/n²)² = (A/n²)² with A = πR²
    # and the energy Σ|P|²/n² (Parseval). The pupil's edge falls from 1 to 0 over one pixel, where P² < P: the
    # energy lacks 1/6 of a pixel per unit of circumference, A(1 − 1/(3R)).
    area = np.pi * radius ** 2
    assert peak / (area / n ** 2) ** 2 == pytest.approx(1.0, rel=0.01)
    assert image.sum() / (area * (1 - 1 / (3 * radius)) / n ** 2) == pytest.approx(1.0, rel=0.005)


def test_the_first_dark_ring_lies_at_the_papers_spot_radius(point_image):
    """Holloway et al.: the diffraction spot of an aperture d at distance z is 2.44·λ·z/d across (1.22·λ·z/d radius)."""
    geometry, _, image = point_image
    n = image.shape[-1]
    fine = 16
    profile = np.abs(fft.fourier_interpolate(image, (n * fine, n * fine)))[n * fine // 2, n * fine // 2:]
    first_zero = int(np.argmax(np.diff(profile) > 0))   # the profile falls to the first minimum, then rises
    pixel_m = geometry.field_width_m / n
    radius_m = first_zero / fine * pixel_m
    expected = 1.22 * OPTICS["wavelength_m"] * OPTICS["distance_m"] / OPTICS["aperture_diameter_m"]
    assert radius_m == pytest.approx(expected, rel=0.02)
