"""The `cca` console script: the command line, with Ctrl-C during start-up answered in one line too."""

from __future__ import annotations

import ctypes
import gc
import os
import sys

#: numpy's BLAS libraries and how many threads each uses unless told. cca's matrix products are small (a
#: local DFT, a few Zernike modes): threads of their own only wait for cores the engines' threads hold,
#: and OpenBLAS waits actively, which on a busy machine cost a run up to half a second.
_BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")

#: glibc's ``mallopt`` parameters (malloc.h) and the values the command sets: memory a run frees stays
#: with the process up to this size (instead of going back to the system and being mapped and zeroed
#: afresh for the next array), and arrays up to 32 MiB (glibc's largest such threshold) come from it.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_KEPT_BYTES, _HEAP_ARRAY_BYTES = 1 << 30, 32 << 20


def main() -> None:
    """Import the command line (numpy, h5py, numba … take a moment) and run it."""
    if "OMP_NUM_THREADS" not in os.environ:   # a user's OpenMP setting reaches the BLAS as they meant it
        for name in _BLAS_THREADS:
            os.environ.setdefault(name, "1")   # before numpy loads its BLAS; a user's own setting is kept
    keep_freed_memory()
    try:
        from cca_cli.optics import hidden_imports

        hidden_imports.running_the_command()  # cca's code alone: pyfftw and numba need not load scipy's parts
        from cca_cli.commands.app import app
    except KeyboardInterrupt:
        sys.stderr.write("interrupted: nothing was done\n")
        sys.exit(130)
    try:
        app()
    finally:
        _skip_the_final_collection()


def keep_freed_memory() -> bool:
    """Let glibc keep the memory a run frees for the arrays it makes next; returns whether it was set.

    A reconstruction makes and drops arrays of tens of MB (each visiting order's amplitudes and weights,
    pupil boxes, the fit report's); by default glibc maps each anew and returns it when freed, and the
    kernel zeroes every page again on first touch, which a virtual machine pays dearly for. Elsewhere
    than glibc (musl, macOS) nothing is changed; an explicit ``MALLOC_*`` or ``GLIBC_TUNABLES`` setting
    in the environment is kept. A notebook may call it too: it changes how memory is reused, not results.

    Returns
    -------
    bool
        True when glibc took both settings.
    """
    if not sys.platform.startswith("linux") or any(name.startswith(("MALLOC_", "GLIBC_TUNABLES"))
                                                   for name in os.environ):
        return False
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version   # glibc only: another libc's mallopt takes other parameters
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_TRIM_THRESHOLD, _KEPT_BYTES)) and bool(mallopt(_M_MMAP_THRESHOLD, _HEAP_ARRAY_BYTES))


#: Extension modules that count their objects still alive when the interpreter ends and print a warning
#: for each (nanobind's leak check): objects the collector was not let free would show up there.
_COUNTING_MODULES = ("OpenImageIO",)


def _skip_the_final_collection() -> None:
    """Spare the ending process the collector's passes over every object (about half a second with numpy,
    scipy and numba loaded); files and temporaries are closed by then. Not when a module that checks for
    leaks at exit is loaded: objects in reference cycles would stay uncollected and be reported."""
    if not any(name in sys.modules for name in _COUNTING_MODULES):
        gc.freeze()
