"""Recorded captures: manifest → ingest → hdr → register → reconstruct → report, and bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.config.load import load_config
from cca_cli.io.images import write_image
from cca_cli.metrics import rmse
from cca_cli.registration.homography import apply_homography
from cca_cli.registration.synthetic import checkerboard_corners
from cca_cli.report.summary import on_grid
from cca_cli.stages.runner import run_pipeline

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data_samples" / "sample_capture"
SHARED = ROOT.parent / "shared" / "datasets" / "fpm-zheng-bloodsmear"
runner = CliRunner()

OPTICS = {"wavelength_m": 550e-9, "focal_length_m": 0.1, "aperture_diameter_m": 4.6e-3, "pixel_pitch_m": 2.5e-6,
          "distance_m": 10.0}


def _cli(*args):
    return runner.invoke(app, [str(a) for a in args])


def _one_line_error(result, *needles):
    assert result.exit_code != 0
    text = " ".join(result.output.split())
    assert "error:" in text
    for needle in needles:
        assert needle in text, text


@pytest.fixture(scope="module")
def sample_run(tmp_path_factory):
    """The shipped sample capture set through the configured pipeline (fewer iterations)."""
    out = tmp_path_factory.mktemp("sample")
    config = load_config(ROOT / "configs" / "sample_capture.yaml")
    config = config.model_copy(update={"reconstruct": config.reconstruct.model_copy(update={"iterations": 60})})
    outcomes = run_pipeline(config, out, force=True)
    return out, {o.name: o for o in outcomes}


def test_sample_path_recovers_object_better_than_centre_view(sample_run):
    out, outcomes = sample_run
    assert [*outcomes] == ["ingest", "hdr", "register", "reconstruct", "report"]
    truth = np.load(SAMPLE / "truth.npy")
    with h5py.File(out / "recon.h5") as f:
        recovered, observed = f["/recon/intensity"][()], f["/observed/centre"][()]
    size = truth.shape[-1]
    err_obs, err_rec = rmse(on_grid(observed, size), truth), rmse(on_grid(recovered, size), truth)
    assert err_rec < 0.85 * err_obs, (err_obs, err_rec)
    report = json.loads((out / "report" / "report.json").read_text())
    assert report["lost_positions"] == []
    assert report["sharpness_gain"] > 1.2
    assert report["energy_beyond_cutoff_recovered"] > 10 * report["energy_beyond_cutoff_observed"]
    assert {"observed_centre.png", "recovered_phase.png", "spectrum.png"} <= set(report["figures"])


def test_registration_recovers_known_homographies(sample_run):
    out, _ = sample_run
    truth = np.load(SAMPLE / "truth_homographies.npy")  # reference → view
    ref = checkerboard_corners((9, 6), 9.0, (110.0, 48.0))
    with h5py.File(out / "registered.h5") as f:
        estimated = f["/registration/homography"][()]    # view → reference
        assert f["/measurements/intensity"].shape == (25, 96, 96)
        assert f["/geometry"].attrs["field_width_m"] == pytest.approx(96 * 0.25e-3)
    errors = [np.sqrt(np.mean(np.sum((apply_homography(apply_homography(ref, h), e) - ref) ** 2, axis=-1)))
              for h, e in zip(truth, estimated)]
    assert max(errors) < 0.1, errors


def test_hdr_stage_recovers_radiance_within_one_percent(tmp_path):
    rng = np.random.default_rng(1)
    radiance = np.exp(rng.uniform(np.log(1e3), np.log(3.9e6), (24, 24))).astype(np.float32)  # counts/s
    radiance[:3] = 5e6                                               # saturated in every exposure
    times = (0.001, 0.01, 0.1)
    images = []
    for e, t in enumerate(times):
        codes = np.clip(np.rint(radiance * t) + 10, 0, 4095)
        write_image(tmp_path / f"a{e}.png", codes, bit_depth=16)
        images.append({"path": f"a{e}.png", "exposure_s": t, "stage_x_mm": 0.0, "stage_y_mm": 0.0})
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(
        {"optics": OPTICS, "sensor": {"black_level": 10, "white_level": 4095}, "images": images}))
    assert _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5", "-q").exit_code == 0
    result = _cli("hdr", tmp_path / "raw.h5", "-o", tmp_path / "hdr.h5", "-q")
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "hdr.h5") as f:
        merged, weight = f["/measurements/intensity"][0], f["/measurements/weight"][0]
        assert f["/hdr/dynamic_range_gain"][0] >= 1
    ok = weight > 0
    assert not ok[:3].any() and ok[3:].all()
    rel = np.abs(merged[ok] - radiance[ok]) / radiance[ok]
    assert rel.max() < 0.01, rel.max()
    # one warning for the whole set, naming the position and its share (3 rows of 24: 12.5%)
    said = " ".join(result.output.split())
    assert said.count("saturated in every exposure") == 1
    assert "1 of 1 positions have pixels saturated in every exposure (" in said and "12.5%)" in said


def test_positions_saturated_in_every_exposure_are_named_in_one_line():
    from cca_cli.stages.hdr import saturated_note

    labels = [f"image {i}" for i in range(6)]
    assert saturated_note(np.array([0, 0.005, 0, 0, 0, 0]), labels) == ""
    note = saturated_note(np.array([0.02, 0.5, 0, 0.03, 0.2, 0.011]), labels)
    assert note.startswith("5 of 6 positions have pixels saturated in every exposure (image 1 50.0%, image 4 20.0%, "
                           "image 3 3.0% and 2 more)")


def _small_set(tmp_path: Path, n: int = 2, size=(16, 16), **extra) -> Path:
    images = []
    for i in range(n):
        write_image(tmp_path / f"v{i}.png", np.full(size, 100 + i, np.float32), bit_depth=16)
        images.append({"path": f"v{i}.png", "exposure_s": 0.01, "stage_x_mm": float(i), "stage_y_mm": 0.0})
    manifest = {"optics": OPTICS, "sensor": {"black_level": 0, "white_level": 4095}, "images": images, **extra}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(manifest))
    return tmp_path / "m.yaml"


def _ingest_fails(tmp_path, *needles):
    out = tmp_path / "raw.h5"
    result = _cli("ingest", tmp_path / "m.yaml", "-o", out, "-q")
    _one_line_error(result, *needles)
    assert not out.exists()
    assert not list(tmp_path.glob(".raw.h5*"))


def test_small_manifest_ingests(tmp_path):
    _small_set(tmp_path)
    result = _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5", "-q")
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "raw.h5") as f:
        assert f["/raw/frames"].shape == (2, 1, 16, 16)
        np.testing.assert_allclose(f["/measurements/intensity"][1], 101 / 0.01, rtol=1e-6)


def test_missing_image_file(tmp_path):
    _small_set(tmp_path)
    (tmp_path / "v1.png").unlink()
    _ingest_fails(tmp_path, "v1.png", "not found")


def test_unreadable_image_file(tmp_path):
    _small_set(tmp_path)
    (tmp_path / "v1.png").write_bytes(b"not a png at all")
    _ingest_fails(tmp_path, "v1.png", "cannot read image")


def test_mixed_image_sizes(tmp_path):
    _small_set(tmp_path)
    write_image(tmp_path / "v1.png", np.zeros((16, 20), np.float32), bit_depth=16)
    _ingest_fails(tmp_path, "v1.png", "v0.png", "same size")


def test_exposure_listed_twice(tmp_path):
    path = _small_set(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["images"].append(dict(data["images"][0]))
    path.write_text(yaml.safe_dump(data))
    _ingest_fails(tmp_path, "m.yaml", "v0.png is listed twice at position (x 0, y 0) mm with exposure 0.01 s")


def test_two_images_at_one_position_are_both_named(tmp_path):
    path = _small_set(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["images"][1].update(stage_x_mm=data["images"][0]["stage_x_mm"], stage_y_mm=data["images"][0]["stage_y_mm"])
    path.write_text(yaml.safe_dump(data))
    _ingest_fails(tmp_path, "m.yaml", "v0.png and v1.png are both at position (x 0, y 0) mm with exposure 0.01 s",
                  "fix the position of one")


def test_misspelled_manifest_key(tmp_path):
    path = _small_set(tmp_path)
    data = yaml.safe_load(path.read_text())
    data["images"][1]["exposre_s"] = data["images"][1].pop("exposure_s")
    path.write_text(yaml.safe_dump(data))
    _ingest_fails(tmp_path, "m.yaml", "images.1.exposre_s", "unknown key")
    data["images"][1]["exposure_s"] = data["images"][1].pop("exposre_s")
    data["optics"]["wavelenght_m"] = data["optics"].pop("wavelength_m")
    path.write_text(yaml.safe_dump(data))
    _ingest_fails(tmp_path, "optics.wavelenght_m", "unknown key")


def test_nan_pixels(tmp_path):
    _small_set(tmp_path)
    bad = np.ones((16, 16), np.float32)
    bad[3, 4] = np.nan
    write_image(tmp_path / "v1.exr", bad)
    data = yaml.safe_load((tmp_path / "m.yaml").read_text())
    data["images"][1]["path"] = "v1.exr"
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(data))
    _ingest_fails(tmp_path, "v1.exr", "NaN")


def _two_sample_views_merged(tmp_path, covered: tuple[str, ...]) -> None:
    """The sample's views r2c2 (the centre) and r2c3, the board covered in those whose names start with ``covered``,
    ingested and merged into tmp_path/hdr.h5."""
    from cca_cli.io.images import read_image

    manifest = yaml.safe_load((SAMPLE / "manifest.yaml").read_text())
    chosen = [m for m in manifest["images"] if m["path"].startswith(("view_r2c2_", "view_r2c3_"))]
    for entry in chosen:
        shutil.copy(SAMPLE / entry["path"], tmp_path / entry["path"])
        if entry["path"].startswith(covered):
            pixels = read_image(tmp_path / entry["path"]).pixels
            pixels[:, 105:] = 64 + 100
            write_image(tmp_path / entry["path"], pixels, bit_depth=16)
    manifest["images"] = chosen
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(manifest))
    assert _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5", "-q").exit_code == 0
    assert _cli("hdr", tmp_path / "raw.h5", "-o", tmp_path / "hdr.h5", "-q").exit_code == 0


def test_no_checkerboard_names_view_or_drops_it(tmp_path):
    _two_sample_views_merged(tmp_path, covered=("view_r2c3_",))   # the second view's board covered
    out = tmp_path / "reg.h5"
    result = _cli("register", tmp_path / "hdr.h5", "-o", out, "--crop", "16,32,96,96", "-q")
    _one_line_error(result, "view_r2c3_e0.png", "no 9x6 checkerboard")
    assert not out.exists()
    result = _cli("register", tmp_path / "hdr.h5", "-o", out, "--crop", "16,32,96,96", "--drop-missing", "-q")
    assert result.exit_code == 0, result.output
    assert "lost" in result.output and "view_r2c3_e0.png" in " ".join(result.output.split())
    with h5py.File(out) as f:
        assert f["/measurements/intensity"].shape[0] == 1
        assert len(f["/registration/dropped"]) == 1


def test_no_checkerboard_in_the_reference_view_says_registration_cannot_drop_it(tmp_path):
    """Every view is registered to the centre one: dropping views cannot help when it lacks the board, and the one
    line says so (and how to go on without registration)."""
    _two_sample_views_merged(tmp_path, covered=("view_r2c2_", "view_r2c3_"))
    out = tmp_path / "reg.h5"
    result = _cli("register", tmp_path / "hdr.h5", "-o", out, "--crop", "16,32,96,96", "--drop-missing", "-q")
    _one_line_error(result, "no 9x6 checkerboard", "the reference (centre) view needs the board",
                    "leave register out of run.stages")
    assert "--drop-missing" not in " ".join(result.output.split()) and not out.exists()


def test_config_rejects_simulate_with_ingest(tmp_path):
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({"run": {"stages": ["simulate", "ingest", "reconstruct"]},
                                                     "ingest": {"manifest": "m.yaml"}}))
    from cca_cli.errors import ConfigError

    with pytest.raises(ConfigError, match="alternative"):
        load_config(tmp_path / "c.yaml")


@pytest.mark.skipif(not SHARED.is_dir(), reason=f"shared datasets not present: {SHARED}")
@pytest.mark.slow
def test_bloodsmear_led_dataset_reconstructs_sharper(tmp_path):
    config = load_config(ROOT / "configs" / "bloodsmear_green.yaml")
    config = config.model_copy(update={"reconstruct": config.reconstruct.model_copy(update={"iterations": 8})})
    run_pipeline(config, tmp_path, force=True)
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["n_images"] == 225
    assert report["grid"] == [15, 15]
    # The recovery puts several times more of its power beyond what the single objective records.
    assert report["energy_beyond_cutoff_recovered"] > 3 * report["energy_beyond_cutoff_observed"]


def test_a_camera_array_s_images_name_their_cameras(tmp_path):
    """Each camera its own lens: the rows name it, and /geometry/camera_index gives each capture's pupil."""
    path = _small_set(tmp_path, n=3)
    data = yaml.safe_load(path.read_text())
    for i, image in enumerate(data["images"]):
        image["camera"] = [0, 1, 1][i]
    path.write_text(yaml.safe_dump(data))
    result = _cli("ingest", path, "-o", tmp_path / "raw.h5", "-q")
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "raw.h5") as f:
        assert f["/geometry/camera_index"][()].tolist() == [0, 1, 1]
    (tmp_path / "raw.h5").unlink()
    del data["images"][2]["camera"]
    path.write_text(yaml.safe_dump(data))
    _ingest_fails(tmp_path, "m.yaml", "v2.png names no camera while v0.png names camera 0",
                  "give every image its camera")
