"""Errors that reach the user as one line.

Every error the pipeline raises on purpose derives from :class:`CcaError`.
The command layer prints ``str(error)`` on one line and exits with
:attr:`CcaError.exit_code`; nothing else in the package prints.
"""

from __future__ import annotations

__all__ = [
    "short",
    "CcaError",
    "ConfigError",
    "InputError",
    "OutputError",
    "OutputExistsError",
    "ResourceError",
    "RunLockedError",
    "CheckerboardNotFound",
]


def short(value, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters: how messages quote what the user wrote."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


class CcaError(Exception):
    """Base class of every expected, user-facing failure.

    The message must fit on one line and say what is wrong, where (file or
    key), and how to fix it.
    """

    exit_code = 1


class ConfigError(CcaError):
    """A configuration file or value is wrong (unknown key, wrong type, bad value)."""

    exit_code = 2


class InputError(CcaError):
    """An input file is missing, unreadable, corrupt or of the wrong shape or content."""

    exit_code = 3


class OutputError(CcaError):
    """An output cannot be written where asked: over an input, over what cca did not write, in a file or an
    unwritable folder."""

    exit_code = 4


class OutputExistsError(OutputError):
    """An output already exists and ``--force`` was not given."""


class ResourceError(CcaError):
    """The machine cannot hold the run: not enough memory or disk space (estimated, or met while writing)."""

    exit_code = 5


class RunLockedError(CcaError):
    """Another cca run is writing in the same folder."""

    exit_code = 6


class CheckerboardNotFound(InputError):
    """The registration checkerboard was not found in a view.

    Parameters
    ----------
    source : str
        File name or view label in which the board was searched for.
    pattern : tuple of int
        Inner-corner pattern ``(columns, rows)`` that was searched for.
    """

    def __init__(self, source: str, pattern: tuple[int, int]):
        self.source = source
        self.pattern = tuple(pattern)
        super().__init__(
            f"{source}: no {pattern[0]}x{pattern[1]} checkerboard (inner corners) found; "
            "check the pattern size in the manifest, the lighting, or allow dropping views "
            "with registration.drop_missing: true (cca register --drop-missing)"
        )
