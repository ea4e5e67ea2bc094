"""`cca` with hooks that make a fault happen at a chosen moment (run as a script by test_faults.py).

- ``CCA_TEST_PAUSE_BEFORE_RENAME=<name>``: when the output ``<name>`` (``recon.h5``, ``report`` …) is
  complete in its temporary file, sleep instead of renaming it into place, so that the test can kill
  the process while the temporary exists.
- ``CCA_TEST_NO_DISK_CHECK=1``: skip the free-space estimate, so that a write meets a full disk
  (as when another process fills it after the check).
- ``CCA_TEST_MARK_ITERATING=<file>``: create ``<file>`` once the reconstruction's first iteration is done.
- ``CCA_TEST_MARK_SIMULATING=<file>``: create ``<file>`` when a simulation starts computing.
- ``CCA_TEST_WAIT_AT=<moment>:<file>``: at a moment of the report stage, create ``<file>`` and wait (up to
  60 s) for a signal. Moments: ``report-start`` (the stage begins), ``figure-in-gc`` (a weakref callback
  runs as the first figure is saved, as a garbage collection would run one: Python drops an exception
  raised there), ``report-complete`` (the report is complete in its temporary folder), ``report-renamed``
  (the report folder was just renamed into place), ``stage-done-in-gc`` (a weakref callback after the
  stage returned, before the runner's bookkeeping).
"""

from __future__ import annotations

import os
import sys
import time
import weakref


def _waiter(mark: str):
    def wait() -> None:  # once: the signal comes once
        if os.path.exists(mark):
            return
        open(mark, "w").close()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            time.sleep(0.01)
    return wait


def _in_a_weakref_callback(wait) -> None:
    class Token:
        pass

    token = Token()
    ref = weakref.ref(token, lambda _: wait())  # noqa: F841 - the callback runs only while the ref lives
    del token


def _wait_at(moment: str, mark: str) -> None:
    from cca_cli.io import outputs
    from cca_cli.report import figures
    from cca_cli.stages import runner

    wait = _waiter(mark)
    run_report = runner.RUNS["report"]

    def report(*args, **kwargs):
        if moment == "report-start":
            wait()
        result = run_report(*args, **kwargs)
        if moment == "stage-done-in-gc":
            _in_a_weakref_callback(wait)
        return result

    runner.RUNS["report"] = report
    save = figures._save

    def saved(*args, **kwargs):
        if moment == "figure-in-gc":
            _in_a_weakref_callback(wait)
        return save(*args, **kwargs)

    figures._save = saved
    replace = outputs._replace

    def replaced(tmp, path):
        if path.name == "report" and moment == "report-complete":
            wait()
        replace(tmp, path)
        if path.name == "report" and moment == "report-renamed":
            wait()

    outputs._replace = replaced


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
        from cca_cli.library import recovery

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
    if os.environ.get("CCA_TEST_WAIT_AT"):
        _wait_at(*os.environ["CCA_TEST_WAIT_AT"].split(":", 1))
    if os.environ.get("CCA_TEST_NO_DISK_CHECK"):
        from cca_cli.stages import footprint

        footprint._free_disk = lambda path: float("inf")


if __name__ == "__main__":
    install()
    from cca_cli.commands.app import app

    sys.argv[0] = "cca"
    app()
