"""Where reconstructions run: reconstruct.device, --device, device=, and what records it.

Without a GPU the ``cuda`` path is exercised with numpy standing in for CuPy (the batched engines take
any array module): the choice, the wiring and the records are what is tested here; the numbers of the
batched engines are tests/engines/test_batched.py's.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app
from cca_cli.config.load import parse_config
from cca_cli.config.model import ReconstructSection
from cca_cli.engines.options import AltMinOptions, MomentumOptions
from cca_cli.errors import ConfigError
from cca_cli.library import recovery
from cca_cli.optics import backend
from cca_cli.optics.backend import DeviceStatus, DeviceUnavailable, resolve_device
from cca_cli.stages.runner import config_hash

NO_GPU = DeviceStatus(False, "cpu only: CuPy not installed")
FAKE_GPU = DeviceStatus(True, "CuPy 0.0 (numpy standing in), GPU 0: none")


@pytest.fixture
def no_gpu(monkeypatch):
    """This machine as one without CuPy, whatever it has."""
    monkeypatch.setattr(backend, "device_status", lambda: NO_GPU)


@pytest.fixture
def numpy_gpu(monkeypatch):
    """A 'GPU' whose array module is numpy: the cuda path runs the batched engines on the CPU."""
    monkeypatch.setattr(backend, "device_status", lambda: FAKE_GPU)
    monkeypatch.setattr(backend, "array_module", lambda device: np)


def _geometry_and_images(grid=3):
    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3, grid=grid, overlap=0.61)
    chart = cca.resolution_chart(64, widths=(4, 3, 2))
    return g, cca.simulate(chart.image, g, snr_db=40), chart


# ----------------------------------------------------------------------------- choosing the device
def test_cpu_is_cpu_and_auto_is_cpu_without_a_gpu(no_gpu):
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == "cpu"
    with pytest.raises(ValueError, match="device must be one of auto, cpu, cuda"):
        resolve_device("gpu")


def test_cuda_without_cupy_is_one_line_with_the_fix(no_gpu):
    with pytest.raises(DeviceUnavailable) as caught:
        resolve_device("cuda")
    message = str(caught.value)
    assert "\n" not in message and "CuPy not installed" in message
    assert "pip install 'cca[gpu]'" in message and "device cpu" in message


def test_auto_takes_the_gpu_only_for_options_it_runs(numpy_gpu):
    assert resolve_device("auto") == "cuda"
    assert recovery.engine_device("auto", "altmin", AltMinOptions()) == "cuda"
    calibrating = MomentumOptions(position_refinement="both")
    assert recovery.engine_device("auto", "momentum", calibrating) == "cpu"
    with pytest.raises(DeviceUnavailable, match="position_refinement: both"):
        recovery.engine_device("cuda", "momentum", calibrating)


def test_the_status_says_why_there_is_no_gpu_here():
    status = backend.device_status()
    assert isinstance(status.summary, str) and status.summary
    if backend.cupy_module() is None:
        assert not status.cuda and status.summary == "cpu only: CuPy not installed"


def test_the_backend_moves_and_transforms_numpy_arrays():
    rng = np.random.default_rng(1)
    fields = (rng.normal(size=(3, 8, 8)) + 1j * rng.normal(size=(3, 8, 8))).astype(np.complex64)
    assert backend.get_array_module(fields) is np and backend.to_host(fields) is fields
    forward = backend.fft2(np, fields.copy())
    assert forward.dtype == np.complex64
    np.testing.assert_allclose(forward, np.fft.fft2(fields), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(backend.ifft2(np, forward.copy()), fields * 64, rtol=1e-4, atol=1e-3)
    target = np.zeros(5, np.complex64)
    backend.scatter_add(np, target, np.array([[0, 1], [1, 4]]), np.array([[1, 2j], [3, 4]], np.complex64))
    np.testing.assert_array_equal(target, [1, 3 + 2j, 0, 0, 4])


# ----------------------------------------------------------------------------- config, API, CLI
def test_the_config_takes_a_device_and_keeps_it_out_of_the_recipe(tiny_config_data):
    assert ReconstructSection().device == "cpu"
    assert ReconstructSection(device="auto").device == "auto"
    tiny_config_data["reconstruct"]["device"] = "gpu"
    with pytest.raises(ConfigError, match="reconstruct.device"):
        parse_config(tiny_config_data, source="tiny")
    sections = [{"reconstruct": ReconstructSection(device=device)} for device in ("cpu", "cuda")]
    assert config_hash(sections[0]) == config_hash(sections[1])


def test_the_api_runs_auto_on_the_cpu_bit_for_bit(no_gpu):
    g, images, _ = _geometry_and_images()
    cpu = cca.reconstruct(images, g, engine="altmin", iterations=5, tol=0)
    auto = cca.reconstruct(images, g, engine="altmin", iterations=5, tol=0, device="auto")
    assert cpu.device == auto.device == "cpu"
    np.testing.assert_array_equal(cpu.spectrum, auto.spectrum)
    with pytest.raises(ValueError, match=r"device cuda needs CuPy .*pip install 'cca\[gpu\]'"):
        cca.reconstruct(images, g, engine="altmin", iterations=5, device="cuda")


@pytest.mark.parametrize("engine", ["altmin", "momentum"])
def test_the_api_runs_the_batched_engines_on_device_cuda(numpy_gpu, engine):
    g, images, chart = _geometry_and_images(grid=5)
    cpu = cca.reconstruct(images, g, engine=engine, iterations=8, tol=0, threads=1)   # momentum: its camera-scan
    gpu = cca.reconstruct(images, g, engine=engine, iterations=8, tol=0, device="cuda")   # preset (Zernike pupil)
    assert cpu.device == "cpu" and gpu.device == "cuda"
    assert gpu.iterations == 8 and gpu.stopped_by == cpu.stopped_by == "cap"
    if engine == "altmin":
        np.testing.assert_allclose(gpu.spectrum, cpu.spectrum, atol=1e-5 * np.abs(cpu.spectrum).max())
    assert cca.rmse(gpu.intensity, np.abs(chart.image) ** 2) < 1.1 * cca.rmse(cpu.intensity, np.abs(chart.image) ** 2)


def test_the_api_names_options_the_gpu_does_not_run(numpy_gpu):
    g, images, _ = _geometry_and_images()
    with pytest.raises(ValueError, match="brightness: true .*device cpu"):
        cca.reconstruct(images, g, engine="momentum", brightness=True, device="cuda")


def _error_line(result) -> str:
    assert result.exit_code != 0, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    return lines[0]


@pytest.fixture
def captures(write_config, tiny_config_data, tmp_path):
    path = tmp_path / "captures.h5"
    tiny_config_data["report"]["figures"] = False
    result = CliRunner().invoke(app, ["simulate", str(write_config(tiny_config_data)), "-o", str(path), "-q"])
    assert result.exit_code == 0, result.output
    return path


def test_cli_device_cuda_without_cupy_is_one_line(no_gpu, captures, tmp_path):
    result = CliRunner().invoke(app, ["reconstruct", str(captures), "-o", str(tmp_path / "r.h5"), "--device", "cuda",
                                      "-q"])
    line = _error_line(result)
    assert "reconstruct.device" in line and "pip install 'cca[gpu]'" in line and "device cpu" in line
    assert not (tmp_path / "r.h5").exists()
    result = CliRunner().invoke(app, ["reconstruct", str(captures), "-o", str(tmp_path / "r.h5"), "--device", "tpu"])
    assert "--device" in _error_line(result)


def test_cli_records_the_device_in_recon_h5_and_report_json(numpy_gpu, captures, tmp_path):
    runner = CliRunner()
    for device in ("cpu", "cuda"):
        recon, report = tmp_path / f"{device}.h5", tmp_path / f"report-{device}"
        result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(recon), "--iterations", "3",
                                     "--device", device, "-q"])
        assert result.exit_code == 0, result.output
        assert ("on the GPU" in result.stdout) == (device == "cuda")
        with h5py.File(recon, "r") as handle:
            assert handle["recon"].attrs["device"] == device
        result = runner.invoke(app, ["report", str(recon), "-o", str(report)])
        assert result.exit_code == 0, result.output
        assert json.loads((report / "report.json").read_text())["device"] == device


def test_cca_run_refuses_cuda_before_anything_runs(no_gpu, write_config, tmp_path):
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["run", str(write_config()), "--out-dir", str(out), "--device", "cuda", "-q"])
    assert "reconstruct.device" in _error_line(result)
    assert not (out / "captures.h5").exists()


def test_cca_info_without_a_file_lists_the_devices(no_gpu):
    result = CliRunner().invoke(app, ["info"])
    assert result.exit_code == 0, result.output
    assert "devices" in result.stdout and "cpu only: CuPy not installed" in result.stdout
