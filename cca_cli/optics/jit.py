"""Whether and where numba caches compiled kernels on disk, decided once per process.

numba keeps compiled kernels in the ``__pycache__`` folder beside their
module, in ``NUMBA_CACHE_DIR`` or in the user's cache folder, the first of
them it can write. Where it can write none of them (a read-only install in a
container, a shared lab workstation whose home is read-only), ``cache=True``
raises at import ("no locator available"). The cache then goes to a private
folder in the temporary directory (``cca-numba-<uid>``: created with mode
0700, and used only when it is a real folder of this user that no one else
may write, since numba loads compiled code from it), so later runs still
start at once; failing that, the kernels are compiled without a cache in
every process (about 20 s of one core on a 2-core machine). One note says which.

Every numba kernel of the package lives in this folder (``cca_cli/optics``),
so one probe function here answers for all of them.

numba's first compile or load in a process also sets up its BLAS support, which
imports ``scipy.linalg`` (about 0.2 s); no kernel of cca calls BLAS. In the ``cca``
command, a process that runs only cca's code
(:func:`~cca_cli.optics.hidden_imports.running_the_command`), the kernels' first
load (:func:`first_load`) hides ``scipy.linalg`` from numba. A library caller's
process is left as it is: its own numba code may need BLAS.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import stat
import sys
import tempfile

from cca_cli.optics.hidden_imports import hidden_in_this_thread, is_the_command

__all__ = ["cache_enabled", "first_load"]


@contextlib.contextmanager
def first_load():
    """The block in which the kernels are first loaded: ``scipy.linalg`` hidden in the ``cca`` command.

    numba sets up its BLAS support once per process, with its first compile or load, and then never
    again; hiding it is only done before that.
    """
    if is_the_command() and "numba.np.arraymath" not in sys.modules:
        with hidden_in_this_thread(("scipy.linalg",)):
            yield
    else:
        yield

_log = logging.getLogger(__name__)


def _probe():  # pragma: no cover - never called, only decorated
    return None


def _can_cache(numba) -> bool:
    """Whether numba finds a writable cache folder for this module (it compiles nothing to find out)."""
    try:
        numba.njit(cache=True)(_probe)
    except RuntimeError as exc:  # numba's "cannot cache function …: no locator available"
        _log.debug("numba cache unavailable: %s", exc)
        return False
    return True


def _private_folder() -> str | None:
    """``<temp>/cca-numba-<uid>``, created if needed; None unless it is this user's own folder, closed to others."""
    uid = os.getuid() if hasattr(os, "getuid") else None
    folder = os.path.join(tempfile.gettempdir(), f"cca-numba-{uid if uid is not None else 'user'}")
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        info = os.lstat(folder)
        if not stat.S_ISDIR(info.st_mode) or (uid is not None and info.st_uid != uid) or info.st_mode & 0o022:
            return None
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return None
    return folder


@functools.cache
def cache_enabled() -> bool:
    """Whether ``numba.njit(cache=True)`` works for this package's kernels.

    Found once per process. When numba can write none of its own cache
    folders, it is pointed at a private folder in the temporary directory
    (``NUMBA_CACHE_DIR`` is set for this process and its children); one
    ``note:`` line says so, or that the kernels are compiled in every run.

    Returns
    -------
    bool
        True when numba has a writable cache folder.
    """
    import numba

    if _can_cache(numba):
        return True
    package = os.path.dirname(os.path.abspath(__file__))
    folder = _private_folder()
    if folder is not None:
        given = os.environ.get("NUMBA_CACHE_DIR"), numba.config.CACHE_DIR
        os.environ["NUMBA_CACHE_DIR"] = folder  # numba re-reads its settings from the environment now and then
        numba.config.CACHE_DIR = folder
        if _can_cache(numba):
            _log.warning("note: numba cannot write its cache in %s/__pycache__ or the user's cache folder; compiled "
                         "kernels are kept in %s instead (set NUMBA_CACHE_DIR to choose the folder)", package, folder)
            return True
        if given[0] is None:
            del os.environ["NUMBA_CACHE_DIR"]
        else:
            os.environ["NUMBA_CACHE_DIR"] = given[0]
        numba.config.CACHE_DIR = given[1]
    _log.warning("note: numba can write no cache folder (%s/__pycache__, NUMBA_CACHE_DIR, the user's cache folder, "
                 "the temporary directory): the kernels are compiled in every run (about 20 s of one core on a 2-core machine); set "
                 "NUMBA_CACHE_DIR to a writable folder to keep them", package)
    return False
