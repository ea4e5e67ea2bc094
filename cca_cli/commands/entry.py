"""The `cca` console script: the command line, with Ctrl-C during start-up answered in one line too."""

from __future__ import annotations

import gc
import sys


def main() -> None:
    """Import the command line (numpy, h5py, numba … take a moment) and run it."""
    try:
        from cca_cli.commands.app import app
    except KeyboardInterrupt:
        sys.stderr.write("interrupted: nothing was done\n")
        sys.exit(130)
    try:
        app()
    finally:
        # The process ends here: spare it the collector's passes over every object at shutdown (about half
        # a second with numpy, scipy and numba loaded). Files and temporaries are closed by then.
        gc.freeze()
