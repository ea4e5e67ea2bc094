"""The staged pipeline on a tiny config: outputs, report keys, provenance, resume and force."""

import json
import shutil

from pathlib import Path

import h5py
import numpy as np
import pytest

from cca_cli.config.load import apply_overrides
from cca_cli.config.model import ReconstructSection
from cca_cli.errors import OutputExistsError
from cca_cli.io.schema import SCHEMA_VERSION
from cca_cli.stages import reconstruct as reconstruct_stage
from cca_cli.stages import simulate as simulate_stage
from cca_cli.stages.runner import config_hash, pick_sections, plan_stages, run_pipeline
from cca_cli.units import spot_size_m
from cca_cli.library.data import CaptureSet
from cca_cli.workflows.recovery import reconstruct_captures

REPORT_KEYS = {
    "sar", "grid", "overlap", "n_images", "engine", "iterations", "seconds", "mtf20_observed_px",
    "mtf20_recovered_px", "resolution_gain", "rmse_observed", "rmse_recovered", "spot_size_sensor_m",
    "spot_size_object_m", "contrast_observed", "contrast_recovered",
}
PROVENANCE_KEYS = {"cca_schema", "stage", "cca_version", "created_utc", "config", "config_hash", "inputs"}


@pytest.fixture(scope="module")
def finished_run(tiny_run_config, tmp_path_factory):
    """One complete run of the tiny config (do not modify; copy it first)."""
    out = tmp_path_factory.mktemp("run") / "out"
    events = []
    stages = []
    outcomes = run_pipeline(tiny_run_config, out, progress=events.append,
                            on_stage=lambda plan, status: stages.append((plan.name, status)))
    return out, outcomes, events, stages


def _copy(finished_run, tmp_path):
    target = tmp_path / "out"
    shutil.copytree(finished_run[0], target)
    return target


def _statuses(outcomes):
    return {o.name: o.status for o in outcomes}


def _bytes(directory):
    return {p.relative_to(directory): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def test_first_run_runs_every_stage_and_writes_all_outputs(finished_run):
    out, outcomes, events, stages = finished_run
    assert [o.name for o in outcomes] == ["simulate", "reconstruct", "report"]
    assert _statuses(outcomes) == {"simulate": "ran", "reconstruct": "ran", "report": "ran"}
    assert stages == [("simulate", "start"), ("reconstruct", "start"), ("report", "start")]
    assert (out / "captures.h5").is_file() and (out / "recon.h5").is_file()
    assert (out / "report" / "report.json").is_file()
    pngs = sorted(p.name for p in (out / "report").glob("*.png"))
    assert {"observed_centre.png", "recovered_magnitude.png"} <= set(pngs)
    for png in pngs:
        assert (out / "report" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    iterations = [e for e in events if e.stage == "reconstruct"]
    assert [e.done for e in iterations] == list(range(1, 31))
    assert any(e.stage == "simulate" and e.done == e.total == 25 for e in events)
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


def test_report_has_the_required_keys_and_a_real_gain(finished_run, tiny_run_config):
    out = finished_run[0]
    report = json.loads((out / "report" / "report.json").read_text())
    assert REPORT_KEYS <= set(report)
    assert report["sar"] == pytest.approx(2.56)
    assert report["grid"] == [5, 5] and report["n_images"] == 25 and report["overlap"] == pytest.approx(0.61)
    assert report["engine"] == "altmin" and report["iterations"] == 30 and report["seconds"] >= 0
    optics = tiny_run_config.optics
    assert report["spot_size_sensor_m"] == pytest.approx(
        spot_size_m(optics.wavelength_m, optics.focal_length_m, optics.aperture_diameter_m))
    assert report["spot_size_object_m"] == pytest.approx(
        spot_size_m(optics.wavelength_m, optics.distance_m, optics.aperture_diameter_m))
    assert report["mtf20_observed_px"] == 6
    assert report["mtf20_recovered_px"] <= 3
    assert report["resolution_gain"] == pytest.approx(report["mtf20_observed_px"] / report["mtf20_recovered_px"])
    assert report["rmse_recovered"] < 0.8 * report["rmse_observed"]
    for key in ("contrast_observed", "contrast_recovered"):
        assert report[key]["widths_px"] == [6, 4, 3, 2, 1]
    assert report["provenance"]["stage"] == "report"
    assert set(report["figures"]) == {p.name for p in (out / "report").glob("*.png")}


def test_hdf5_outputs_carry_units_and_provenance(finished_run, tiny_run_config):
    out = finished_run[0]
    plans = {p.name: p for p in plan_stages(tiny_run_config, out)}
    for name, stage in (("captures.h5", "simulate"), ("recon.h5", "reconstruct")):
        with h5py.File(out / name, "r") as handle:
            attrs = dict(handle.attrs)
            assert PROVENANCE_KEYS <= set(attrs)
            assert attrs["cca_schema"] == SCHEMA_VERSION and attrs["stage"] == stage
            digest = config_hash(pick_sections(tiny_run_config, plans[stage].sections))
            assert attrs["config_hash"] == digest
            datasets = []
            handle.visititems(lambda n, o: datasets.append(o) if isinstance(o, h5py.Dataset) else None)
            assert datasets
            for dataset in datasets:
                assert "units" in dataset.attrs, dataset.name
    with h5py.File(out / "captures.h5", "r") as handle:
        intensity = handle["/measurements/intensity"]
        assert intensity.shape == (25, 96, 96) and intensity.dtype == np.float32
        assert intensity.attrs["units"].startswith("irradiance")
        assert json.loads(handle.attrs["inputs"]) == []
    with h5py.File(out / "recon.h5", "r") as handle:
        inputs = json.loads(handle.attrs["inputs"])
        assert [i["path"] for i in inputs] == [str(out / "captures.h5")]
        assert "tau: 0.001" in handle.attrs["config"]
        assert handle["/recon/spectrum"].dtype == np.complex64
        assert handle["/history/residual"].shape == (30,)
        assert handle["recon"].attrs["iterations"] == 30


def test_second_run_skips_every_stage(finished_run, tiny_run_config, tmp_path):
    out = _copy(finished_run, tmp_path)
    before = _bytes(out)
    stages = []
    outcomes = run_pipeline(tiny_run_config, out, on_stage=lambda plan, status: stages.append(status))
    assert _statuses(outcomes) == {"simulate": "skipped", "reconstruct": "skipped", "report": "skipped"}
    assert stages == ["skipped"] * 3
    assert _bytes(out) == before


def test_deleting_recon_reruns_only_reconstruct_and_report(finished_run, tiny_run_config, tmp_path):
    out = _copy(finished_run, tmp_path)
    captures = (out / "captures.h5").read_bytes()
    (out / "recon.h5").unlink()
    outcomes = run_pipeline(tiny_run_config, out)
    assert _statuses(outcomes) == {"simulate": "skipped", "reconstruct": "ran", "report": "ran"}
    assert (out / "captures.h5").read_bytes() == captures
    report = json.loads((out / "report" / "report.json").read_text())
    recorded = json.loads(report["provenance"]["inputs"])
    from cca_cli.io.h5 import file_sha256

    assert recorded[0]["sha256"] == file_sha256(out / "recon.h5")
    # ... and now everything is up to date again.
    assert set(_statuses(run_pipeline(tiny_run_config, out)).values()) == {"skipped"}


@pytest.mark.parametrize("how", ["defaults changed", "made before recipes were recorded"])
def test_a_recon_from_other_engine_defaults_is_recomputed(finished_run, tiny_run_config, tmp_path, monkeypatch, how):
    """Same config and captures, but cca's defaults changed since recon.h5 was made: recomputed, with a note."""
    out = _copy(finished_run, tmp_path)
    captures = (out / "captures.h5").read_bytes()
    with h5py.File(out / "recon.h5", "r") as handle:
        recorded = handle.attrs["engine_recipe"]
    assert recorded == reconstruct_stage.engine_recipe(out / "captures.h5", tiny_run_config.reconstruct)
    if how == "defaults changed":
        name, options = reconstruct_stage.engine_options(tiny_run_config.reconstruct, "simulation")
        changed = options.model_copy(update={"tau": options.tau * 2 + 1e-3})
        monkeypatch.setattr(reconstruct_stage, "engine_options", lambda section, kind, **_: (name, changed))
    else:
        with h5py.File(out / "recon.h5", "a") as handle:
            del handle.attrs["engine_recipe"]
    stages = []
    outcomes = run_pipeline(tiny_run_config, out, on_stage=lambda plan, status: stages.append((plan.name, status)))
    assert _statuses(outcomes) == {"simulate": "skipped", "reconstruct": "ran", "report": "ran"}
    assert ("reconstruct", "outdated") in stages
    assert (out / "captures.h5").read_bytes() == captures
    with h5py.File(out / "recon.h5", "r") as handle:
        assert handle.attrs["engine_recipe"] == reconstruct_stage.engine_recipe(out / "captures.h5",
                                                                                tiny_run_config.reconstruct)
    assert set(_statuses(run_pipeline(tiny_run_config, out)).values()) == {"skipped"}


def test_the_engine_recipe_leaves_threads_and_device_out(finished_run, tiny_run_config):
    captures = finished_run[0] / "captures.h5"
    section = tiny_run_config.reconstruct
    recipe = reconstruct_stage.engine_recipe(captures, section)
    options = {**section.options, "threads": 1}
    assert reconstruct_stage.engine_recipe(captures, section.model_copy(update={"options": options})) == recipe
    assert reconstruct_stage.engine_recipe(captures, section.model_copy(update={"device": "auto"})) == recipe
    assert reconstruct_stage.engine_recipe(captures, section.model_copy(update={"tau": section.tau * 2})) != recipe
    # tiles resolve as the tiled run does (the calibrating preset of the geometry's kind), not as a whole frame
    whole = ReconstructSection(**{**section.model_dump(), "engine": "auto"})
    tiled = ReconstructSection(**{**whole.model_dump(), "tiles": {"size_px": 96, "overlap_px": 32}})
    assert reconstruct_stage.engine_recipe(captures, tiled) not in (reconstruct_stage.engine_recipe(captures, whole), "")
    assert reconstruct_stage.engine_recipe(finished_run[0] / "missing.h5", section) == ""


def test_a_recon_written_by_cca_reconstruct_is_current_for_cca_run(finished_run, tiny_run_config, tmp_path):
    """The one-stage command records the same recipe, so a later `cca run` of that config skips it."""
    out = _copy(finished_run, tmp_path)
    with h5py.File(out / "recon.h5", "r") as handle:
        recorded = handle.attrs["engine_recipe"]
    (out / "recon.h5").unlink()
    shutil.rmtree(out / "report")   # its input is about to change
    plan = next(p for p in plan_stages(tiny_run_config, out) if p.name == "reconstruct")
    from cca_cli.stages.runner import stage_provenance

    provenance = stage_provenance("reconstruct", pick_sections(tiny_run_config, plan.sections), plan.inputs)
    reconstruct_stage.run(plan.inputs[0], tiny_run_config.reconstruct, out / "recon.h5", provenance=provenance)
    with h5py.File(out / "recon.h5", "r") as handle:
        assert handle.attrs["engine_recipe"] == recorded
    assert _statuses(run_pipeline(tiny_run_config, out)) == {"simulate": "skipped", "reconstruct": "skipped",
                                                             "report": "ran"}


def test_changed_reconstruct_config_needs_force(finished_run, tiny_run_config, tmp_path):
    out = _copy(finished_run, tmp_path)
    before = _bytes(out)
    changed = apply_overrides(tiny_run_config, {"reconstruct.tau": 0.01, "reconstruct.iterations": 5})
    with pytest.raises(OutputExistsError, match="--force") as excinfo:
        run_pipeline(changed, out)
    assert "recon.h5" in str(excinfo.value)
    assert _bytes(out) == before
    outcomes = run_pipeline(changed, out, force=True)
    assert _statuses(outcomes) == {"simulate": "ran", "reconstruct": "ran", "report": "ran"}
    with h5py.File(out / "recon.h5", "r") as handle:
        assert "tau: 0.01" in handle.attrs["config"]
        assert handle["recon"].attrs["iterations"] == 5
    assert json.loads((out / "report" / "report.json").read_text())["iterations"] == 5
    assert set(_statuses(run_pipeline(changed, out)).values()) == {"skipped"}


def test_changed_report_config_needs_force_but_keeps_upstream(finished_run, tiny_run_config, tmp_path):
    out = _copy(finished_run, tmp_path)
    changed = apply_overrides(tiny_run_config, {"report.mtf_threshold": 0.3})
    with pytest.raises(OutputExistsError, match="report"):
        run_pipeline(changed, out)


def test_sensor_and_band_storage_give_the_same_recovery(tiny_run_config):
    """Band-size captures are the sensor captures Fourier-cropped: the recovered field must agree."""
    spectra, sims = {}, {}
    for store in ("sensor", "band"):
        config = apply_overrides(tiny_run_config, {"simulate.store": store, "noise.model": "none"})
        sims[store] = sim = simulate_stage.simulate(config)
        captures = CaptureSet(intensity=sim.intensity, geometry=sim.geometry)
        spectra[store] = reconstruct_captures(captures, config.reconstruct, source=Path("x")).spectrum
    assert sims["sensor"].intensity.shape[-1] == 96
    band_size = sims["band"].intensity.shape[-1]
    assert band_size == sims["band"].layout.lowres_size < 96
    # The band images are exactly the sensor images with their (empty) high frequencies cut off.
    from cca_cli.optics.fft import fourier_resample

    np.testing.assert_allclose(fourier_resample(sims["sensor"].intensity, band_size), sims["band"].intensity,
                               atol=1e-5 * float(sims["band"].intensity.max()))
    # Spectra live on different grids (M = 96 vs the band's M); zero-pad the smaller one (orthonormal scale M).
    big, small = spectra["sensor"], spectra["band"]
    n, size = small.shape[-1], big.shape[-1]
    padded = np.zeros_like(big)
    start = size // 2 - n // 2
    padded[start:start + n, start:start + n] = small * (size / n)
    assert np.linalg.norm(padded - big) <= 1e-3 * np.linalg.norm(big)


def test_simulation_is_reproducible_and_noise_follows_the_seed(tiny_run_config):
    a = simulate_stage.simulate(tiny_run_config).intensity
    b = simulate_stage.simulate(tiny_run_config).intensity
    c = simulate_stage.simulate(apply_overrides(tiny_run_config, {"noise.seed": 2})).intensity
    clean = simulate_stage.simulate(apply_overrides(tiny_run_config, {"noise.model": "none"})).intensity
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    noise = (a - clean).astype(np.float64)
    expected = clean.reshape(25, -1).var(axis=1, dtype=np.float64) / 10 ** (40 / 10)
    np.testing.assert_allclose(noise.reshape(25, -1).var(axis=1), expected, rtol=0.1)


def test_recorded_positions_report_the_overlap_their_step_gives():
    """Stage readings carry no stated overlap: the derived quantities give the one their usual spacing gives
    (60% at 0.4 d), whatever one position re-recorded 20 µm off its neighbour does."""
    import cca_cli as cca
    from cca_cli.report.summary import derived_quantities

    d = 25e-3
    positions = [[0.4 * d * r, 0.4 * d * c] for r in range(-2, 3) for c in range(-2, 3)] + [[20e-6, 0.0]]
    geometry = cca.stage_scan(positions, wavelength_m=550e-9, focal_length_m=0.075, aperture_diameter_m=d,
                              pixel_pitch_m=2e-6, distance_m=50.0, image_pixels=128)
    derived = derived_quantities(geometry)
    assert derived["overlap"] == pytest.approx(0.6)
