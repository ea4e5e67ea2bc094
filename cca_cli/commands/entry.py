"""The `cca` console script: the command line, with Ctrl-C during start-up answered in one line too."""

from __future__ import annotations

import gc
import os
import sys

#: numpy's BLAS libraries and how many threads each uses unless told. cca's matrix products are small (a
#: local DFT, a few Zernike modes): threads of their own only wait for cores the engines' threads hold,
#: and OpenBLAS waits actively, which on a busy machine cost a run up to half a second.
_BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")


def main() -> None:
    """Import the command line (numpy, h5py, numba … take a moment) and run it."""
    if "OMP_NUM_THREADS" not in os.environ:   # a user's OpenMP setting reaches the BLAS as they meant it
        for name in _BLAS_THREADS:
            os.environ.setdefault(name, "1")   # before numpy loads its BLAS; a user's own setting is kept
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


#: Extension modules that count their objects still alive when the interpreter ends and print a warning
#: for each (nanobind's leak check): objects the collector was not let free would show up there.
_COUNTING_MODULES = ("OpenImageIO",)


def _skip_the_final_collection() -> None:
    """Spare the ending process the collector's passes over every object (about half a second with numpy,
    scipy and numba loaded); files and temporaries are closed by then. Not when a module that checks for
    leaks at exit is loaded: objects in reference cycles would stay uncollected and be reported."""
    if not any(name in sys.modules for name in _COUNTING_MODULES):
        gc.freeze()
