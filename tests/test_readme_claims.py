"""Claims of the README that the code decides: they must be what cca prints and does today."""

from pathlib import Path

import numpy as np

from cca_cli.commands.info import derived_lines
from cca_cli.config.load import load_config
from cca_cli.report.summary import derived_quantities
from cca_cli.stages.simulate import simulation_geometry
from cca_cli.library.simulation import simulation_layout

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


def test_the_headlines_derived_quantities_are_what_cca_prints():
    config = load_config()
    geometry, sensor = simulation_geometry(config)
    layout = simulation_layout(geometry)
    derived = derived_quantities(geometry, sensor_pixels=sensor, hires_size=layout.hires_size,
                                 lowres_size=layout.lowres_size)
    block = "\n".join(["derived quantities:", *derived_lines(derived)])
    assert block in README, block


def test_the_headlines_band_grid_is_what_the_readme_says():
    layout = simulation_layout(simulation_geometry(load_config())[0])
    assert f"{layout.lowres_size} px band grid per capture" in README
    assert f"{layout.lowres_size}² for the headline" in README
    assert np.isclose(layout.pupil_radius_px, 20.95, atol=0.005)
