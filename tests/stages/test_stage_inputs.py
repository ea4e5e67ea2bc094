"""Stage building blocks: scene construction and the checks on stage inputs."""

import shutil

import h5py
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from cca_cli.config.load import apply_overrides
from cca_cli.config.model import ReconstructSection, ReportSection
from cca_cli.errors import ConfigError, InputError
from cca_cli.io.h5 import Provenance
from cca_cli.stages import report as report_stage
from cca_cli.stages import simulate as simulate_stage
from cca_cli.workflows.scenes import bars_to_table, build_scene, table_to_bars
from cca_cli.io.captures import read_captures
from cca_cli.workflows.recovery import embed_region, engine_options


def test_chart_scene_on_a_finer_grid_keeps_values_and_scales_boxes(tiny_run_config):
    scene = build_scene(tiny_run_config.scene, 96)
    finer = build_scene(tiny_run_config.scene, 192)
    assert scene.field.dtype == np.complex64 and scene.field.shape == (96, 96)
    np.testing.assert_array_equal(finer.field.real[::2, ::2], scene.field.real)
    assert {g.width_px for g in scene.bars} == {6, 4, 3, 2, 1}
    for coarse, fine in zip(scene.bars, finer.bars):
        assert fine.box == tuple(2 * v for v in coarse.box)
    assert table_to_bars(bars_to_table(scene.bars)) == scene.bars


def test_chart_that_does_not_fit_is_a_config_error(tiny_run_config):
    section = apply_overrides(tiny_run_config, {"scene.widths_px": [20, 18, 16]}).scene
    with pytest.raises(ConfigError, match="scene"):
        build_scene(section, 96)


def test_optics_that_leave_too_few_pixels_are_a_config_error(tiny_run_config):
    config = apply_overrides(tiny_run_config, {"scene.field_width_m": 0.5e-3})
    with pytest.raises(ConfigError, match="sensor pixels"):
        simulate_stage.simulate(config)


@pytest.fixture(scope="module")
def captures_file(tiny_run_config, tmp_path_factory):
    path = tmp_path_factory.mktemp("caps") / "captures.h5"
    provenance = Provenance.make("simulate", "", "x")
    config = apply_overrides(tiny_run_config, {"report.figures": False})
    simulate_stage.run(config, path, provenance=provenance)
    return path


def _edited_copy(source, tmp_path, edit):
    path = tmp_path / "edited.h5"
    shutil.copy(source, path)
    with h5py.File(path, "r+") as handle:
        edit(handle)
    return path


def test_read_captures_round_trip(captures_file):
    captures = read_captures(captures_file)
    assert captures.intensity.shape == (25, 96, 96)
    assert captures.geometry.n_images == 25 and captures.weight is None
    assert {"object", "bars"} <= set(captures.truth)


def test_read_captures_rejects_nan_images(captures_file, tmp_path):
    def poison(handle):
        handle["/measurements/intensity"][3, 5, 5] = np.nan

    with pytest.raises(InputError, match="image 3 .*NaN"):
        read_captures(_edited_copy(captures_file, tmp_path, poison))


def test_read_captures_pads_non_square_and_rejects_mismatched_images(captures_file, tmp_path):
    def crop(handle):
        data = handle["/measurements/intensity"][()]
        del handle["/measurements/intensity"]
        handle["/measurements/intensity"] = data[:, :, :90]

    # Non-square images are a window on a larger scene: padded to a square grid, unless padding is off.
    cropped = read_captures(_edited_copy(captures_file, tmp_path, crop))
    assert cropped.boundary == "open"
    padded, region = embed_region(cropped, ReconstructSection(), source=Path("c.h5"))
    assert padded.intensity.shape[1] == padded.intensity.shape[2] > 96 and region.shape == (96, 90)
    with pytest.raises(InputError, match="square"):
        embed_region(cropped, ReconstructSection(padding={"mode": "off"}), source=Path("c.h5"))

    def drop(handle):
        data = handle["/measurements/intensity"][()]
        del handle["/measurements/intensity"]
        handle["/measurements/intensity"] = data[:24]

    with pytest.raises(InputError, match="24 images"):
        read_captures(_edited_copy(captures_file, tmp_path, drop))

    def no_geometry(handle):
        del handle["geometry"]

    with pytest.raises(InputError, match="geometry"):
        read_captures(_edited_copy(captures_file, tmp_path, no_geometry))


def test_bad_engine_options_are_refused_when_the_config_is_read(tiny_run_config):
    with pytest.raises(ValidationError, match="chunk"):
        ReconstructSection(options={"chunk": "many"})
    with pytest.raises(ConfigError, match="reconstruct.options: chunk"):
        apply_overrides(tiny_run_config, {"reconstruct.options": {"chunk": "many"}})
    unchecked = ReconstructSection.model_construct(engine="altmin", tau=1e-3, iterations=5, tol=0.0,
                                                   options={"chunk": 0})
    with pytest.raises(ConfigError, match="reconstruct.options"):  # the stage checks again what it is given
        engine_options(unchecked)


def test_report_stage_refuses_a_captures_file(captures_file, tmp_path):
    provenance = Provenance.make("report", "", "x", [captures_file])
    with pytest.raises(InputError, match="expected 'reconstruct'"):
        report_stage.run(captures_file, ReportSection(), tmp_path / "report", provenance=provenance)
    assert not (tmp_path / "report").exists()
