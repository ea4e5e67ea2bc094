"""cca design, baselines, speckle and the USAF/diffuse report additions."""

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.config.model import SceneSection
from cca_cli.metrics import contrast_table, mtf_limit, speckle_contrast
from cca_cli.optics.baselines import circ_otf, coherent_image, incoherent_otf
from cca_cli.optics.pupil import centred_disc
from cca_cli.sampling.design import plan_array
from cca_cli.sampling.overlap import synthetic_aperture_ratio
from cca_cli.workflows.scenes import build_scene, surface_phase, table_to_usaf, usaf_to_table
from cca_cli.targets import resolution_chart
from cca_cli.units import spot_size_m

LENS = dict(wavelength_m=550e-9, focal_length_m=1.2, aperture_diameter_m=0.075, pixel_pitch_m=4e-6)


@pytest.mark.parametrize("distance, expected", [(30, (536e-6, 134e-6, 187e-6)), (1000, (17.9e-3, 4.5e-3, 6.2e-3))])
def test_spot_sizes_match_paper(distance, expected):
    got = [spot_size_m(550e-9, distance, d) for d in (0.075, 0.300, 0.215)]
    for g, e in zip(got, expected):
        assert abs(g / e - 1) < 0.01 or abs(g - e) < 0.05e-3 * (distance / 1000)  # paper rounds 4.47 → 4.5 mm


def test_plan_reaches_paper_numbers():
    plan = plan_array(**LENS, distance_m=30, sar=4, field_width_m=0.0128)
    assert plan.grid == 9
    assert abs(plan.sar - 4.12) < 1e-9 and abs(plan.synthetic_aperture_m - 0.309) < 1e-6
    assert abs(plan.spot_lens_m / 536e-6 - 1) < 0.01
    beat = plan_array(**LENS, distance_m=30, beat_lens_m=0.215, field_width_m=0.0128)
    assert beat.sar >= 0.215 / 0.075 and beat.spot_synthetic_m < beat.spot_beat_m
    for grid, sar in ((23, 7.16), (5, 2.12), (13, 4.36), (17, 5.48)):
        assert abs(synthetic_aperture_ratio(grid, 0.72) / sar - 1) < 0.01


def test_plan_warns_below_half_overlap_and_off_sensor():
    low = plan_array(**LENS, distance_m=30, sar=3, overlap=0.4, field_width_m=0.0128)
    assert any("50%" in w for w in low.warnings)
    ok = plan_array(**LENS, distance_m=30, sar=3, overlap=0.6, field_width_m=0.0128)
    assert not ok.warnings
    big = plan_array(**LENS, distance_m=30, sar=3, field_width_m=0.0128, sensor_px=64)
    assert not big.fits_sensor and big.warnings


def test_incoherent_otf_matches_closed_form():
    for size, radius in ((128, 12.3), (96, 20.0)):
        otf = incoherent_otf(centred_disc(size, radius))
        assert otf[size // 2, size // 2] == pytest.approx(1.0)
        assert np.max(np.abs(otf - circ_otf(size, radius))) < 0.015


def test_big_lens_resolves_finer_bars():
    chart = resolution_chart(256, widths=(12, 10, 8, 6, 5, 4, 3, 2))
    field = np.asarray(chart.image, np.complex64)
    small = mtf_limit(contrast_table(coherent_image(field, 14.0), chart))
    big = mtf_limit(contrast_table(coherent_image(field, 45.0), chart))
    assert big is not None and small is not None and big < small


def test_speckle_contrast():
    field = np.exp(1j * surface_phase(256, roughness_rad=4.0, seed=3))
    speckle = coherent_image(field.astype(np.complex64), 20.0)
    assert speckle_contrast(speckle) == pytest.approx(1.0, abs=0.1)
    assert speckle_contrast(np.ones((8, 8))) == 0.0
    with pytest.raises(ValueError):
        speckle_contrast(np.ones((8, 8)), (4, 4, 0, 8))


def test_usaf_table_round_trip():
    scene = build_scene(SceneSection(kind="usaf", size_px=256, field_width_m=0.01, usaf_groups=[0, 1, 2]), 128)
    chart = table_to_usaf(usaf_to_table(scene.usaf, scene.usaf_size))
    assert chart.size == 256 and len(chart.elements) == len(scene.usaf)
    assert chart.elements[0].horizontal == scene.usaf[0].horizontal


def test_design_cli_json_and_write_config_runs(tmp_path):
    runner = CliRunner()
    cfg = tmp_path / "plan.yaml"
    args = ["design", "--wavelength-m", "550e-9", "--focal-length-m", "0.8", "--aperture-m", "0.018",
            "--pixel-pitch-m", "4e-6", "--distance-m", "50", "--sar", "2", "--overlap", "0.6",
            "--field-width-m", "0.0256", "--iterations", "20", "--no-measure", "--json", "--write-config", str(cfg)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout[: result.stdout.rindex("}") + 1])
    assert data["grid"] == 5 and data["sar"] == pytest.approx(2.6)
    config = yaml.safe_load(cfg.read_text())
    assert config["array"]["grid"] == data["grid"]
    out = tmp_path / "run"
    result = runner.invoke(app, ["run", str(cfg), "--out-dir", str(out), "-q"])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "report" / "report.json").read_text())
    assert "passive_incoherent" in report["baselines"] and report["mtf20_recovered_px"] is not None
    assert (out / "report" / "comparison.png").exists()
    again = runner.invoke(app, args)
    assert again.exit_code != 0 and "exists" in again.output


def test_design_cli_warns_low_overlap():
    result = CliRunner().invoke(app, ["design", "--sar", "3", "--overlap", "0.3", "--no-measure"])
    assert result.exit_code == 0 and "50%" in result.output
