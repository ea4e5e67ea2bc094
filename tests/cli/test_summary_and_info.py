"""What the terminal shows: derived quantities (`cca simulate`, `cca info`), the report summary, the stop note."""

from __future__ import annotations

import json

import pytest
from rich.console import Console
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.commands.console import summary_table


def _text(result) -> str:
    return " ".join(result.output.split())


@pytest.fixture(scope="module")
def files(tmp_path_factory, tiny_run_config):
    """captures.h5 and recon.h5 of the tiny config, reconstructed with tol 0 (the cap ends the run)."""
    from cca_cli.config.load import dump_config

    out = tmp_path_factory.mktemp("summary")
    config = out / "tiny.yaml"
    config.write_text(dump_config(tiny_run_config))
    runner = CliRunner()
    simulate = runner.invoke(app, ["simulate", str(config), "-o", str(out / "captures.h5"), "-q"])
    assert simulate.exit_code == 0, simulate.output
    reconstruct = runner.invoke(app, ["reconstruct", str(out / "captures.h5"), "-o", str(out / "recon.h5"),
                                      "--iterations", "3", "--tol", "0", "-q"])
    assert reconstruct.exit_code == 0, reconstruct.output
    return out, simulate, reconstruct


def test_simulate_prints_the_derived_quantities(files):
    text = _text(files[1])
    for needle in ("25 captures of 96² px", "images 25 (5 x 5 grid)", "SAR 2.56", "step 17.6 mm, overlap 61%",
                   "pupil radius 9.82 spectrum px", "spot at sensor 23.9 µm", "spot at object 1.49 mm",
                   "output grid 96 x 96 px of 125 µm"):
        assert needle in text, (needle, text)


@pytest.mark.parametrize("name", ["captures.h5", "recon.h5"])
def test_info_prints_the_derived_quantities(files, name):
    result = CliRunner().invoke(app, ["info", str(files[0] / name)])
    assert result.exit_code == 0, result.output
    text = _text(result)
    for needle in ("derived quantities:", "images 25 (5 x 5 grid)", "SAR 2.56", "pupil radius 9.82 spectrum px",
                   "spot at object 1.49 mm", "output grid 96 x 96 px of 125 µm"):
        assert needle in text, (needle, text)


def test_the_iteration_cap_is_reported_in_terminal_file_and_report(files):
    out, _, reconstruct = files
    assert "note: reconstruct stopped at the iteration cap (3) before the change reached tol" in _text(reconstruct)
    import h5py

    with h5py.File(out / "recon.h5") as handle:
        assert handle["recon"].attrs["stopped_by"] == "cap"
    from cca_cli.config.model import ReportSection
    from cca_cli.io.h5 import Provenance
    from cca_cli.stages import report

    report.run(out / "recon.h5", ReportSection(figures=False), out / "report",
               provenance=Provenance.make("report", "", ""))
    summary = json.loads((out / "report" / "report.json").read_text())
    assert summary["stopped_by"] == "cap" and summary["tol"] == 0.0 and summary["final_change"] > 0
    console = Console(record=True, width=200)
    console.print(summary_table(summary))
    assert "stopped by │ iteration cap (before tol)" in " ".join(console.export_text().split())


def test_a_run_that_meets_tol_says_so(files, tmp_path):
    out = files[0]
    result = CliRunner().invoke(app, ["reconstruct", str(out / "captures.h5"), "-o", str(tmp_path / "r.h5"),
                                      "--iterations", "50", "--tol", "0.5", "-q"])
    assert result.exit_code == 0 and "note:" not in result.output
    import h5py

    with h5py.File(tmp_path / "r.h5") as handle:
        assert handle["recon"].attrs["stopped_by"] == "tol" and handle["recon"].attrs["iterations"] < 50


def test_summary_table_shows_usaf_baselines_and_speckle():
    summary = {
        "sar": 7.16, "n_images": 529, "engine": "altmin", "iterations": 200, "stopped_by": "tol",
        "spot_size_object_m": 9.27e-4, "kind": "camera_scan",
        "usaf": {"observed": {"group": 0, "element": 3, "lp_per_mm": 1.26}, "recovered":
                 {"group": 3, "element": 1, "lp_per_mm": 8.0}, "lens_215mm": {"group": None, "element": None,
                                                                            "lp_per_mm": None},
                 "gain": 6.35, "elements": []},
        "baselines": {"passive_incoherent": {"rmse": 0.1663, "mtf20_px": 12, "spot_size_object_m": 9.27e-4}},
        "speckle_contrast_observed": 0.91, "speckle_contrast_recovered": 0.42,
        "speckle_contrast_baselines": {"passive_incoherent": 0.33},
    }
    console = Console(record=True, width=200)
    console.print(summary_table(summary))
    text = " ".join(console.export_text().split())
    for needle in ("USAF observed │ G0 E3 (1.26 lp/mm)", "USAF recovered │ G3 E1 (8 lp/mm)",
                   "USAF lens 215mm │ none resolved", "USAF gain (recovered / observed lp/mm) │ 6.35",
                   "baseline passive incoherent │ MTF20 12 px, RMSE 0.1663, spot 927 µm",
                   "speckle contrast observed │ 0.910", "speckle contrast recovered │ 0.420",
                   "speckle contrast passive incoherent │ 0.330", "stopped by │ tol",
                   "spot size at object │ 927 µm"):
        assert needle in text, (needle, text)


def test_a_run_that_also_stops_on_a_plateau_is_told_so_at_the_cap():
    """The recorded-data presets stop on a misfit plateau; their cap note speaks of it, not of a tol never set."""
    from cca_cli.commands.console import stop_note

    note = stop_note("cap", 150, 0.00143, 1e-7, 0.02, 5)
    assert note == ("reconstruct stopped at the iteration cap (150) before its misfit plateau (less than 2% better "
                    "over 5 iterations) was reached; raise reconstruct.iterations (--iterations) to go on")
    assert "tol" in stop_note("cap", 150, 0.00143, 1e-7) and stop_note("plateau", 40, 0.01, 1e-7, 0.02, 5) is None


def test_a_tiled_run_s_cap_note_counts_the_tiles_the_cap_stopped():
    from types import SimpleNamespace

    from cca_cli.commands.console import recovery_stop_note

    tiles = [SimpleNamespace(stopped_by=reason) for reason in ("plateau", "cap", "plateau", "cap", "plateau")]
    history = SimpleNamespace(iterations=150, records=[SimpleNamespace(change=0.002)])   # the longest tile's
    recovery = SimpleNamespace(results=tiles, stopped_by="cap", history=history,
                               options={"tol": 1e-7, "plateau": 0.02, "plateau_window": 5})
    assert recovery_stop_note(recovery) == (
        "2 of 5 tiles stopped at the iteration cap (150) before their misfit plateau (less than 2% better over 5 "
        "iterations) was reached; raise reconstruct.iterations (--iterations) to go on")


def test_lengths_read_in_one_unit_down_to_below_a_nanometre():
    from cca_cli.commands.console import length_text

    assert [length_text(v) for v in (2e-3, 1.25e-7, 1.42e-10, 0.0)] == ["2 mm", "125 nm", "0.142 nm", "0 m"]
    assert length_text(float("nan")) == "nan"
