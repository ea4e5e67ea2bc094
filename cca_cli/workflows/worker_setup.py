"""Set-up of each worker process of cca's local Dask cluster (the ``preload`` of
:func:`~cca_cli.workflows.cluster.open_client`).

Ctrl-C in a terminal reaches every process of the command's process group, the
local workers included. The ``cca`` process handles it (it stops the cluster and
says what was kept); a worker that took it as well printed Dask's tracebacks of
its own interrupted event loop. So a local worker ignores SIGINT and ends when
the cluster closes it.
"""

from __future__ import annotations

import signal
import threading

__all__ = ["dask_setup"]


def dask_setup(worker) -> None:
    """Ignore SIGINT in this worker process (called by Dask as the worker starts)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
