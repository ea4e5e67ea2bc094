"""The base of every config section: frozen, unknown keys refused, finite numbers, values read strictly."""

from __future__ import annotations

from cca_cli.values import StrictModel

__all__ = ["Section"]


class Section(StrictModel):
    """Base of every section: frozen, unknown keys rejected, no inf/nan, booleans and numbers kept apart
    (:mod:`cca_cli.values`)."""
