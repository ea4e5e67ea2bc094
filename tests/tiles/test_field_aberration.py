"""The simulated lens with a field-varying aberration: weights, its Zernike modes, its limits, its truth on file."""

from __future__ import annotations

import copy

import h5py
import numpy as np
import pytest

from cca_cli.config.load import parse_config
from cca_cli.optics.zernike import zernike_basis, zernike_modes
from cca_cli.errors import ConfigError
from cca_cli.io.h5 import Provenance
from cca_cli.optics import fft
from cca_cli.optics.field_aberration import (MODES, aberration_at, field_varying_intensity, hat_weights,
                                             node_positions, zernike_phases)
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import band_layout
from cca_cli.stages import simulate

from .conftest import FRAME_CONFIG


def _layout():
    centres = np.array([[0.0, 0.0], [0.0, 6.4], [-6.4, 0.0], [6.4, -6.4]])
    return band_layout(centres, 8.0, sensor_size=64)


def test_hat_weights_sum_to_one_and_peak_at_their_node():
    nodes = node_positions(5, 200)
    weights = hat_weights(nodes, np.linspace(-3, 203, 777))
    np.testing.assert_allclose(weights.sum(axis=0), 1.0, atol=1e-12)
    np.testing.assert_allclose(hat_weights(nodes, nodes), np.eye(5), atol=1e-12)


def test_modes_match_the_engines_zernike_normalisation():
    layout = _layout()
    ours = zernike_phases(layout)
    engines = zernike_basis(layout.box_size, layout.box_centres, layout.pupil_radius_px, order=3)
    index = [zernike_modes(3).index(mode) for mode in MODES]
    np.testing.assert_allclose(ours, engines[index], atol=1e-4)


def test_equal_nodes_are_the_ordinary_model_with_that_pupil():
    layout = _layout()
    rng = np.random.default_rng(0)
    obj = (rng.random((layout.hires_size,) * 2) + 0.5).astype(np.complex64)
    spectrum = fft.fft2c(obj).astype(np.complex64)
    coefficients = np.array([0.3, -0.2, 0.1, 0.05, -0.05])
    waves = np.broadcast_to(coefficients, (3, 3, 5))
    varying = field_varying_intensity(spectrum, layout, waves, 64)
    disc = circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px)
    phase = np.tensordot(coefficients, zernike_phases(layout), axes=1)
    fixed = ForwardModel(layout, disc * np.exp(1j * phase)).sensor_intensity(spectrum)
    assert np.linalg.norm(varying - fixed) / np.linalg.norm(fixed) < 1e-5


def test_aberration_at_interpolates_the_nodes():
    nodes = node_positions(3, 101)
    waves = np.arange(3 * 3 * 5, dtype=float).reshape(3, 3, 5)
    np.testing.assert_allclose(aberration_at(waves, nodes, [[nodes[1], nodes[2]]])[0], waves[1, 2])
    middle = aberration_at(waves, nodes, [[(nodes[0] + nodes[1]) / 2, nodes[0]]])[0]
    np.testing.assert_allclose(middle, (waves[0, 0] + waves[1, 0]) / 2)


def _aberrated_config(**aberration):
    data = copy.deepcopy(FRAME_CONFIG)
    data["aberration"] = aberration
    data["scene"]["size_px"] = 96
    data["scene"]["field_width_m"] = 12e-3
    return parse_config(data, source="aberrated")


def test_simulation_writes_the_aberration_it_used(tmp_path):
    config = _aberrated_config(field_curvature_waves=1.0, astigmatism_waves=0.5, nodes=3)
    path = tmp_path / "captures.h5"
    sim = simulate.run(config, path, provenance=Provenance.make("simulate", "", ""))
    with h5py.File(path, "r") as f:
        waves = np.asarray(f["/truth/aberration_waves"])
        assert f["/truth/aberration_waves"].attrs["units"] == "waves RMS"
        assert [tuple(m) for m in f["/truth/aberration_waves"].attrs["zernike_modes"]] == list(MODES)
        np.testing.assert_allclose(np.asarray(f["/truth/aberration_nodes_px"]), [0, 47.5, 95])
    np.testing.assert_allclose(waves[1, 1], 0, atol=0.002)                 # the centre sees no field aberration
    np.testing.assert_allclose(waves[0, 1, :3], [1.0, -0.5, 0.0], atol=0.03)  # h = (−1, 0): curvature and astig
    perfect = simulate.simulate(_aberrated_config(nodes=3))
    assert np.abs(sim.intensity - perfect.intensity).max() > 0.05 * perfect.intensity.max()


def test_aberration_keys_are_checked():
    with pytest.raises(Exception, match="nodes"):
        _aberrated_config(nodes=1)
    with pytest.raises(Exception, match="coma_waves"):
        _aberrated_config(coma_waves="lots")
    data = copy.deepcopy(FRAME_CONFIG)
    data.update(aberration={"field_curvature_waves": 1.0},
                multiplex={"cameras": 2, "patterns": 2})
    with pytest.raises((ConfigError, ValueError)):
        simulate.run(parse_config(data, source="x"), None, provenance=Provenance.make("simulate", "", ""))
