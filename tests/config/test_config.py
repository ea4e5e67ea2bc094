"""Config loading: one-line errors naming the file and the dotted key, presets, overrides."""

from pathlib import Path

import pytest
import yaml

from cca_cli.config.load import apply_overrides, dump_config, load_config, parse_config, preset_path
from cca_cli.config.model import RunConfig
from cca_cli.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]


def _error(write_config, data) -> str:
    path = write_config(data, name="bad.yaml")
    with pytest.raises(ConfigError) as excinfo:
        load_config(path)
    message = str(excinfo.value)
    assert str(path) in message
    assert "\n" not in message
    return message


def test_tiny_config_loads(write_config, tiny_config_data):
    config = load_config(write_config(tiny_config_data))
    assert isinstance(config, RunConfig)
    assert config.array.grid == 5 and config.scene.size_px == 96
    assert config.reconstruct.iterations == 30


@pytest.mark.parametrize(
    ("section", "key", "value", "dotted", "hint"),
    [
        ("optics", "wavelenght_m", 5e-7, "optics.wavelenght_m", "wavelength_m"),  # unknown key, lists accepted
        ("array", "grid", "five", "array.grid", "five"),                           # wrong type
        ("optics", "distance_m", "far", "optics.distance_m", "far"),                # wrong type
        ("noise", "model", "loud", "noise.model", "gaussian"),                      # bad literal
        ("reconstruct", "engine", "magic", "reconstruct.engine", "altmin"),         # unknown engine
        ("reconstruct", "options", {"bogus": 1}, "reconstruct.options", "bogus"),   # unknown engine option
        ("reconstruct", "tau", -1.0, "reconstruct.tau", "-1"),                      # out of range
    ],
)
def test_bad_values_name_the_file_and_the_dotted_key(write_config, tiny_config_data, section, key, value, dotted,
                                                      hint):
    tiny_config_data[section][key] = value
    message = _error(write_config, tiny_config_data)
    assert f"{dotted}:" in message
    assert hint in message


def test_unknown_section_is_rejected(write_config, tiny_config_data):
    tiny_config_data["optix"] = {}
    message = _error(write_config, tiny_config_data)
    assert "optix" in message and "optics" in message


def test_grid_and_sar_together_are_rejected(write_config, tiny_config_data):
    tiny_config_data["array"]["sar"] = 3.0
    message = _error(write_config, tiny_config_data)
    assert "array.grid" in message and "array.sar" in message


def test_neither_grid_nor_sar_is_rejected(write_config, tiny_config_data):
    del tiny_config_data["array"]["grid"]
    assert "array.sar" in _error(write_config, tiny_config_data)


def test_missing_file_and_invalid_yaml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("optics: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML") as excinfo:
        load_config(broken)
    assert str(broken) in str(excinfo.value)
    top = tmp_path / "list.yaml"
    top.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(top)


def test_scientific_notation_without_a_dot_is_a_float(tmp_path):
    path = tmp_path / "sci.yaml"
    path.write_text("optics:\n  wavelength_m: 550e-9\n  aperture_diameter_m: 18e-3\narray:\n  grid: 3\n")
    assert isinstance(yaml.safe_load(path.read_text())["optics"]["wavelength_m"], str)  # PyYAML's reading
    config = load_config(path)
    assert isinstance(config.optics.wavelength_m, float)
    assert config.optics.wavelength_m == pytest.approx(550e-9)
    assert config.optics.aperture_diameter_m == pytest.approx(18e-3)
    path.write_text("optics:\n  wavelength_m: -550e-9\n")
    with pytest.raises(ConfigError) as excinfo:
        load_config(path)
    assert str(excinfo.value).endswith("optics.wavelength_m: must be greater than 0 (in metres) (got -550e-9)")


def test_configs_headline_equals_the_builtin_preset():
    shipped = REPO / "configs" / "headline.yaml"
    preset = preset_path("headline")
    assert preset.is_file()
    assert shipped.read_text() == preset.read_text()
    assert load_config(shipped) == load_config(None) == load_config(preset)


def test_headline_preset_is_the_figure_5_case():
    config = load_config()
    assert config.optics.wavelength_m == pytest.approx(550e-9)
    assert config.optics.focal_length_m == pytest.approx(0.8)
    assert config.optics.aperture_diameter_m == pytest.approx(18e-3)
    assert config.optics.pixel_pitch_m == pytest.approx(2e-6)
    assert config.optics.distance_m == pytest.approx(50.0)
    assert config.scene.kind == "resolution_chart" and config.scene.size_px == 512
    assert config.scene.field_width_m == pytest.approx(64e-3)
    assert config.array.grid == 21 and config.array.overlap == pytest.approx(0.61)
    assert config.noise.model == "gaussian" and config.noise.snr_db == pytest.approx(30.0)
    assert config.reconstruct.engine == "altmin"
    assert config.reconstruct.tau == pytest.approx(1e-3) and config.reconstruct.tol == pytest.approx(1e-5)
    assert config.reconstruct.iterations == 1500
    assert config.report.mtf_threshold == pytest.approx(0.2)


def test_unknown_preset_is_a_config_error():
    with pytest.raises(ConfigError, match="headline"):
        preset_path("nope")


def test_apply_overrides_replaces_and_revalidates(tiny_config_data):
    config = parse_config(tiny_config_data)
    changed = apply_overrides(config, {"array.grid": 7, "array.overlap": 0.5, "reconstruct.tau": 0.01})
    assert changed.array.grid == 7 and changed.array.overlap == 0.5 and changed.reconstruct.tau == 0.01
    assert config.array.grid == 5  # the original is untouched (frozen)
    assert changed.optics == config.optics
    with pytest.raises(ConfigError, match=r"--set: array\.nope: unknown key"):
        apply_overrides(config, {"array.nope": 1})
    with pytest.raises(ConfigError, match="no such section 'nope'"):
        apply_overrides(config, {"nope.x": 1})
    with pytest.raises(ConfigError, match=r"array\.overlap"):
        apply_overrides(config, {"array.overlap": 1.5})


def test_config_is_frozen_and_round_trips_through_yaml(tiny_config_data):
    config = parse_config(tiny_config_data)
    with pytest.raises(Exception):
        config.array.grid = 9
    assert parse_config(yaml.safe_load(dump_config(config))) == config


def test_run_stages_must_be_in_pipeline_order(tiny_config_data):
    tiny_config_data["run"]["stages"] = ["report", "simulate"]
    with pytest.raises(ConfigError, match="run.stages|run:"):
        parse_config(tiny_config_data, source="x.yaml")


def test_unknown_key_in_an_optional_section_lists_its_keys(write_config, tiny_config_data):
    tiny_config_data["multiplex"] = {"camera_grid": [3, 3], "source_grid": [3, 3], "n_mux": 1, "bogus": 1}
    message = _error(write_config, tiny_config_data)
    assert "multiplex.bogus: unknown key" in message
    assert "camera_grid" in message and "n_mux" in message
