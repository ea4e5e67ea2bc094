"""How values are read (booleans, integers, finite numbers), in configs and engine options alike."""

from dataclasses import replace
from typing import Optional

import pytest
from pydantic import ValidationError, model_validator

from cca_cli.config.load import parse_config
from cca_cli.config.model import ReconstructSection
from cca_cli.engines.options import EngineOptions
from cca_cli.engines.registry import ENGINES, engine_help, resolve
from cca_cli.errors import ConfigError
from cca_cli.values import read_value


@pytest.mark.parametrize(("annotation", "value", "expected"), [
    (int, 10, 10), (int, "1e1", 10), (int, 12.7, 12.7), (int, 4.0, 4), (float, "550e-9", "550e-9"), (bool, False, False),
    (bool | None, None, None), (list[int], ["2e0", 3], [2, 3]), (tuple[float, ...], (1, 2), [1, 2]),
])
def test_values_that_are_read(annotation, value, expected):
    assert read_value(annotation, value) == expected  # pydantic then refuses 12.7 for an int


@pytest.mark.parametrize(("annotation", "value", "message"), [
    (int, True, "expected a number"), (float, False, "expected a number"), (bool, "no", "true or false"),
    (bool, 1, "true or false"), (bool | None, "yes", "true or false"), (str, True, "expected text"),
    (list[int], [1, True], "expected a number"),
])
def test_values_that_are_refused(annotation, value, message):
    with pytest.raises(ValueError, match=message):
        read_value(annotation, value)


def test_every_section_refuses_non_finite_numbers_and_booleans_as_numbers():
    for data, key in (({"optics": {"wavelength_m": float("inf")}}, "optics.wavelength_m"),
                      ({"reconstruct": {"tau": float("nan")}}, "reconstruct.tau"),
                      ({"noise": {"seed": True}}, "noise.seed"),
                      ({"run": {"stages": []}}, "run.stages"),
                      ({"report": {"figures": "no"}}, "report.figures")):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            parse_config(data, source="c.yaml")


class FutureOptions(EngineOptions):
    """An engine's options with fields no code in config knows about."""

    max_iterations: int = 10
    window: int = 3
    adaptive: bool = False
    weights: tuple[float, ...] = (1.0,)
    mode: str = "fast"
    cap: Optional[int] = None

    @model_validator(mode="after")
    def _window(self):
        if self.window < 1:
            raise ValueError(f"window must be ≥ 1, got {self.window}")
        return self


def test_a_new_engine_needs_no_config_code(monkeypatch):
    monkeypatch.setitem(ENGINES, "future", replace(ENGINES["altmin"], name="future", options=FutureOptions))
    section = ReconstructSection(engine="future", options={"window": "5e0", "adaptive": True, "weights": [1, "2"],
                                                           "cap": 4.0})
    assert section.options == {"window": 5, "adaptive": True, "weights": (1.0, 2.0), "cap": 4}
    for options, message in (({"window": 2.5}, "window: must be a whole number \\(got 2.5\\)"),
                             ({"adaptive": "no"}, "adaptive: expected true or false"),
                             ({"window": 0}, "window must be ≥ 1"),
                             ({"mode": True}, "mode: expected text"),
                             ({"tau": 1}, "tau is not an option: set it as reconstruct.tau"),
                             ({"windw": 3}, "accepted: .*window, adaptive, weights, mode, cap")):
        with pytest.raises(ValidationError, match=message):
            ReconstructSection(engine="future", options=options)
    assert "future" in engine_help()


@pytest.mark.parametrize(("given", "read"), [
    ({"tau": "1e-3"}, {"tau": 1e-3}), ({"batch": 2.0}, {"batch": 2}), ({"iterations": "3e1"}, {"max_iterations": 30}),
    ({"position_refinement": True}, {"position_refinement": "both"}), ({"pupil_order": "3"}, {"pupil_order": 3}),
])
def test_the_api_and_a_config_read_an_option_alike(given, read, tmp_path):
    import cca_cli as cca

    options = {k: v for k, v in given.items() if k not in ("tau", "iterations")}
    section_keys = {k: v for k, v in given.items() if k in ("tau", "iterations")}
    config = parse_config({"reconstruct": {"engine": "momentum", "options": options, **section_keys}}, source="c.yaml")
    _, from_config = resolve("momentum", "simulation", config.reconstruct.given())
    _, from_api = resolve("momentum", "simulation", given)
    for key, value in read.items():
        assert getattr(from_config, key) == getattr(from_api, key) == value
        assert type(getattr(from_api, key)) is type(value)
    geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                               distance_m=50, field_width_m=12e-3, grid=3, overlap=0.61)
    images = cca.simulate(cca.resolution_chart(96, widths=(4, 2)).image, geometry, snr_db=None)
    result = cca.reconstruct(images, geometry, engine="momentum", **{**given, "iterations": 2})
    for key, value in read.items():
        if key != "max_iterations":
            assert result.options[key] == value


@pytest.mark.parametrize(("given", "message"), [
    ({"batch": 1.5}, "batch: must be a whole number \\(got 1.5\\)"), ({"tau": "-1"}, "tau must be ≥ 0"),
    ({"beta": 3}, r"beta must be in \(0, 2\)"), ({"cost": "l2"}, "cost: must be one of amplitude, poisson"),
    ({"batsh": 3}, "unknown option.*batsh.*accepted: .*batch"), ({"restart": "yes"}, "restart: expected true or false"),
])
def test_the_api_refuses_an_option_in_one_line_naming_it(given, message):
    import cca_cli as cca

    geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                               distance_m=50, field_width_m=12e-3, grid=3, overlap=0.61)
    images = cca.simulate(cca.resolution_chart(96, widths=(4, 2)).image, geometry, snr_db=None)
    with pytest.raises(ValueError, match=message) as caught:
        cca.reconstruct(images, geometry, engine="momentum", **given)
    assert "\n" not in str(caught.value)


def test_reading_a_config_that_names_an_engine_loads_no_numeric_code():
    import subprocess
    import sys

    code = ("import sys; from cca_cli.config.load import parse_config; "
            "parse_config({'reconstruct': {'engine': 'momentum', 'options': {'batch': 4}}}, source='c.yaml'); "
            "print(sorted(m for m in ('numba', 'pyfftw', 'cca_cli.engines.momentum', 'cca_cli.optics.fft') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
