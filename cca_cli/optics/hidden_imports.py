"""Imports a third-party package makes for features cca never uses, left out while it loads.

Some packages import optional neighbours when they are installed: pyfftw its dask and scipy
interfaces, numba its BLAS support (``scipy.linalg``). Each costs a ``cca`` command a fraction
of a second. :func:`hidden_in_this_thread` makes those imports fail in the importing thread only,
while the package loads; the package then leaves the feature out, and every other thread, and this
one afterwards, imports them as usual.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import sys
import threading

__all__ = ["hidden_in_this_thread"]


class _HiddenFromThread(importlib.abc.MetaPathFinder):
    """Makes the import of some packages (and their submodules) fail in one thread."""

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
    sys.meta_path.insert(0, finder)
    try:
        yield
    finally:
        sys.meta_path.remove(finder)
