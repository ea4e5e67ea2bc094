"""Errors that reach the user as one line.

Every error the pipeline raises on purpose derives from :class:`CcaError`.
The command layer prints ``str(error)`` on one line and exits with
:attr:`CcaError.exit_code`; nothing else in the package prints.

Ctrl-C is a ``KeyboardInterrupt``, which Python drops when it is raised while a
weakref callback, a ``__del__`` method or a garbage collection runs (matplotlib
and h5py run many). Inside :func:`noting_interrupts` every Ctrl-C is noted as
well, and :func:`check_interrupt` raises it again where it matters: before an
output is put in place and before a command reports success.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Iterator

__all__ = [
    "check_interrupt",
    "ctrl_c_pressed",
    "noting_interrupts",
    "keeping_what_finished",
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


_interrupted = False
_pressed = False   # Ctrl-C came in this command, handled or not (:func:`keeping_what_finished` resets the other)


def ctrl_c_pressed() -> bool:
    """Whether Ctrl-C was pressed inside the present :func:`noting_interrupts` block, even if handled since."""
    return _pressed


def check_interrupt() -> None:
    """Raise ``KeyboardInterrupt`` if Ctrl-C was pressed inside :func:`noting_interrupts` (even if its exception
    was dropped)."""
    if _interrupted:
        raise KeyboardInterrupt


def _on_sigint(signum, frame) -> None:
    global _interrupted, _pressed
    _interrupted = _pressed = True
    raise KeyboardInterrupt


@contextlib.contextmanager
def noting_interrupts() -> Iterator[None]:
    """Note every Ctrl-C (SIGINT) in the enclosed block for :func:`check_interrupt`.

    A ``KeyboardInterrupt`` that Python drops is not printed either ("Exception ignored in …"): it is
    raised again by the next :func:`check_interrupt`. Where SIGINT has a handler other than Python's
    own (or is ignored), or outside the main thread, nothing changes.
    """
    global _interrupted, _pressed
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    previous_hook = sys.unraisablehook

    def unraisable(info) -> None:
        if not (_interrupted and issubclass(info.exc_type, KeyboardInterrupt)):
            previous_hook(info)

    _interrupted = _pressed = False
    signal.signal(signal.SIGINT, _on_sigint)
    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.unraisablehook = previous_hook
        _interrupted = _pressed = False


@contextlib.contextmanager
def keeping_what_finished() -> Iterator[None]:
    """Inside ``except KeyboardInterrupt``: write what the interrupted work had finished (a sweep's table).

    The Ctrl-C being handled no longer stops an output from being put in place (:func:`check_interrupt`); a
    new one does. Afterwards the command still ends as interrupted.
    """
    global _interrupted
    was = _interrupted
    _interrupted = False
    try:
        yield
    finally:
        _interrupted = _interrupted or was


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
    """Another cca run is writing in the same folder, or another cca command the same output."""

    exit_code = 6


class CheckerboardNotFound(InputError):
    """The registration checkerboard was not found in a view.

    Parameters
    ----------
    source : str
        File name or view label in which the board was searched for.
    pattern : tuple of int
        Inner-corner pattern ``(columns, rows)`` that was searched for.
    reference : bool
        The view is the one every other is registered to (dropping views cannot help then).
    """

    def __init__(self, source: str, pattern: tuple[int, int], *, reference: bool = False):
        self.source = source
        self.pattern = tuple(pattern)
        if reference:   # every other view is registered to this one: dropping views cannot help
            advice = ("the reference (centre) view needs the board: check the pattern size in the manifest or the "
                      "lighting, or leave register out of run.stages (hdr, then reconstruct) when the views are "
                      "aligned already")
        else:
            advice = ("check the pattern size in the manifest, the lighting, or allow dropping views "
                      "with registration.drop_missing: true (cca register --drop-missing)")
        super().__init__(f"{source}: no {pattern[0]}x{pattern[1]} checkerboard (inner corners) found; {advice}")
