"""SI ↔ pixel conversions of cca_cli.units."""

import numpy as np
import pytest

from cca_cli.units import (
    AIRY_SPOT_FACTOR,
    FourierScale,
    led_fourier_scale,
    object_pixel_pitch_m,
    sensor_field_width_m,
    spot_size_m,
)


def test_object_pixel_pitch_and_field_width():
    assert object_pixel_pitch_m(2e-6, 0.8, 50.0) == pytest.approx(125e-6)
    assert sensor_field_width_m(512, 2e-6, 0.8, 50.0) == pytest.approx(64e-3)


def test_spot_size_is_airy_diameter():
    assert AIRY_SPOT_FACTOR == 2.44
    assert spot_size_m(500e-9, 1.0, 1e-3) == pytest.approx(2.44 * 500e-9 / 1e-3)
    # Doubling the aperture halves the spot; doubling the distance doubles it.
    base = spot_size_m(550e-9, 30.0, 0.075)
    assert spot_size_m(550e-9, 30.0, 0.15) == pytest.approx(base / 2)
    assert spot_size_m(550e-9, 60.0, 0.075) == pytest.approx(base * 2)


def test_fourier_scale_round_trip_and_radius():
    scale = FourierScale.fraunhofer(550e-9, 50.0, 64e-3)
    assert scale.metres_per_pixel == pytest.approx(550e-9 * 50.0 / 64e-3)
    positions = np.array([[-7.02e-3, 0.0], [3.5e-3, 14.04e-3]])
    np.testing.assert_allclose(scale.to_metres(scale.to_pixels(positions)), positions, rtol=1e-14)
    assert scale.pupil_radius_px(18e-3) == pytest.approx(float(scale.to_pixels(9e-3)))
    # The radius in spectrum pixels grows with the field of view (more cycles per field).
    wider = FourierScale.fraunhofer(550e-9, 50.0, 128e-3)
    assert wider.pupil_radius_px(18e-3) == pytest.approx(2 * scale.pupil_radius_px(18e-3))


def test_led_fourier_scale_takes_numerical_aperture():
    scale = led_fourier_scale(500e-9, 1e-3)
    # NA 0.1 over a 1 mm field at 500 nm reaches 0.1 * 1e-3 / 500e-9 = 200 spectrum pixels.
    assert float(scale.to_pixels(0.1)) == pytest.approx(200.0)


def test_fourier_scale_is_frozen():
    scale = FourierScale(1e-4)
    with pytest.raises(Exception):
        scale.metres_per_pixel = 2.0
