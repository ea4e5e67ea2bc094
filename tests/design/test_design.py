"""cca design, baselines, speckle and the USAF/diffuse report additions."""

import json
import math
import re

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.config.model import SceneSection
from cca_cli.metrics import contrast_table, mtf_limit, speckle_contrast
from cca_cli.optics.baselines import circ_otf, coherent_image, incoherent_otf
from cca_cli.optics.pupil import centred_disc
from cca_cli.sampling.design import iteration_seconds, plan_array
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


def _design_json(runner, args):
    result = runner.invoke(app, ["design", *args, "--json"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout[: result.stdout.rindex("}") + 1])


#: Small designs (λ 550 nm, f 0.8 m, d 18 mm, z 50 m): 5 x 5 captures with a 36-px band grid, 9 x 9 with an
#: 84-px one (pupil radius 20 px), 13 x 13 with a 64-px one.
SMALL_DESIGNS = {
    "5x5": ["--pixel-pitch-m", "4e-6", "--sar", "2", "--overlap", "0.6", "--field-width-m", "0.0256"],
    "9x9": ["--pixel-pitch-m", "9.8e-6", "--sar", "4", "--field-width-m", "0.0611"],
    "13x13": ["--pixel-pitch-m", "9.8e-6", "--sar", "5.5", "--field-width-m", "0.0458"],
}


@pytest.mark.parametrize("design", ["5x5", "13x13"])
def test_written_config_resolves_the_bars_the_design_predicts(tmp_path, design):
    runner = CliRunner()
    cfg = tmp_path / "plan.yaml"
    args = [*SMALL_DESIGNS[design], "--no-measure", "--write-config", str(cfg)]
    plan = _design_json(runner, args)
    config = yaml.safe_load(cfg.read_text())
    assert config["array"]["grid"] == plan["grid"] and config["reconstruct"]["engine"] == "momentum"
    predicted = plan["spot_synthetic_px"]
    assert predicted == pytest.approx(plan["spot_synthetic_m"] / plan["output_pixel_m"])
    # The chart has bars as wide as the predicted spot, and finer ones.
    widths = config["scene"]["widths_px"]
    assert math.floor(predicted) in widths and min(widths) <= predicted / 2
    out = tmp_path / "run"
    result = runner.invoke(app, ["run", str(cfg), "--out-dir", str(out), "-q"])
    assert result.exit_code == 0, result.output
    report = json.loads((out / "report" / "report.json").read_text())
    # It stops on its own (the misfit's plateau), well before the cap.
    assert report["engine"] == "momentum" and report["stopped_by"] == "plateau"
    assert report["iterations"] < config["reconstruct"]["iterations"] / 2
    assert report["mtf20_recovered_px"] is not None and report["mtf20_recovered_px"] <= predicted
    assert report["mtf20_observed_px"] is None or report["mtf20_observed_px"] > report["mtf20_recovered_px"]
    assert "passive_incoherent" in report["baselines"]
    assert (out / "report" / "comparison.png").exists()
    again = runner.invoke(app, ["design", *args])
    assert again.exit_code != 0 and "exists" in again.output


def test_design_writes_the_engine_asked_for(tmp_path):
    runner = CliRunner()
    cfg = tmp_path / "plan.yaml"
    args = [*SMALL_DESIGNS["5x5"], "--no-measure", "--engine", "altmin", "--write-config", str(cfg)]
    plan = _design_json(runner, args)
    assert plan["engine"] == "altmin"
    config = yaml.safe_load(cfg.read_text())
    assert config["reconstruct"] == {"engine": "altmin", "tau": 1e-3, "iterations": 1000, "tol": 1e-5}
    # lengths as a person would type them (0.032, not 0.031999999999999994), equal to the plan's to 1e-12
    assert not re.search(r"\d\.\d{13,}", cfg.read_text())
    assert config["scene"]["field_width_m"] == pytest.approx(plan["field_width_m"], rel=1e-11)
    assert config["report"]["baselines"][1]["aperture_diameter_m"] == pytest.approx(plan["synthetic_aperture_m"],
                                                                                     rel=1e-11)
    result = runner.invoke(app, ["design", "--sar", "3", "--no-measure", "--engine", "pie"])
    assert result.exit_code == 2 and "--engine" in result.output


def _simulated(plan):
    import cca_cli as cca

    geometry = cca.camera_scan(wavelength_m=plan["wavelength_m"], focal_length_m=plan["focal_length_m"],
                               aperture_diameter_m=plan["aperture_diameter_m"], pixel_pitch_m=plan["pixel_pitch_m"],
                               distance_m=plan["distance_m"], field_width_m=plan["field_width_m"], grid=plan["grid"],
                               overlap=plan["overlap"])
    chart = resolution_chart(plan["output_px"], widths=(6, 4, 3, 2, 1))
    return cca.CaptureSet(intensity=cca.simulate(chart.image, geometry, snr_db=30), geometry=geometry,
                          truth={"object": chart.image})


def _seconds_per_iteration(captures, engine, iterations=10):
    """Median time of a real run's iterations (the first two, which plan and warm up, left out)."""
    import cca_cli as cca

    result = cca.reconstruct(captures, engine=engine, iterations=iterations, tol=0)
    return float(np.median(np.diff(result.history["seconds"])[1:]))


@pytest.mark.parametrize("design", ["9x9", "13x13"])
def test_time_estimate_is_within_twice_a_measured_run(design):
    runner = CliRunner()
    captures = _simulated(_design_json(runner, [*SMALL_DESIGNS[design], "--no-measure"]))
    for engine in ("momentum", "altmin"):
        # Shared machines: an estimate and a run in turn, five times, so that bursts of other work that
        # slow one or the other skew two ratios at most.
        ratios = []
        for _ in range(5):
            plan = _design_json(runner, [*SMALL_DESIGNS[design], "--engine", engine])
            assert plan["engine"] == engine and plan["threads"] >= 1
            ratios.append(plan["seconds_per_iteration"] / _seconds_per_iteration(captures, engine))
        assert 0.5 <= np.median(ratios) <= 2, (engine, ratios)


def test_time_estimate_counts_every_capture_and_spectrum_pixel():
    plan = plan_array(**LENS, distance_m=30, sar=4, field_width_m=0.0128)
    seconds = iteration_seconds(plan, capture_seconds=1e-4, pixel_seconds=1e-9)
    assert seconds == pytest.approx(plan.n_images * 1e-4 + plan.output_px ** 2 * 1e-9)
    assert plan.fft_count_per_iteration == 2 * plan.n_images
    huge = plan_array(**LENS, distance_m=30, sar=1e300, field_width_m=0.0128)
    assert iteration_seconds(huge, capture_seconds=1e-4, pixel_seconds=1e-9) == float("inf")


def test_design_cli_warns_low_overlap():
    result = CliRunner().invoke(app, ["design", "--sar", "3", "--overlap", "0.3", "--no-measure"])
    assert result.exit_code == 0 and "50%" in result.output
