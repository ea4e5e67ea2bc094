"""How config values are read (booleans, integers, finite numbers) and engine options derived from dataclasses."""

from dataclasses import dataclass

import numpy as np
import pytest
from pydantic import ValidationError

from cca_cli.config.load import parse_config
from cca_cli.config.model import ReconstructSection
from cca_cli.config.options import options_model
from cca_cli.config.values import read_value
from cca_cli.engines.registry import ENGINES, EngineEntry
from cca_cli.errors import ConfigError


@pytest.mark.parametrize(("annotation", "value", "expected"), [
    (int, 10, 10), (int, "1e1", 10), (int, 12.7, 12.7), (float, "550e-9", "550e-9"), (bool, False, False),
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


@dataclass(frozen=True)
class FutureOptions:
    """An engine's options with fields no code in config knows about."""

    tau: float = 1e-3
    max_iterations: int = 10
    tol: float = 0.0
    window: int = 3
    adaptive: bool = False
    weights: tuple[float, ...] = (1.0,)
    mode: str = "fast"
    cap: int | None = None
    start: np.ndarray | None = None

    def __post_init__(self):
        if self.window < 1:
            raise ValueError(f"window must be ≥ 1, got {self.window}")


def test_a_new_option_field_needs_no_config_code(monkeypatch):
    monkeypatch.setitem(ENGINES, "future", EngineEntry(ENGINES["altmin"].engine, FutureOptions))
    options_model.cache_clear()
    section = ReconstructSection(engine="future", options={"window": "5e0", "adaptive": True, "weights": [1, "2"],
                                                           "cap": 4.0})
    assert section.options == {"window": 5, "adaptive": True, "weights": (1.0, 2.0), "cap": 4}
    for options, message in (({"window": 2.5}, "window: Input should be a valid integer"),
                             ({"adaptive": "no"}, "adaptive: expected true or false"),
                             ({"window": 0}, "window must be ≥ 1"),
                             ({"mode": True}, "mode: expected text"),
                             ({"tau": 1}, "tau is not an option: set it as reconstruct.tau"),
                             ({"windw": 3}, "accepted: window, adaptive, weights, mode, cap, start")):
        with pytest.raises(ValidationError, match=message):
            ReconstructSection(engine="future", options=options)
    options_model.cache_clear()


def test_the_real_engines_options_models_match_their_dataclasses():
    from dataclasses import fields

    for name, entry in ENGINES.items():
        model = options_model(entry.options)
        assert set(model.model_fields) == {f.name for f in fields(entry.options)} - {"tau", "max_iterations", "tol"}
        defaults = entry.options()
        for key, field in model.model_fields.items():
            default = getattr(defaults, key)
            if isinstance(default, (bool, int, float, str, tuple, type(None))):
                assert field.default == default, (name, key)
