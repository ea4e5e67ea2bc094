"""``frame_scale`` in files: every writer keeps it, every reader gives it, and the recipe resolves as the run does."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app
from cca_cli.config.model import ReconstructSection
from cca_cli.io.captures import read_captures
from cca_cli.io.images import write_image
from cca_cli.io.tiles import read_frame_info, read_tile_captures
from cca_cli.stages.reconstruct import engine_recipe
from cca_cli.workflows.recovery import engine_options, recipe_of
from cca_cli.workflows.tiled import tile_engine, tile_recipe

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data_samples" / "sample_capture"
runner = CliRunner()


def _cli(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    """One small recorded-like LED set saved twice: images scaled each on its own, and on one scale."""
    folder = tmp_path_factory.mktemp("frame_scale")
    geometry = cca.led_array(cca.led_grid_sines(3, pitch_m=4e-3, height_m=60e-3), wavelength_m=532e-9,
                             numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6, image_pixels=64)
    chart = cca.resolution_chart(128, widths=(6, 4, 3, 2)).image
    images = cca.simulate(chart, geometry, snr_db=None).astype(np.float32)
    paths = {}
    for scale in ("per_frame", "shared"):
        paths[scale] = cca.save(cca.CaptureSet(images, geometry, units="counts/s", boundary="open",
                                               frame_scale=scale), folder / f"{scale}.h5")
    return paths


def test_the_tile_readers_give_the_frame_scale(paths):
    assert read_frame_info(paths["per_frame"]).frame_scale == "per_frame"
    assert read_frame_info(paths["shared"]).frame_scale == "shared"
    assert read_tile_captures(paths["per_frame"], (0, 0, 32, 32)).frame_scale == "per_frame"
    assert read_tile_captures(paths["shared"], (0, 0, 32, 32)).frame_scale == "shared"


def test_the_recipes_resolve_as_the_runs_do(paths):
    section = ReconstructSection()
    recipes = {}
    for scale, path in paths.items():
        captures = read_captures(path)
        ran = recipe_of(*engine_options(section, captures.kind, frame_scale=captures.frame_scale))
        assert ran["options"]["brightness"] is (scale == "per_frame")
        recipes[scale] = engine_recipe(path, section)
        assert recipes[scale] == hashlib.sha256(json.dumps(ran, sort_keys=True).encode()).hexdigest()
    assert recipes["per_frame"] != recipes["shared"]   # a recon of the one is not reused for the other

    tiled = ReconstructSection.model_validate({"tiles": {"size_px": 32, "overlap_px": 8}})
    for scale, path in paths.items():
        frame = read_frame_info(path)
        geometry_kind = read_captures(path).geometry.kind
        ran = recipe_of(*tile_engine(tiled, geometry_kind, frame_scale=frame.frame_scale))
        assert tile_recipe(tiled, path) == {**ran, "dead_captures": "left out"}
        assert ran["options"]["brightness"] is (scale == "per_frame")


def test_a_bad_attribute_is_one_line_naming_the_file(paths, tmp_path):
    bad = tmp_path / "bad.h5"
    shutil.copy(paths["per_frame"], bad)
    with h5py.File(bad, "a") as handle:
        handle["/measurements/intensity"].attrs["frame_scale"] = "each"
    result = _cli("reconstruct", bad, "-o", tmp_path / "recon.h5", "-q")
    assert result.exit_code != 0
    text = " ".join(result.output.split())
    assert text.startswith("error:") and text.count("error:") == 1, text
    assert str(bad) in text and "frame_scale 'each'" in text and "'per_frame'" in text
    assert not (tmp_path / "recon.h5").exists()


def test_single_exposures_ingest_with_the_frame_scale(tmp_path):
    images = []
    for i in range(2):
        write_image(tmp_path / f"v{i}.png", 100 + i + np.arange(256, dtype=np.float32).reshape(16, 16), bit_depth=16)
        images.append({"path": f"v{i}.png", "exposure_s": 0.01, "stage_x_mm": float(i), "stage_y_mm": 0.0})
    optics = {"wavelength_m": 550e-9, "focal_length_m": 0.1, "aperture_diameter_m": 4.6e-3, "pixel_pitch_m": 2.5e-6,
              "distance_m": 10.0}
    manifest = {"optics": optics, "sensor": {"black_level": 0, "white_level": 4095, "frame_scale": "per_frame"},
                "images": images}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(manifest))
    result = _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5", "-q")
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "raw.h5") as handle:
        assert handle["/raw/frames"].attrs["frame_scale"] == "per_frame"
        assert handle["/measurements/intensity"].attrs["frame_scale"] == "per_frame"
    assert cca.load(tmp_path / "raw.h5").frame_scale == "per_frame"


def test_register_keeps_the_frame_scale(tmp_path):
    manifest = yaml.safe_load((SAMPLE / "manifest.yaml").read_text())
    # one exposure a position: frames scaled each on its own have no exposure brackets
    chosen = [m for m in manifest["images"] if m["path"] in ("view_r2c2_e1.png", "view_r2c3_e1.png")]
    for entry in chosen:
        shutil.copy(SAMPLE / entry["path"], tmp_path / entry["path"])
    manifest["images"] = chosen
    manifest["sensor"] = {**manifest["sensor"], "frame_scale": "per_frame"}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(manifest))
    assert _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5", "-q").exit_code == 0
    assert _cli("hdr", tmp_path / "raw.h5", "-o", tmp_path / "hdr.h5", "-q").exit_code == 0
    result = _cli("register", tmp_path / "hdr.h5", "-o", tmp_path / "reg.h5", "--crop", "16,32,96,96", "-q")
    assert result.exit_code == 0, result.output
    assert read_captures(tmp_path / "reg.h5").frame_scale == "per_frame"
    assert read_frame_info(tmp_path / "reg.h5").frame_scale == "per_frame"


def test_cca_reconstruct_fits_the_brightness_of_images_scaled_each_on_its_own(paths, tmp_path):
    for scale, path in paths.items():
        out = tmp_path / f"{scale}_recon.h5"
        result = _cli("reconstruct", path, "-o", out, "--iterations", 14, "-q")   # brightness rounds from pass 10
        assert result.exit_code == 0, result.output
        assert cca.load(out).options["brightness"] is (scale == "per_frame")
        printed = _cli("report", out, "-o", tmp_path / f"{scale}_report", "--no-figures")
        assert printed.exit_code == 0, printed.output
        assert ("capture brightness min / median / max" in printed.output) is (scale == "per_frame")


def test_any_engine_that_can_fit_the_brightness_does_and_other_engines_say_they_do_not(paths, caplog):
    from cca_cli.engines.registry import resolve

    for kind in ("led_array", "camera_scan", "simulation"):
        assert resolve("momentum", kind, {}, frame_scale="per_frame")[1].brightness is True
        assert resolve("momentum", kind, {}, frame_scale="shared")[1].brightness is False
    with pytest.raises(ValueError, match="frame_scale must be"):
        resolve("momentum", "led_array", {}, frame_scale="per-frame")
    with caplog.at_level("WARNING", logger="cca"):
        cca.reconstruct(cca.load(paths["per_frame"]), engine="altmin", max_iterations=1)
    assert "fits no brightness" in caplog.text


@pytest.mark.parametrize("white_level", [None, 65535])
def test_frames_scaled_to_their_own_maximum_keep_their_brightest_pixel(tmp_path, white_level):
    images = []
    for i in range(4):
        frame = (1 + i + np.arange(256, dtype=np.float64)).reshape(16, 16)
        write_image(tmp_path / f"v{i}.png", np.round(frame / frame.max() * 65535).astype(np.uint16), bit_depth=16)
        images.append({"path": f"v{i}.png", "exposure_s": 0.01, "stage_x_mm": float(i), "stage_y_mm": 0.0})
    optics = {"wavelength_m": 550e-9, "focal_length_m": 0.1, "aperture_diameter_m": 4.6e-3, "pixel_pitch_m": 2.5e-6,
              "distance_m": 10.0}
    sensor = {"frame_scale": "per_frame"} if white_level is None else {"frame_scale": "per_frame",
                                                                       "white_level": white_level}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"optics": optics, "sensor": sensor, "images": images}))
    result = _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5", "-q")
    assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "raw.h5") as handle:
        clipped = int((handle["/measurements/weight"][()] == 0).sum())
    assert (clipped == 0) is (white_level is None)   # a stated white level still marks what comes near it


def test_frames_that_all_peak_at_one_value_are_noted_when_nothing_is_said(tmp_path):
    images = []
    for i in range(4):
        frame = np.roll(1 + i + np.arange(256, dtype=np.float64), 37 * i).reshape(16, 16)   # brightest here and there
        write_image(tmp_path / f"v{i}.png", np.round(frame / frame.max() * 65535).astype(np.uint16), bit_depth=16)
        images.append({"path": f"v{i}.png", "exposure_s": 0.01, "stage_x_mm": float(i), "stage_y_mm": 0.0})
    optics = {"wavelength_m": 550e-9, "focal_length_m": 0.1, "aperture_diameter_m": 4.6e-3, "pixel_pitch_m": 2.5e-6,
              "distance_m": 10.0}
    for sensor, noted in (({}, True), ({"frame_scale": "per_frame"}, False), ({"white_level": 65535}, False)):
        (tmp_path / "m.yaml").write_text(yaml.safe_dump({"optics": optics, "sensor": sensor, "images": images}))
        result = _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5", "--force")
        assert result.exit_code == 0, result.output
        text = " ".join(result.output.split())
        assert ("every frame peaks at exactly 65535" in text and "sensor.frame_scale: per_frame" in text) is noted


def test_one_hot_pixel_brightest_in_every_frame_is_not_taken_for_scaled_frames(tmp_path):
    frames = [np.full((16, 16), 500 + 100 * i, np.uint16) for i in range(4)]
    for frame in frames:
        frame[3, 5] = 4095   # a hot pixel: every frame's brightest, at one place
    result = _ingest_frames(tmp_path, frames)
    assert result.exit_code == 0, result.output
    assert "peaks at exactly" not in result.output


def _ingest_frames(tmp_path, frames):
    """Ingest 16-bit ``frames`` of a four-position stage scan (the CLI's result)."""
    images = []
    for i, frame in enumerate(frames):
        write_image(tmp_path / f"v{i}.png", frame, bit_depth=16)
        images.append({"path": f"v{i}.png", "exposure_s": 0.01, "stage_x_mm": float(i), "stage_y_mm": 0.0})
    optics = {"wavelength_m": 550e-9, "focal_length_m": 0.1, "aperture_diameter_m": 4.6e-3, "pixel_pitch_m": 2.5e-6,
              "distance_m": 10.0}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"optics": optics, "images": images}))
    return _cli("ingest", tmp_path / "m.yaml", "-o", tmp_path / "raw.h5")


def test_a_hot_pixel_at_full_scale_beside_clipped_frames_is_named_and_not_taken_for_scaled_frames(tmp_path):
    """Bright-field frames clip at full scale here and there, and one hot pixel sits there in every frame."""
    frames = [np.full((16, 16), 500 + 100 * i, np.uint16) for i in range(4)]
    for i, frame in enumerate(frames):
        if i % 2:
            frame[:2, :] = 65535   # clipped, ahead of the hot pixel in raster order
        frame[3, 5] = 65535
    result = _ingest_frames(tmp_path, frames)
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "pixel (x 5, y 3) sits at 65535 in every frame: a hot pixel? it counts as clipped (weight 0)" in text
    assert "per_frame" not in text
    with h5py.File(tmp_path / "raw.h5") as handle:
        assert (handle["/measurements/weight"][:, 3, 5] == 0).all()


def test_a_hot_pixel_clipped_in_every_frame_stays_clipped_rather_than_filled(tmp_path):
    """With enough frames for the hot-pixel fill, a pixel at full scale in every frame keeps the clipped rule."""
    frames = [np.full((16, 16), 500 + 100 * i, np.uint16) for i in range(6)]
    for i, frame in enumerate(frames):
        if i % 2:
            frame[:2, :] = 65535
        frame[3, 5] = 65535
    result = _ingest_frames(tmp_path, frames)
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "a hot pixel? it counts as clipped (weight 0)" in text and "stand far above" not in text
    with h5py.File(tmp_path / "raw.h5") as handle:
        assert (handle["/measurements/weight"][:, 3, 5] == 0).all()
