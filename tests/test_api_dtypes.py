"""The Python API takes any real or complex NumPy dtype a user has, and always answers in the same dtypes."""

import numpy as np
import pytest

import cca_cli as cca


@pytest.fixture(scope="module")
def geometry():
    return cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                           distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)


@pytest.fixture(scope="module")
def chart():
    return cca.resolution_chart(64, widths=(4, 2)).image


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.complex64, np.complex128, np.uint8, np.int16, bool])
def test_simulate_reads_any_object_dtype_and_returns_float32(geometry, chart, dtype):
    reference = cca.simulate(chart.astype(np.float64), geometry, snr_db=None)
    images = cca.simulate(chart.astype(dtype), geometry, snr_db=None)
    assert images.dtype == np.float32 and images.shape == reference.shape
    np.testing.assert_allclose(images, reference, atol=1e-5 * float(reference.max()))


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.float16, np.uint16, np.int32])
def test_reconstruct_reads_any_real_intensity_dtype_and_returns_complex64(geometry, chart, dtype):
    images = cca.simulate(chart, geometry, snr_db=None)
    scale = 1000.0 if np.issubdtype(dtype, np.integer) else 1.0   # counts, as a camera gives them
    given = np.round(images * scale).astype(dtype) if scale != 1 else images.astype(dtype)
    as_float32 = given.astype(np.float32)
    result = cca.reconstruct(given, geometry, engine="altmin", iterations=3, tol=0)
    reference = cca.reconstruct(as_float32, geometry, engine="altmin", iterations=3, tol=0)
    assert result.object.dtype == result.spectrum.dtype == np.complex64
    assert result.intensity.dtype == result.amplitude.dtype == result.phase.dtype == np.float32
    assert result.history["residual"].dtype == np.float64
    np.testing.assert_array_equal(result.spectrum, reference.spectrum)   # read as float32 before anything else


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint8])
def test_weights_of_any_real_dtype_read_alike(geometry, chart, dtype):
    images = cca.simulate(chart, geometry, snr_db=None)
    ones = np.ones(images.shape, dtype)
    weighted = cca.reconstruct(images, geometry, engine="altmin", iterations=2, tol=0, weight=ones)
    plain = cca.reconstruct(images, geometry, engine="altmin", iterations=2, tol=0)
    np.testing.assert_allclose(weighted.spectrum, plain.spectrum, atol=1e-6 * np.abs(plain.spectrum).max())


@pytest.mark.parametrize("kind", [list, np.float32, np.float64])
def test_geometry_positions_read_from_lists_and_any_float_dtype(kind):
    steps = [[y, x] for y in (-1e-3, 0, 1e-3) for x in (-1e-3, 0, 1e-3)]
    positions = steps if kind is list else np.asarray(steps, kind)
    g = cca.stage_scan(positions, wavelength_m=633e-9, focal_length_m=75e-3, aperture_diameter_m=2.5e-3,
                       pixel_pitch_m=3.75e-6, distance_m=1.5, image_pixels=128)
    reference = cca.stage_scan(np.asarray(steps, np.float64), wavelength_m=633e-9, focal_length_m=75e-3,
                               aperture_diameter_m=2.5e-3, pixel_pitch_m=3.75e-6, distance_m=1.5, image_pixels=128)
    assert g.spectrum_centres_yx_px.dtype == np.float64
    np.testing.assert_allclose(g.spectrum_centres_yx_px, reference.spectrum_centres_yx_px, rtol=1e-6)
