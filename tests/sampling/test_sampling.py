"""Grids, overlap / SAR arithmetic, band layouts and capture geometry."""

import math

import numpy as np
import pytest

from cca_cli.sampling.geometry import camera_scan_geometry
from cca_cli.sampling.grid import band_layout, smallest_fft_size, square_scan
from cca_cli.sampling.overlap import grid_for_sar, overlap_for, step_m, synthetic_aperture_ratio


def _factors_7_smooth(n):
    for p in (2, 3, 5, 7):
        while n % p == 0:
            n //= p
    return n == 1


@pytest.mark.parametrize("n", [1, 2, 3, 11, 13, 22, 23, 26, 37, 97, 121, 127, 500, 511, 1021])
def test_smallest_fft_size_is_the_smallest_even_7_smooth_at_least_n(n):
    size = smallest_fft_size(n)
    assert size >= n and size % 2 == 0 and _factors_7_smooth(size)
    assert not any(k % 2 == 0 and _factors_7_smooth(k) for k in range(max(n, 2), size))


def test_square_scan_is_centred_and_row_major():
    scan = square_scan(3, 2.0)
    assert scan.shape == (3, 3) and scan.n_images == 9
    np.testing.assert_allclose(scan.centres_yx_m.mean(axis=0), 0.0, atol=1e-15)
    np.testing.assert_array_equal(scan.indices[:4], [[0, 0], [0, 1], [0, 2], [1, 0]])
    np.testing.assert_allclose(scan.centres_yx_m[1] - scan.centres_yx_m[0], [0.0, 2.0])
    assert scan.centre_index == 4
    with pytest.raises(ValueError):
        square_scan(0, 1.0)


def test_overlap_step_and_sar_arithmetic():
    assert step_m(18e-3, 0.61) == pytest.approx(0.39 * 18e-3)
    assert synthetic_aperture_ratio(1, 0.5) == 1.0
    assert synthetic_aperture_ratio(2, 0.0) == 2.0
    for bad in (-0.1, 1.0, 1.5):
        with pytest.raises(ValueError):
            step_m(1.0, bad)
    with pytest.raises(ValueError):
        synthetic_aperture_ratio(0, 0.5)


@pytest.mark.parametrize("sar", [1.0, 2.0, 3.32, 5.0, 8.8])
def test_grid_for_sar_is_the_smallest_odd_grid_reaching_the_target(sar):
    grid = grid_for_sar(sar, 0.61)
    assert grid % 2 == 1
    assert synthetic_aperture_ratio(grid, 0.61) >= sar - 1e-9
    if grid > 2:
        assert synthetic_aperture_ratio(grid - 2, 0.61) < sar


def test_overlap_for_inverts_the_sar():
    overlap = overlap_for(21, 8.8)
    assert overlap == pytest.approx(0.61)
    assert synthetic_aperture_ratio(21, overlap) == pytest.approx(8.8)
    with pytest.raises(ValueError):
        overlap_for(1, 2.0)
    with pytest.raises(ValueError):
        overlap_for(3, 10.0)  # needs a negative overlap


@pytest.mark.parametrize("radius", [2.6, 6.0, 9.8, 20.945])
def test_band_layout_picks_m_above_4r_and_an_m_that_holds_every_box(radius):
    centres = square_scan(7, 2 * radius * 0.39).centres_yx_m  # 61 % overlap, in spectrum pixels
    layout = band_layout(centres, radius)
    m, big, b = layout.lowres_size, layout.hires_size, layout.box_size
    assert m > 4 * radius and m % 2 == 0 and _factors_7_smooth(m)
    assert b >= 2 * radius and b <= m
    assert np.all(layout.box_origins >= 0) and np.all(layout.box_origins + b <= big)
    # The pupil disc lies inside its box.
    assert np.all(layout.box_centres - radius >= 0) and np.all(layout.box_centres + radius <= b - 1)
    # Box centres are the pupil centres in box coordinates.
    np.testing.assert_allclose(layout.box_origins + layout.box_centres - big // 2, centres, atol=1e-12)
    assert layout.band_radius_px == pytest.approx(np.max(np.abs(centres)) + radius)


def test_band_layout_respects_the_sensor_size():
    layout = band_layout([[0.0, 0.0]], 6.0, sensor_size=96)
    assert layout.hires_size >= 96 and layout.lowres_size <= 96


def test_band_layout_rejects_grids_forced_too_small():
    centres = square_scan(5, 4.7).centres_yx_m
    layout = band_layout(centres, 6.0)
    with pytest.raises(ValueError, match="too small"):
        band_layout(centres, 6.0, hires_size=layout.hires_size - 8)
    with pytest.raises(ValueError):
        band_layout(centres, 6.0, lowres_size=10)  # cannot hold a 16-px pupil box
    with pytest.raises(ValueError):
        band_layout(centres, 6.0, lowres_size=29)  # odd
    with pytest.raises(ValueError):
        band_layout(centres, 0.0)


def test_camera_scan_geometry_of_the_tiny_config():
    geometry, sensor_pixels = camera_scan_geometry(
        wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
        distance_m=50.0, field_width_m=12e-3, grid=5, overlap=0.61)
    assert sensor_pixels == 96
    assert geometry.pupil_radius_px == pytest.approx(45e-3 * 12e-3 / (2 * 550e-9 * 50.0))
    assert geometry.synthetic_aperture_ratio == pytest.approx(synthetic_aperture_ratio(5, 0.61))
    assert geometry.n_images == 25 and geometry.grid_shape == (5, 5) and geometry.centre_index == 12
    step_px = 0.39 * 2 * geometry.pupil_radius_px
    assert float(np.ptp(geometry.spectrum_centres_yx_px[:, 1])) == pytest.approx(4 * step_px)
    assert math.isclose(geometry.overlap, 0.61)


def test_camera_scan_geometry_rejects_too_few_pixels():
    with pytest.raises(ValueError, match="sensor pixels"):
        camera_scan_geometry(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3,
                             pixel_pitch_m=2e-6, distance_m=50.0, field_width_m=0.5e-3, grid=3, overlap=0.5)


def test_an_led_matrix_and_a_jittery_stage_keep_their_rows_and_columns():
    """An LED matrix's sines drift in x with y (sin θx = x / r), and stage readings jitter: the grid the positions
    form is still the matrix's (9 x 9 was read as 41 x 41)."""
    import cca_cli as cca
    from cca_cli.sampling.capture import grid_from_positions

    sines = cca.led_grid_sines(9, pitch_m=4e-3, height_m=90e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1e-6,
                             image_pixels=64)
    assert geometry.grid_shape == (9, 9)
    assert np.array_equal(geometry.grid_indices[:, 1], 8 - np.tile(np.arange(9), 9))   # as listed, sign −1
    rows, cols = np.divmod(np.arange(25), 5)
    stage = np.stack([rows * 2.0, cols * 2.0], axis=1) + np.random.default_rng(0).normal(0, 0.05, (25, 2))
    assert np.array_equal(grid_from_positions(stage), np.stack([rows, cols], axis=1))
