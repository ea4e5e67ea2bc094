"""`cca` with hooks that make a fault happen at a chosen moment (run as a script by test_faults.py).

- ``CCA_TEST_PAUSE_BEFORE_RENAME=<name>``: when the output ``<name>`` (``recon.h5``, ``report`` …) is
  complete in its temporary file, sleep instead of renaming it into place, so that the test can kill
  the process while the temporary exists.
- ``CCA_TEST_NO_DISK_CHECK=1``: skip the free-space estimate, so that a write meets a full disk
  (as when another process fills it after the check).
- ``CCA_TEST_MARK_ITERATING=<file>``: create ``<file>`` once the reconstruction's first iteration is done.
- ``CCA_TEST_MARK_SIMULATING=<file>``: create ``<file>`` when a simulation starts computing.
"""

from __future__ import annotations

import os
import sys
import time


def install() -> None:
    pause = os.environ.get("CCA_TEST_PAUSE_BEFORE_RENAME")
    if pause:
        from cca_cli.io import outputs

        replace = outputs._replace

        def paused(tmp, path):
            if path.name == pause:
                time.sleep(600)
            return replace(tmp, path)

        outputs._replace = paused
    mark = os.environ.get("CCA_TEST_MARK_ITERATING")
    if mark:
        from cca_cli.workflows import recovery

        run_engine = recovery.run_engine

        def marked(engine, *, on_iteration=None, **kwargs):
            def report(record):
                if record.iteration == 1:
                    open(mark, "w").close()
                if on_iteration is not None:
                    on_iteration(record)
            return run_engine(engine, on_iteration=report, **kwargs)

        recovery.run_engine = marked
    simulating = os.environ.get("CCA_TEST_MARK_SIMULATING")
    if simulating:
        from cca_cli.stages import simulate

        compute = simulate.simulate

        def marked_simulate(*args, **kwargs):
            open(simulating, "w").close()
            return compute(*args, **kwargs)

        simulate.simulate = marked_simulate
    if os.environ.get("CCA_TEST_NO_DISK_CHECK"):
        from cca_cli.stages import footprint

        footprint._free_disk = lambda path: float("inf")


if __name__ == "__main__":
    install()
    from cca_cli.commands.app import app

    sys.argv[0] = "cca"
    app()
