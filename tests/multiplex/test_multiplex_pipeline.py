"""Multiplexed runs through the config, the stages and the CLI."""

import json

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.config.load import parse_config
from cca_cli.errors import ConfigError
from cca_cli.workflows.multiplex import multiplex_geometry
from cca_cli.units import FourierScale

#: 128-px chart 16 mm wide at 50 m, 25 mm apertures (pupil radius 7.3 spectrum px), 3 x 3 abutting cameras,
#: 3 x 3 sources at 66 % overlap.
MUX = {
    "run": {"stages": ["simulate", "reconstruct", "report"]},
    "optics": {"aperture_diameter_m": 25e-3},
    "scene": {"kind": "resolution_chart", "size_px": 128, "field_width_m": 16e-3, "widths_px": [6, 4, 3, 2, 1]},
    "noise": {"model": "gaussian", "snr_db": 30.0, "seed": 0},
    "reconstruct": {"iterations": 60, "tol": 0.0},
    "report": {"figures": True},
    "multiplex": {"camera_grid": [3, 3], "source_grid": [3, 3], "source_overlap": 0.66, "n_mux": 3, "patterns": 2},
}


def _config(**multiplex):
    data = json.loads(json.dumps(MUX))
    data["multiplex"].update(multiplex)
    return data


def test_geometry_follows_the_optics():
    mux, virtual, sensor = multiplex_geometry(parse_config(_config()))
    scale = FourierScale.fraunhofer(550e-9, 50.0, 16e-3)
    assert sensor == 128
    assert mux.pupil_radius_px == pytest.approx(scale.pupil_radius_px(25e-3))
    # abutting cameras: one aperture diameter apart; sources: (1 - 0.66) of a diameter
    assert np.diff(np.unique(mux.camera_centres_px[:, 1]))[0] == pytest.approx(2 * mux.pupil_radius_px)
    assert np.diff(np.unique(mux.source_shifts_px[:, 1]))[0] == pytest.approx(0.34 * 2 * mux.pupil_radius_px)
    assert mux.neighbour_overlap() == pytest.approx(0.66)
    assert virtual.n_images == 9 * 2 * 3 and mux.n_measurements == 18


def test_sources_by_position_match_the_overlap_they_make():
    # a 0.34-diameter spectrum shift at 50 m is a tilt of 0.34 * 25 mm / 50 m; sources 10 m away
    pitch = 0.34 * 25e-3 / 50.0 * 10.0
    by_pos = _config(source_overlap=None, source_pitch_m=pitch, source_distance_m=10.0)
    mux, _, _ = multiplex_geometry(parse_config(by_pos))
    assert mux.neighbour_overlap() == pytest.approx(0.66, abs=1e-9)


@pytest.mark.parametrize("multiplex, needle", [
    ({"source_overlap": 0.0}, "no overlap"),
    ({"n_mux": 10}, "larger than the 9 sources"),
    ({"pattern_list": [[0, 9]]}, "names source 9"),
])
def test_bad_multiplex_config_is_one_line(multiplex, needle):
    with pytest.raises(ConfigError, match=needle) as info:
        parse_config(_config(**multiplex), source="mux.yaml")
    assert "\n" not in str(info.value) and "multiplex" in str(info.value)


def test_sources_too_far_apart_fail_on_the_cli(tmp_path):
    # pitch equal to a whole aperture's shift: neighbouring regions only touch
    data = _config(source_overlap=None, source_pitch_m=25e-3 / 50.0 * 10.0, source_distance_m=10.0)
    path = tmp_path / "far.yaml"
    path.write_text(yaml.safe_dump(data))
    result = CliRunner().invoke(app, ["simulate", str(path), "-o", str(tmp_path / "c.h5"), "-q"])
    assert result.exit_code != 0
    lines = [line for line in result.output.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "no overlap" in lines[0], result.output
    assert not (tmp_path / "c.h5").exists()


@pytest.mark.parametrize("multiplex", [{"n_mux": 10}, {"pattern_list": [[0, 3], [12]]}])
def test_bad_patterns_fail_on_the_cli(tmp_path, multiplex):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(_config(**multiplex)))
    result = CliRunner().invoke(app, ["run", str(path), "--out-dir", str(tmp_path / "run"), "-q"])
    assert result.exit_code != 0
    assert len(result.output.strip().splitlines()) == 1, result.output


def test_multiplexed_run_reports_coverage_and_beats_the_centre_image(tmp_path):
    path = tmp_path / "mux.yaml"
    path.write_text(yaml.safe_dump(_config()))
    out = tmp_path / "run"
    result = CliRunner().invoke(app, ["run", str(path), "--out-dir", str(out), "-q"])
    assert result.exit_code == 0, result.output
    assert "spectrum holes" in result.output
    with h5py.File(out / "captures.h5", "r") as handle:
        assert handle["/measurements/intensity"].shape == (18, 128, 128)
        assert handle["/geometry/spectrum_centres_yx_px"].shape == (54, 2)
        assert handle["/multiplex/group_offsets"][-1] == 54
        assert "/observed/centre" in handle
    with h5py.File(out / "recon.h5", "r") as handle:
        assert "multiplex" in handle
    report = json.loads((out / "report" / "report.json").read_text())
    assert report["multiplex_measurements"] == 18
    assert 0.0 < report["coverage_zero_fraction"] < 0.5
    assert report["rmse_recovered"] < report["rmse_observed"]
    assert "coverage.png" in report["figures"]


def test_single_pattern_single_source_leaves_holes():
    from cca_cli.workflows.multiplex import coverage_summary

    one, _, _ = multiplex_geometry(parse_config(_config(n_mux=1, patterns=1)))
    many, _, _ = multiplex_geometry(parse_config(_config(n_mux=5, patterns=3)))
    stats_one, _, _ = coverage_summary(one, 128)
    stats_many, _, _ = coverage_summary(many, 128)
    assert stats_one["coverage_zero_fraction"] > 0.2
    assert stats_many["coverage_zero_fraction"] < stats_one["coverage_zero_fraction"] / 2


def test_multiplexed_simulation_of_a_usaf_chart_stores_its_elements(tmp_path):
    from cca_cli.workflows.multiplex import run_simulate

    data = _config(n_mux=1, patterns=1)
    data["scene"] = {"kind": "usaf", "size_px": 128, "field_width_m": 16e-3, "usaf_groups": [0, 1]}
    output = tmp_path / "captures.h5"
    run_simulate(parse_config(data), output, provenance={"stage": "simulate"})
    with h5py.File(output, "r") as handle:
        assert "multiplex" in handle and handle["truth/usaf"].shape[0] > 0


def test_dead_measurements_are_left_out_or_refused_as_dead_captures_are(tmp_path):
    """A measurement whose image holds one value is left out (weight 0) with one warning, up to 5% of them; more is
    one error line, and nothing is written."""
    config = _config(patterns=7)                       # 63 measurements: 3 may be left out
    config["run"]["stages"] = ["simulate"]
    config["reconstruct"]["iterations"] = 3
    path = tmp_path / "mux.yaml"
    path.write_text(yaml.safe_dump(config))
    result = CliRunner().invoke(app, ["run", str(path), "--out-dir", str(tmp_path), "-q"])
    assert result.exit_code == 0, result.output
    captures = tmp_path / "captures.h5"
    with h5py.File(captures, "r+") as handle:
        assert handle["/measurements/intensity"].shape[0] == 63
        handle["/measurements/intensity"][5] = 0.0
    recon = tmp_path / "recon.h5"
    result = CliRunner().invoke(app, ["reconstruct", str(captures), "-o", str(recon), "--config", str(path), "-q"])
    assert result.exit_code == 0, result.output
    assert "left out 1 of 63 measurements" in " ".join(result.output.split())
    with h5py.File(recon, "r") as handle:
        assert list(handle["recon"].attrs["dropped_captures"]) == [5]
    with h5py.File(captures, "r+") as handle:
        for i in (6, 7, 8):
            handle["/measurements/intensity"][i] = 2.0
    recon.unlink()
    result = CliRunner().invoke(app, ["reconstruct", str(captures), "-o", str(recon), "--config", str(path), "-q"])
    assert result.exit_code != 0 and not recon.exists()
    text = " ".join(result.output.split())
    assert "4 of 63 measurements of /measurements/intensity hold one value each" in text and "measurement 5" in text
