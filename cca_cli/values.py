"""How values a user gives are read: numbers stay numbers, booleans stay booleans.

Configs, manifests and the Python API's keyword options all read values by
these rules. pydantic's lax mode reads ``true`` as the integer 1 and the string
``"no"`` as False. A value means what it says instead:

- a boolean key takes only ``true`` or ``false`` (YAML's unquoted ``yes``/``no``
  are booleans already); a string, a number or null is refused;
- a number key refuses ``true``/``false``;
- an integer key accepts an integral number written in any form (``10``,
  ``10.0``, ``1e1``, ``"1e1"``) and refuses a fractional one (``12.7``);
- number strings such as ``550e-9`` (strings to PyYAML) are read as numbers;
- non-finite numbers (``.inf``, ``.nan``) are refused by the models
  (``allow_inf_nan=False``).

:func:`read_value` applies these rules to one value given its annotation, and
walks into lists, tuples and unions. :class:`StrictModel` is the pydantic base
that applies them to every field (config sections, engine options), and
:func:`validation_message` turns a validation error into one line naming the
key.
"""

from __future__ import annotations

import math
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union

from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator

from cca_cli.errors import short

__all__ = ["read_value", "StrictModel", "error_message", "validation_message"]


def _flat(annotation) -> list:
    """The alternatives of a union (or the annotation itself), with ``Annotated`` metadata stripped."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _flat(typing.get_args(annotation)[0])
    if origin in (Union, types.UnionType):
        out = []
        for arg in typing.get_args(annotation):
            out += _flat(arg)
        return out
    return [annotation]


def _accepts(options: list, kind: type) -> bool:
    for option in options:
        if option is Any or option is kind:
            return True
        if typing.get_origin(option) is Literal and any(type(v) is kind for v in typing.get_args(option)):
            return True
    return False


def _integral(text: str):
    try:
        number = float(text)
    except ValueError:
        return text
    return int(number) if math.isfinite(number) and number == int(number) else text


def read_value(annotation, value):
    """``value`` checked against ``annotation`` by the rules of this module (possibly converted).

    Raises
    ------
    ValueError
        A boolean where a number or text is wanted, or anything but a boolean where one is wanted.
    """
    options = _flat(annotation)
    if any(option is Any for option in options) or value is None:
        return value
    if isinstance(value, bool):
        if _accepts(options, bool):
            return value
        if _accepts(options, int) or _accepts(options, float):
            raise ValueError(f"expected a number, got {str(value).lower()}")
        if _accepts(options, str) or Path in options:
            raise ValueError(f"expected text, got {str(value).lower()}")
        return value
    if options and all(option is bool for option in options if option is not type(None)):
        raise ValueError(f"expected true or false, got {value!r}")
    if (isinstance(value, (int, float)) and not (_accepts(options, int) or _accepts(options, float))
            and _accepts(options, str) and _accepts(options, bool)):
        raise ValueError(f"expected text or true/false, got {value!r}")
    if isinstance(value, (str, float)) and _accepts(options, int) and not _accepts(options, float) \
            and not _accepts(options, str):
        if isinstance(value, str):
            return _integral(value)
        return int(value) if value.is_integer() else value
    if isinstance(value, (list, tuple)):
        for option in options:
            origin = typing.get_origin(option)
            args = typing.get_args(option)
            if origin is list and args:
                return [read_value(args[0], v) for v in value]
            if origin is tuple and args:
                if len(args) == 2 and args[1] is Ellipsis:
                    return [read_value(args[0], v) for v in value]
                if len(args) == len(value):
                    return [read_value(a, v) for a, v in zip(args, value)]
    return value


class StrictModel(BaseModel):
    """Frozen, unknown keys refused, no inf/nan, every value read by :func:`read_value`."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _read_value(cls, value, info: ValidationInfo):
        field = cls.model_fields.get(info.field_name)
        return value if field is None else read_value(field.annotation, value)


def error_message(error: dict) -> str:
    """The message of one pydantic error, without pydantic's ``Value error,`` prefix.

    pydantic's ``Input should be …`` reads ``must be …``; a bound on a key named for its unit (``…_m``,
    ``…_s``, ``…_mm``) says the unit too.
    """
    text = error["msg"].removeprefix("Value error, ")
    if error["type"] in _PLAIN:
        return _PLAIN[error["type"]]
    if text.startswith("Input should be "):
        text = "must be " + text.removeprefix("Input should be ")
        if error["type"] in _BOUNDS and error.get("loc"):
            text += _unit_hint(str(error["loc"][-1]))
    return text


def shown_value(value) -> str:
    """A value given, for a message: a number that YAML read as text (``-550e-9``) is shown as the number."""
    if isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            return short(value)
        return value.strip() if math.isfinite(number) else short(value)
    return short(value)


#: pydantic's messages for a number that is not one, in the project's words.
_PLAIN = {"int_from_float": "must be a whole number", "int_parsing": "must be a whole number",
          "float_parsing": "must be a number"}


_BOUNDS = ("greater_than", "greater_than_equal", "less_than", "less_than_equal")
_UNITS = (("_mm", "millimetres"), ("_um", "micrometres"), ("_nm", "nanometres"), ("_m", "metres"), ("_s", "seconds"))


def _unit_hint(name: str) -> str:
    """`` (in metres)`` for a key named ``…_m``, and so on."""
    for suffix, unit in _UNITS:
        if name.endswith(suffix):
            return f" (in {unit})"
    return ""


def validation_message(exc: ValidationError, *, prefix: str = "", accepted: list[str] | None = None) -> str:
    """One line for a validation error: the key (after ``prefix``), what is wrong and the value given.

    An unknown key lists the ``accepted`` ones (default: none listed).
    """
    errors = exc.errors()
    error = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    key = prefix + ".".join(short(p, 40) if not isinstance(p, str) or len(p) > 40 else p for p in error["loc"])
    if error["type"] == "extra_forbidden":
        listed = f"; accepted: {', '.join(accepted)}" if accepted else ""
        return f"unknown key {key}{listed}"
    if error["type"] == "literal_error":
        choices = str(error.get("ctx", {}).get("expected", "")).replace("'", "").replace(" or ", ", ")
        return f"{key}: must be one of {choices} (got {short(error.get('input'))})"
    shown = "input" in error and not isinstance(error["input"], dict) and error["type"] != "value_error"
    got = f" (got {shown_value(error['input'])})" if shown else ""
    return f"{key}: {error_message(error)}{got}" if key != prefix else f"{prefix}{error_message(error)}{got}"
