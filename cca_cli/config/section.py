"""The base of every config section: frozen, unknown keys refused, finite numbers, values read strictly."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, ValidationInfo, field_validator

from cca_cli.config.values import read_value

__all__ = ["Section"]


class Section(BaseModel):
    """Base of every section: frozen, unknown keys rejected, no inf/nan, booleans and numbers kept apart."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _read_value(cls, value, info: ValidationInfo):
        field = cls.model_fields.get(info.field_name)
        return value if field is None else read_value(field.annotation, value)
