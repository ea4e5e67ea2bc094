"""The scripts in examples/ run, on small cases, and reach what they claim."""

from __future__ import annotations

import re
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
BLOODSMEAR = ROOT.parent / "shared" / "datasets" / "fpm-zheng-bloodsmear"


@pytest.fixture
def run_example(monkeypatch, capsys, tmp_path):
    """Run an example script as ``__main__`` in this interpreter (in ``tmp_path``) and return what it printed."""
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)

    def run(script: str, *args) -> str:
        monkeypatch.setattr(sys, "argv", [script, *map(str, args)])
        runpy.run_path(str(EXAMPLES / script), run_name="__main__")
        import matplotlib.pyplot as plt

        plt.close("all")
        return capsys.readouterr().out

    return run


def test_every_example_is_tested():
    tested = {"simulate_reconstruct_plot.py", "files_and_export.py", "led_array_bloodsmear.py"}
    assert {p.name for p in EXAMPLES.glob("*.py")} == tested


def test_simulate_reconstruct_plot_resolves_finer_bars(run_example, tmp_path):
    out = run_example("simulate_reconstruct_plot.py", "--small", "--out", tmp_path)
    observed, recovered = map(int, re.search(r"MTF20: observed (\d+) px, recovered (\d+) px", out).groups())
    assert recovered < observed
    assert (tmp_path / "observed_vs_recovered.png").stat().st_size > 10_000


def test_files_and_export_round_trip(run_example, tmp_path):
    out = run_example("files_and_export.py", "--out", tmp_path)
    assert "MTF20 2 px" in out
    import cca_cli as cca
    from cca_cli.io.export import read_exported

    recon = cca.load(tmp_path / "recon.h5")
    tiff = read_exported(tmp_path / "amplitude.tif")
    assert np.array_equal(tiff.values, recon.amplitude) and tiff.pixel_size_m == pytest.approx(recon.pixel_size_m)


@pytest.mark.skipif(not (BLOODSMEAR / "bloodsmear_green.mat").is_file(),
                    reason="needs ../shared/datasets/fpm-zheng-bloodsmear")
def test_led_array_bloodsmear_reconstructs_the_real_captures(run_example, tmp_path):
    out = run_example("led_array_bloodsmear.py", "--iterations", 3, "--out", tmp_path)
    assert "225 LEDs" in out and "373 px of 633 nm" in out   # the 128² frames on the guard band's 420² grid
    assert (tmp_path / "bloodsmear.png").is_file() and (tmp_path / "bloodsmear_amplitude.tif").is_file()
