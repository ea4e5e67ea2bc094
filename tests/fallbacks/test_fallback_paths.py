"""A focused pass over the paths the fallbacks change: FFTs, kernels, both engines, one small run.

The suite runs this module as it is and, through ``test_fallback_runs.py``, again in
child processes as it runs without pyfftw, without numba, and where FFTW's library
cannot be found (not Linux). It checks first that the switch took effect.
"""

import os
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions
from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.optics import fft, kernels
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import band_layout, square_scan
from cca_cli.targets import resolution_chart

RNG = np.random.default_rng(7)


def _switch(name: str) -> str:
    return os.environ.get(name, "").strip().lower()


def test_the_switches_select_the_fallbacks():
    if _switch("CCA_FFT_BACKEND") == "scipy":
        assert fft.backend_name() == "scipy" and "pyfftw" not in sys.modules
        assert not fft.raw_fftw_available()
    if _switch("CCA_KERNELS") == "numpy":
        assert kernels.kernels_name() == "numpy" and "numba" not in sys.modules
    if _switch("CCA_RAW_FFTW") == "off":
        assert not fft.raw_fftw_available()
        assert fft.BandedFFT2(fft.zeros((2, 8, 8)), 2, 6, threads=1).raw_plans() is None


def test_in_place_transforms_match_numpy():
    data = np.zeros((3, 24, 24), np.complex64)
    data[:, 6:18] = RNG.standard_normal((3, 12, 24))
    full = fft.InPlaceFFT2(fft.zeros((3, 24, 24)), threads=1)
    full.buffer[...] = data
    np.testing.assert_allclose(full.forward(), np.fft.fft2(data), atol=1e-3)
    banded = fft.BandedFFT2(fft.zeros((3, 24, 24)), 6, 18, threads=1)
    banded.buffer[...] = data
    np.testing.assert_allclose(banded.inverse(2)[:2], np.fft.ifft2(data[:2]) * 576, atol=1e-3)


@pytest.fixture(scope="module")
def problem():
    size, radius = 64, 6.0
    scan = square_scan(5, 2 * radius * (1 - 0.61))
    layout = band_layout(scan.centres_yx_m, radius, sensor_size=size)
    model = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, radius))
    chart = resolution_chart(size, widths=(4, 3, 2)).image.astype(np.complex64)
    images = model.sensor_intensity(fft.fft2c(chart).astype(np.complex64))
    return PhaseRetrievalProblem.from_sensor_images(model, images)


def test_forward_model_passes_the_dot_product_test(problem):
    model = problem.model
    x = (RNG.standard_normal(model.spectrum_shape) + 1j * RNG.standard_normal(model.spectrum_shape))
    y = RNG.standard_normal((model.n_images,) + model.field_shape).astype(np.complex64)
    lhs = np.vdot(model.forward(x.astype(np.complex64)).astype(np.complex128), y)
    rhs = np.vdot(x, model.adjoint(y).astype(np.complex128))
    assert abs(lhs - rhs) <= 1e-4 * abs(lhs)


@pytest.mark.parametrize("engine", ["altmin", "momentum"])
def test_engines_fit_the_data(problem, engine):
    if engine == "altmin":
        solver = AlternatingMinimization(problem, AltMinOptions(max_iterations=20, tol=0, threads=2))
    else:
        solver = SequentialMomentum(problem, MomentumOptions(max_iterations=8, tol=0, batch=3, threads=2))
        fused = solver.passes.fused
        assert fused == (kernels.kernels_name() == "numba" and fft.raw_fftw_available())
    residuals = [solver.update()[0] for _ in range(solver.options.max_iterations)]
    solver.close()
    assert residuals[-1] < 0.3 * residuals[0]


def test_a_small_run_from_the_command_line(tmp_path, write_config, tiny_config_data):
    tiny_config_data["run"]["out_dir"] = str(tmp_path / "run")
    tiny_config_data["reconstruct"].update(engine="momentum", iterations=5)
    tiny_config_data["report"]["figures"] = False
    result = CliRunner().invoke(app, ["run", str(write_config(tiny_config_data))])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "run" / "report" / "report.json").is_file()
