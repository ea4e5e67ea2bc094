"""Imports a third-party package makes for features cca never uses, left out while it loads.

Some packages import optional neighbours when they are installed: pyfftw its dask and scipy
interfaces, numba its BLAS support (``scipy.linalg``). Each costs a ``cca`` command a fraction
of a second. :func:`hidden_in_this_thread` makes those imports fail in the importing thread only,
while the package loads; the package then leaves the feature out, and every other thread, and this
one afterwards, imports them as usual.

The dask interface is left out in every process (cca never uses it, and dask's import is slow).
What a library caller's own code might use (pyfftw's scipy interfaces, numba's BLAS) is left out
only in the ``cca`` command (:func:`running_the_command`), a process that runs cca's code alone.
"""

from __future__ import annotations

import contextlib
import sys
import threading

__all__ = ["hidden_in_this_thread", "running_the_command", "is_the_command"]

_command = False


def running_the_command() -> None:
    """Say that this process is the ``cca`` command: its code is cca's alone (called before anything loads)."""
    global _command
    _command = True


def is_the_command() -> bool:
    """Whether :func:`running_the_command` was called in this process."""
    return _command


class _HiddenFromThread:
    """Makes the import of some packages (and their submodules) fail in one thread.

    A finder on ``sys.meta_path`` needs only ``find_spec`` (``importlib.abc`` would cost every command 15 ms).
    """

    def __init__(self, thread: int, names: tuple[str, ...]):
        self.thread = thread
        self.names = names

    def find_spec(self, name, path, target=None):
        if threading.get_ident() == self.thread and any(name == n or name.startswith(n + ".") for n in self.names):
            raise ModuleNotFoundError(f"{name} is hidden while another package loads", name=name)
        return None


@contextlib.contextmanager
def hidden_in_this_thread(names: tuple[str, ...]):
    """Inside the block, importing any of ``names`` (or a submodule) fails in this thread, unless loaded already.

    Parameters
    ----------
    names : tuple of str
        Top-level packages or subpackages (``"dask"``, ``"scipy.fftpack"``).
    """
    hidden = tuple(name for name in names if name not in sys.modules)
    if not hidden:
        yield
        return
    finder = _HiddenFromThread(threading.get_ident(), hidden)
    # The list is replaced, never changed in place: another thread may be walking it in an import.
    sys.meta_path = [finder, *sys.meta_path]
    try:
        yield
    finally:
        sys.meta_path = [f for f in sys.meta_path if f is not finder]
