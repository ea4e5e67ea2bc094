"""One cca run per folder, one writer per output: an exclusive lock file that a dead run leaves free to take over.

:func:`folder_lock` creates ``.cca-run.lock`` in the folder and holds an
exclusive ``flock`` on it for as long as the run lasts; :func:`output_lock`
does the same for one output of a one-stage command (``.recon.h5.cca-lock``
beside ``recon.h5``), so that the same command started twice does not run
twice. The kernel drops the
lock when the process ends, however it ends (kill -9 included), so a lock file
left behind by a dead run is simply taken over; a live run's lock is refused
with one line naming its process. Where ``fcntl`` is missing the lock file is
created exclusively and a lock whose process no longer exists is taken over.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import socket
from pathlib import Path
from typing import Iterator

from cca_cli.errors import OutputError, RunLockedError
from cca_cli.io.outputs import pid_alive

try:
    import fcntl
except ImportError:  # pragma: no cover - not on Linux/macOS
    fcntl = None

__all__ = ["LOCK_NAME", "folder_lock", "output_lock", "output_lock_path"]

#: Name of the lock file in a locked folder.
LOCK_NAME = ".cca-run.lock"


def _holder(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def _who(holder: dict) -> str:
    who = f"pid {holder.get('pid', '?')}"
    if holder.get("host") not in (None, "*", socket.gethostname()):
        who += f" on {holder['host']}"
    since = f", started {holder['started_utc']}" if holder.get("started_utc") else ""
    return who + since


def _locked_message(directory: Path, holder: dict) -> str:
    return (f"{directory}: another cca run ({_who(holder)}) is writing in this folder; wait for it to finish "
            f"or choose another output folder")


def _output_locked_message(output: Path, holder: dict) -> str:
    return (f"{output}: another cca command ({_who(holder)}) is writing it; wait for it to finish or choose "
            "another output")


def _record() -> str:
    return json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                       "started_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")})


@contextlib.contextmanager
def _flock(directory: Path, path: Path, locked=_locked_message) -> Iterator[None]:
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputError(f"{directory}: cannot create the lock file {path.name} ({exc.strerror}); "
                              "choose a folder you can write to") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise RunLockedError(locked(directory, _holder(path))) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the file was replaced or removed between open and flock: lock the current one
    try:
        os.ftruncate(fd, 0)
        os.write(fd, _record().encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)


@contextlib.contextmanager
def _exclusive_file(directory: Path, path: Path,
                    locked=_locked_message) -> Iterator[None]:  # pragma: no cover - without fcntl
    for _ in range(3):
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            holder = _holder(path)
            pid = holder.get("pid")
            foreign_host = holder.get("host") not in (None, "*", socket.gethostname())
            if foreign_host or not isinstance(pid, int) or pid_alive(pid):
                raise RunLockedError(locked(directory, holder)) from None
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            continue
        with os.fdopen(fd, "w") as handle:
            handle.write(_record())
        break
    else:
        raise RunLockedError(locked(directory, _holder(path)))
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)


#: How a lock is held here: ``flock`` where the system has it, else an exclusively created file.
_hold = _flock if fcntl is not None else _exclusive_file


@contextlib.contextmanager
def folder_lock(directory: str | Path) -> Iterator[Path]:
    """Hold the folder's run lock for the duration of the ``with`` block (the folder must exist).

    Raises
    ------
    RunLockedError
        Another live process holds the lock.
    OutputError
        The lock file cannot be created.
    """
    directory = Path(directory)
    path = directory / LOCK_NAME
    with _hold(directory, path):
        yield path


def output_lock_path(output: str | Path) -> Path:
    """The lock file of one output: ``.NAME.cca-lock`` in the output's folder."""
    output = Path(output)
    return output.parent / f".{output.name}.cca-lock"


@contextlib.contextmanager
def output_lock(output: str | Path) -> Iterator[Path]:
    """Hold one output's lock (:func:`output_lock_path`) for the duration of the ``with`` block.

    A one-stage command takes it before it writes ``output`` (and its checkpoint or temporaries), so the
    same command started again while the first runs is refused in one line, not run twice on one file.

    Raises
    ------
    RunLockedError
        Another live process holds the lock.
    OutputError
        The lock file cannot be created.
    """
    output = Path(output)
    path = output_lock_path(output)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)   # the output's folder, which its writer makes anyway
    except OSError as exc:
        raise OutputError(f"{output}: cannot create the folder {path.parent} ({exc.strerror}); choose another "
                          "output") from None
    with _hold(output, path, _output_locked_message):
        yield path
