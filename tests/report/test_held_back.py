"""A run that holds captures back records their misfit in recon.h5, and the report shows it."""

import json

import h5py
import numpy as np
from typer.testing import CliRunner

from cca_cli.commands.app import app


def test_held_back_misfit_reaches_recon_h5_and_the_report(tmp_path, write_config, tiny_config_data):
    tiny_config_data["reconstruct"] = {"engine": "momentum", "iterations": 40, "tol": 0.0,
                                       "options": {"hold_back": 0.1, "hold_back_patience": 5}}
    config = write_config(tiny_config_data)
    runner = CliRunner()
    result = runner.invoke(app, ["run", str(config), "--out-dir", str(tmp_path / "out"), "-q"])
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "out" / "recon.h5", "r") as handle:
        held = np.asarray(handle["/history/held_back"])
        captures = np.asarray(handle["/recon/held_back_captures"])
        assert held.shape == handle["/history/residual"].shape and np.isfinite(held).all()
        assert captures.size == 2 and handle["/history/held_back"].attrs["units"] == "1"
        assert handle["recon"].attrs["residual_held_back"] == held.min()
    report = json.loads((tmp_path / "out" / "report" / "report.json").read_text())
    assert report["held_back_captures"] == 2 and report["residual_held_back"] == round(float(held.min()), 5)
    assert report["held_back_best_iteration"] == int(np.argmin(held)) + 1
