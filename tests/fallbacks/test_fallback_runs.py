"""The fallbacks run in the normal suite: the focused tests pass without pyfftw, without numba and
without FFTW's library (as off Linux), each in a child process with the switch set."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # subprocesses, each a run of seconds: the whole suite only

FOCUSED = [Path(__file__).with_name("test_fallback_paths.py"), Path(__file__).parents[1] / "engines" / "test_golden.py"]
FALLBACKS = {
    "no pyfftw": {"CCA_FFT_BACKEND": "scipy"},
    "no numba": {"CCA_KERNELS": "numpy"},
    "no FFTW library": {"CCA_RAW_FFTW": "off"},
}
#: Switches read when the package is imported (CCA_RAW_FFTW and CCA_FFTW_PLANNING are read later, and
#: checked in-process by test_planning.py and below).
BAD_SWITCHES = {"CCA_FFT_BACKEND": "fftw", "CCA_KERNELS": "cuda"}
CONFIG = """\
run: {stages: [simulate]}
optics: {aperture_diameter_m: 45e-3}
scene: {kind: resolution_chart, size_px: 96, field_width_m: 12e-3, widths_px: [6, 4, 3, 2, 1]}
array: {grid: 5, overlap: 0.61}
"""


@pytest.fixture(scope="module")
def children(tmp_path_factory):
    """Every child started at once (they mostly wait on imports), then collected."""
    root = Path(__file__).resolve().parents[2]
    config = tmp_path_factory.mktemp("switch") / "tiny.yaml"
    config.write_text(CONFIG)
    started = {}
    for name, switch in FALLBACKS.items():
        env = dict(os.environ, **switch)
        started[name] = subprocess.Popen([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-o", "addopts=", "-q",
                                          *map(str, FOCUSED)],
                                         cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for name, value in BAD_SWITCHES.items():
        env = dict(os.environ, **{name: value})
        out = tmp_path_factory.mktemp("out") / "captures.h5"
        started[name] = subprocess.Popen([sys.executable, "-m", "cca_cli", "simulate", str(config), "-o", str(out)],
                                         cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    results = {}
    for name, child in started.items():
        stdout, stderr = child.communicate(timeout=600)
        results[name] = (child.returncode, stdout, stderr)
    return results


@pytest.mark.parametrize("fallback", list(FALLBACKS))
def test_focused_tests_pass_under_the_fallback(children, fallback):
    returncode, output, _ = children[fallback]
    assert returncode == 0, output[-4000:]
    assert " passed" in output and "skipped" not in output, output[-4000:]


@pytest.mark.parametrize("variable", list(BAD_SWITCHES))
def test_an_unknown_switch_value_is_one_line_naming_the_variable(children, variable):
    returncode, _, stderr = children[variable]
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert returncode == 2 and len(lines) == 1, stderr
    assert lines[0].startswith(f"error: environment variable {variable}={BAD_SWITCHES[variable]!r} is not one of")


def test_an_unknown_raw_fftw_switch_is_one_line(write_config, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from cca_cli.commands.app import app

    monkeypatch.setenv("CCA_RAW_FFTW", "maybe")
    result = CliRunner().invoke(app, ["simulate", str(write_config()), "-o", str(tmp_path / "c.h5"), "--quiet"])
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.exit_code == 2 and lines == ["error: environment variable CCA_RAW_FFTW='maybe' is not one of on, "
                                               "off; unset it or pick one"]
