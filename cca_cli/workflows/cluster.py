"""A Dask client for work spread over processes or machines: a local cluster by default, or a scheduler.

Sweeps (one pipeline per point) and tiled reconstructions (one tile per task)
run on ``dask.distributed``: a :class:`~distributed.LocalCluster` of
single-threaded worker processes on this machine, or the workers of an existing
scheduler given as ``--scheduler tcp://host:8786``. :func:`cluster_settings`
carries the command line's ``--workers`` / ``--scheduler`` to a stage that
opens a client deep inside a pipeline.
"""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from concurrent.futures import CancelledError
from dataclasses import dataclass
from typing import Any, Iterator

from cca_cli.errors import CcaError, ConfigError, ctrl_c_pressed

__all__ = ["open_client", "check_workers", "check_scheduler", "scheduler_timeout", "ClusterSettings",
           "cluster_settings", "use_cluster", "scheduler_gone", "scheduler_lost", "SchedulerLost"]

#: Loggers of dask.distributed: their messages (a lost scheduler logs tracebacks) would break the one-line rule.
_DASK_LOGGERS = ("distributed", "distributed.client", "distributed.nanny", "distributed.scheduler",
                 "distributed.worker", "distributed.core", "distributed.comm", "distributed.utils")


@dataclass(frozen=True)
class ClusterSettings:
    """Where Dask work runs: ``workers`` local processes (None: one per core), or the ``scheduler`` at an address."""

    workers: int | None = None
    scheduler: str | None = None


_settings = ClusterSettings()


def cluster_settings() -> ClusterSettings:
    """The settings of the innermost :func:`use_cluster` (local processes, one per core, by default)."""
    return _settings


@contextlib.contextmanager
def use_cluster(workers: int | None = None, scheduler: str | None = None) -> Iterator[ClusterSettings]:
    """Run the enclosed work's Dask tasks on ``workers`` local processes or at ``scheduler``."""
    global _settings
    check_workers(workers)
    previous, _settings = _settings, ClusterSettings(workers, scheduler)
    try:
        yield _settings
    finally:
        _settings = previous


def scheduler_gone() -> tuple[type[BaseException], ...]:
    """What a client raises once its scheduler is gone: its futures are cancelled, or its connection closed.

    distributed's ``FuturesCancelledError`` (recent versions) derives from
    ``concurrent.futures.CancelledError``, which older versions raise themselves.
    """
    from distributed.comm.core import CommClosedError

    return CancelledError, CommClosedError


class SchedulerLost(CcaError):
    """A run's Dask scheduler went away mid-run (exit 1, as a failed point or tile)."""


def scheduler_lost(what: str, kept: str) -> SchedulerLost:
    """The one-line error of ``what`` (``sweep``, ``reconstruct``) when its Dask scheduler went away mid-run.

    ``kept`` says what the finished tasks left behind (``the finished tiles are kept in recon.h5.tiles (3 of 4)``).
    """
    return SchedulerLost(f"{what}: lost the Dask scheduler (its tasks were cancelled); {kept}; start the scheduler again "
                    "(or run without --scheduler) and re-run to do only the rest")


def _quiet_dask_logs() -> None:
    for name in _DASK_LOGGERS:
        logging.getLogger(name).setLevel(logging.CRITICAL)


class _AfterCtrlC(logging.Filter):
    """Drops what the client's event loop logs once Ctrl-C was pressed: the loop is being torn down then,
    and its callbacks can fail on the way (distributed's ``sync`` cancels a call that has not started yet with
    a ``NameError``); the user asked to stop and is told what was kept."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not ctrl_c_pressed()


#: The logger of the event loop the Dask client runs its calls on (tornado's "Exception in callback").
_LOOP_LOGGER = "tornado.application"


@contextlib.contextmanager
def _quiet_loop_after_ctrl_c() -> Iterator[None]:
    after_ctrl_c = _AfterCtrlC()
    logger = logging.getLogger(_LOOP_LOGGER)
    logger.addFilter(after_ctrl_c)
    try:
        yield
    finally:
        logger.removeFilter(after_ctrl_c)


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    message = text[0] if text else ""
    return message if isinstance(exc, CcaError) else f"{type(exc).__name__}: {message}"


#: Module each local worker process loads as it starts: it leaves Ctrl-C to the ``cca`` process.
WORKER_SETUP = "cca_cli.workflows.worker_setup"


@contextlib.contextmanager
def open_client(*, workers: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A ``dask.distributed.Client``: a LocalCluster of ``workers`` single-threaded processes, or ``scheduler``.

    Parameters
    ----------
    workers : int, optional
        Worker processes of the local cluster; default one per core.
    scheduler : str, optional
        Address of an existing scheduler (``tcp://host:8786``); ``workers`` is then ignored.
    """
    with _quiet_loop_after_ctrl_c(), _client(workers=workers, scheduler=scheduler) as client:
        yield client


@contextlib.contextmanager
def _client(*, workers: int | None, scheduler: str | None) -> Iterator[Any]:
    from distributed import Client, LocalCluster

    _quiet_dask_logs()
    if scheduler:
        timeout = scheduler_timeout()
        check_scheduler(scheduler, timeout)
        try:
            client = Client(scheduler, timeout=f"{timeout}s")
        except (OSError, ValueError, TypeError) as exc:
            raise ConfigError(f"--scheduler {scheduler}: cannot connect ({_one_line(exc)}); check the address") \
                from None
        try:
            yield client
        finally:
            client.close()
        return
    from cca_cli.optics.fft import cpu_count

    check_workers(workers)
    n = workers or cpu_count()
    try:
        with warnings.catch_warnings():  # another cluster on this machine holds the usual HTTP port: no matter
            warnings.filterwarnings("ignore", message="Port .* is already in use", category=UserWarning)
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=logging.CRITICAL, preload=[WORKER_SETUP])
    except BaseException:  # Ctrl-C while the workers start: stop them now, not in distributed's exit hook
        _close_unstarted_clusters()
        raise
    try:
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        with contextlib.suppress(Exception):
            cluster.close()


def _close_unstarted_clusters() -> None:
    """Close clusters whose start was interrupted (their own exit hook would fail with a traceback)."""
    from distributed.deploy.spec import SpecCluster

    for cluster in list(SpecCluster._instances):
        with contextlib.suppress(BaseException):
            cluster.close(timeout=5)
        SpecCluster._instances.discard(cluster)


def check_workers(workers: int | None) -> None:
    """Refuse a worker count below 1, or far above the cores this machine has (each worker is a process)."""
    from cca_cli.optics.fft import cpu_count

    if workers is None:
        return
    if workers < 1:
        raise ConfigError(f"--workers {workers}: give at least 1 worker process (or leave it out: one per core)")
    most = 8 * cpu_count()
    if workers > most:
        raise ConfigError(f"--workers {workers}: this machine has {cpu_count()} cores; start at most {most} worker "
                          "processes (or use --scheduler for a cluster)")


def scheduler_timeout() -> float:
    """Seconds to wait for a Dask scheduler to answer: ``CCA_SCHEDULER_TIMEOUT`` or 20."""
    text = os.environ.get("CCA_SCHEDULER_TIMEOUT", "20")
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value < 3600:
        raise ConfigError(f"CCA_SCHEDULER_TIMEOUT={text!r}: give seconds, e.g. 20")
    return value


def check_scheduler(address: str, timeout: float) -> None:
    """Refuse an address that is not a Dask scheduler answering within ``timeout`` seconds (one line).

    A bare TCP connection is not enough: a dashboard or any other server
    accepts it and then never answers the scheduler's handshake, where
    ``distributed.Client`` would wait without end.
    """
    import asyncio

    from distributed.comm import connect

    async def identity() -> object:
        comm = await connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            await comm.close()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout))
    except (asyncio.TimeoutError, TimeoutError):
        raise ConfigError(f"--scheduler {address}: no Dask scheduler answered within {timeout:g} s "
                          "(CCA_SCHEDULER_TIMEOUT); check the address and port (8786 by default, not the dashboard's)") \
            from None
    except (OSError, ValueError, TypeError, EOFError) as exc:
        raise ConfigError(f"--scheduler {address}: cannot connect ({_one_line(exc)}); give tcp://host:port of a Dask "
                          "scheduler") from None
    except Exception as exc:  # a server that speaks another protocol garbles the handshake
        raise ConfigError(f"--scheduler {address}: not a Dask scheduler ({_one_line(exc)})") from None
    if not (isinstance(reply, dict) and reply.get("type") == "Scheduler"):
        raise ConfigError(f"--scheduler {address}: the server there is not a Dask scheduler")
