"""Numbers printed in Holloway et al., IEEE TCI 2016, reproduced by the library's formulas."""

import math

import pytest

from cca_cli.config.load import load_config
from cca_cli.sampling.overlap import step_m, synthetic_aperture_ratio
from cca_cli.stages.simulate import simulation_geometry
from cca_cli.units import FourierScale, spot_size_m

WAVELENGTH = 550e-9


@pytest.mark.parametrize(
    ("grid", "overlap", "paper_sar"),
    [(3, 0.61, 1.77), (7, 0.61, 3.32), (9, 0.61, 4.09), (13, 0.61, 5.64), (21, 0.61, 8.8), (23, 0.72, 7.16)],
)
def test_grid_to_sar_pairs_of_the_paper(grid, overlap, paper_sar):
    sar = synthetic_aperture_ratio(grid, overlap)
    assert sar == pytest.approx(paper_sar, rel=0.01)


def test_headline_sar_is_8_8():
    assert synthetic_aperture_ratio(21, 0.61) == pytest.approx(8.8, abs=0.05)


@pytest.mark.parametrize(
    ("aperture_m", "distance_m", "paper_spot_m"),
    [
        (75e-3, 30.0, 536e-6),
        (215e-3, 30.0, 187e-6),
        (300e-3, 30.0, 134e-6),
        (75e-3, 1000.0, 17.9e-3),
        (215e-3, 1000.0, 6.2e-3),
        (300e-3, 1000.0, 4.5e-3),
    ],
)
def test_spot_sizes_of_the_paper(aperture_m, distance_m, paper_spot_m):
    assert spot_size_m(WAVELENGTH, distance_m, aperture_m) == pytest.approx(paper_spot_m, rel=0.01)


def test_headline_pupil_radius_step_and_sensor_spot():
    d, z, width, f = 18e-3, 50.0, 64e-3, 0.8
    radius = FourierScale.fraunhofer(WAVELENGTH, z, width).pupil_radius_px(d)
    assert radius == pytest.approx(d * width / (2 * WAVELENGTH * z), rel=1e-12)
    assert radius == pytest.approx(20.945, abs=1e-3)
    assert step_m(d, 0.61) == pytest.approx(7.02e-3, rel=1e-9)
    assert spot_size_m(WAVELENGTH, f, d) == pytest.approx(2.44 * WAVELENGTH * f / d, rel=1e-12)
    assert spot_size_m(WAVELENGTH, f, d) == pytest.approx(59.6e-6, rel=0.01)


def test_headline_config_resolves_to_the_figure_5_case():
    config = load_config()  # built-in preset
    geometry, sensor_pixels = simulation_geometry(config)
    assert sensor_pixels == 512
    assert geometry.field_width_m == pytest.approx(64e-3, rel=1e-12)
    assert geometry.pupil_radius_px == pytest.approx(20.945, abs=1e-3)
    assert geometry.n_images == 21 * 21
    assert geometry.grid_shape == (21, 21)
    assert geometry.synthetic_aperture_ratio == pytest.approx(8.8, abs=1e-9)
    # Neighbouring aperture centres are 7.02 mm apart in the aperture plane.
    row = geometry.aperture_centres_yx_m[:21]
    assert float(row[1, 1] - row[0, 1]) == pytest.approx(7.02e-3, rel=1e-9)
    # The centre capture is on axis.
    assert geometry.centre_index == (21 * 21) // 2
    assert math.hypot(*geometry.spectrum_centres_yx_px[geometry.centre_index]) == pytest.approx(0.0, abs=1e-12)
