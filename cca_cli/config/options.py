"""Engine options as pydantic models derived from each engine's options dataclass.

``reconstruct.options`` is validated by the model of the engine that
``reconstruct.engine`` names. The model is built from the dataclass that the
engine registry lists (its fields, type hints and defaults), so an option
added to an engine needs no code here; the same rules as every other section
apply (unknown keys refused with the accepted ones listed, integers and
booleans strict, no inf/nan), and then the dataclass's own range checks run.
"""

from __future__ import annotations

import dataclasses
import functools
import typing

from pydantic import BaseModel, ConfigDict, ValidationError, create_model

from cca_cli.config.messages import error_message
from cca_cli.config.section import Section
from cca_cli.errors import short

__all__ = ["SECTION_KEYS", "options_model", "validate_options"]

#: Options given by reconstruct's own keys (tau, iterations, tol), not in ``options``.
SECTION_KEYS = {"tau": "tau", "max_iterations": "iterations", "tol": "tol"}


class _OptionsSection(Section):
    """Section rules, plus fields of any type an engine may use (arrays are checked with isinstance)."""

    model_config = ConfigDict(**Section.model_config, arbitrary_types_allowed=True)


@functools.lru_cache(maxsize=None)
def options_model(options_class: type) -> type[BaseModel]:
    """A frozen pydantic model with the fields of an engine's options dataclass (section keys left out).

    A field whose type hint cannot be resolved is taken as ``Any`` (the dataclass's own checks still run).
    """
    try:
        hints = typing.get_type_hints(options_class)
    except (NameError, TypeError):
        hints = {}
    fields = {}
    for f in dataclasses.fields(options_class):
        if f.name in SECTION_KEYS:
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = ...
        fields[f.name] = (hints.get(f.name, typing.Any), default)
    return create_model(f"{options_class.__name__}Model", __base__=_OptionsSection, **fields)


def validate_options(engine: str, options: dict, section: dict) -> dict:
    """The options of ``engine``, read and checked; ``section`` gives tau, max_iterations and tol.

    Returns
    -------
    dict
        The given keys with their values read (``"1e-1"`` → 0.1, ``12.0`` → 12).

    Raises
    ------
    ValueError
        One line naming the option and the accepted keys or values.
    """
    from cca_cli.engines.registry import ENGINES

    options_class = ENGINES[engine].options
    model = options_model(options_class)
    try:
        parsed = model.model_validate(options)
    except ValidationError as exc:
        errors = exc.errors()
        error = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
        key = ".".join(short(p, 40) if not isinstance(p, str) or len(p) > 40 else p for p in error["loc"])
        if error["type"] == "extra_forbidden":
            if key in SECTION_KEYS:
                raise ValueError(f"{key} is not an option: set it as reconstruct.{SECTION_KEYS[key]}") from None
            raise ValueError(f"unknown option {key} for engine {engine}; accepted: "
                             f"{', '.join(model.model_fields) or 'none'}") from None
        got = "" if error["type"] == "value_error" else f" (got {short(error.get('input'))})"
        raise ValueError(f"{key}: {error_message(error)}{got}") from None
    given = {key: getattr(parsed, key) for key in options}
    try:
        options_class(**section, **given)
    except (TypeError, ValueError) as exc:
        raise ValueError(str(exc)) from None
    return given
