"""Engines by the names used in configs and on the command line."""

from __future__ import annotations

from dataclasses import dataclass, fields

from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions
from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum

__all__ = ["EngineEntry", "ENGINES", "get_engine", "engine_names"]


@dataclass(frozen=True)
class EngineEntry:
    """An engine class and its options class."""

    engine: type
    options: type

    def option_names(self) -> list[str]:
        """Names of the options the engine accepts."""
        return [f.name for f in fields(self.options)]


ENGINES: dict[str, EngineEntry] = {
    "altmin": EngineEntry(AlternatingMinimization, AltMinOptions),
    "momentum": EngineEntry(SequentialMomentum, MomentumOptions),
}


def engine_names() -> list[str]:
    """Registered engine names, sorted."""
    return sorted(ENGINES)


def get_engine(name: str) -> EngineEntry:
    """Look up an engine by name.

    Raises
    ------
    KeyError
        With a message listing the valid names.
    """
    try:
        return ENGINES[name]
    except KeyError:
        raise KeyError(f"{name!r} is not an engine; choose one of {', '.join(engine_names())}") from None
