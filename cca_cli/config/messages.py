"""Pieces of the one-line messages for pydantic validation errors (configs and manifests)."""

from __future__ import annotations

from pydantic import BaseModel

from cca_cli.values import error_message, shown_value

__all__ = ["model_in", "accepted_keys", "error_message", "shown_value"]


def model_in(annotation) -> type[BaseModel] | None:
    """The pydantic model inside an annotation such as ``X``, ``X | None`` or ``list[X] | None`` (else None)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()):
        found = model_in(arg)
        if found is not None:
            return found
    return None


def accepted_keys(model: type[BaseModel], loc: tuple) -> list[str]:
    """Keys of the (sub)model that an error location ``loc`` points into, in declaration order.

    List indices in ``loc`` are skipped; an empty list means the location is
    not inside a model.
    """
    current: type[BaseModel] | None = model
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        field = current.model_fields.get(str(part))
        current = model_in(field.annotation) if field is not None else None
        if current is None:
            return []
    return list(current.model_fields)
