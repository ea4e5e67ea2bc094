"""Which engine and options a reconstruct section resolves to for each kind of data."""

import pytest

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.presets import DATA_KINDS, engine_defaults, preset
from cca_cli.engines.registry import get_engine, resolve


def resolve_engine(section: ReconstructSection, kind: str):
    return resolve(section.engine, kind, section.given())


def test_auto_on_led_arrays_runs_momentum_with_pupil_recovery_and_growing_batches():
    name, options = resolve_engine(ReconstructSection(), "led_array")
    assert name == "momentum"
    assert options.pupil_recovery == "shared" and options.pupil_model == "full"
    assert options.batch_growth > 1 and options.plateau > 0 and options.max_iterations <= 300


def test_momentum_named_on_recorded_data_keeps_the_preset_unless_told_otherwise():
    name, options = resolve_engine(ReconstructSection(engine="momentum"), "led_array")
    assert (name, options) == resolve_engine(ReconstructSection(), "led_array")
    section = ReconstructSection(engine="momentum", iterations=40, options={"pupil_recovery": "none"})
    _, options = resolve_engine(section, "led_array")
    assert options.pupil_recovery == "none" and options.max_iterations == 40
    assert options.batch_growth == preset("led_array")[1]["batch_growth"]


@pytest.mark.parametrize("engine, kind", [("momentum", "simulation"), ("altmin", "led_array"),
                                          ("altmin", "camera_scan")])
def test_other_engines_and_simulations_keep_their_own_defaults(engine, kind):
    assert engine_defaults(engine, kind) == {}
    _, options = resolve_engine(ReconstructSection(engine=engine), kind)
    assert options == get_engine(engine).options()


def test_every_kind_has_a_preset_and_unknown_kinds_are_refused():
    assert all(preset(kind)[0] for kind in DATA_KINDS)
    with pytest.raises(ValueError, match="unknown kind of data"):
        preset("telescope")
