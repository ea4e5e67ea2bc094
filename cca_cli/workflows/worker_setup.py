"""Set-up of each worker process of cca's local Dask cluster (the ``preload`` of
:func:`~cca_cli.workflows.cluster.open_client`).

Ctrl-C in a terminal reaches every process of the command's process group, the
local workers included. The ``cca`` process handles it (it stops the cluster and
says what was kept); a worker that took it as well printed Dask's tracebacks of
its own interrupted event loop. So a local worker ignores SIGINT and ends when
the cluster closes it.

A local worker is also marked as cca's own (:data:`LOCAL_WORKER`): where a machine
has several GPUs, cca's local workers spread over them
(:func:`~cca_cli.workflows.tiled.run_tile`), while the workers of an existing
cluster use the GPU their launcher gave them (dask-cuda: one per worker).
"""

from __future__ import annotations

import os
import signal
import threading

__all__ = ["LOCAL_WORKER", "dask_setup"]

#: Environment variable set in each worker process of cca's local cluster.
LOCAL_WORKER = "CCA_LOCAL_WORKER"


def dask_setup(worker) -> None:
    """Ignore SIGINT in this worker process and mark it as cca's own (called by Dask as the worker starts)."""
    os.environ[LOCAL_WORKER] = "1"
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
