"""Where an output may be written, and writing it so that nothing is lost.

Rules, checked by :func:`check_output` before any work starts:

- an output is never an input, never holds an input, and is never the current
  folder or one that holds it;
- an existing output is replaced only with ``force``, and only when cca wrote
  it: an HDF5 file with a ``cca_schema`` attribute, a folder with cca's marker
  file listing everything in it (:data:`MARKER`), or a text file its writer
  recognises (``owned``);
- the folder it goes into can be written (a probe file is created and removed),
  and no parent on the way is a file.

:func:`atomic_path` then writes to a temporary sibling ``.<name>.tmp-<pid>``
and renames it into place; on any failure (a full disk included) the
temporary is removed and the previous version is kept. Temporaries left by a
killed process are removed by later writes of the same output
(:func:`remove_stale_temporaries`), and only cca's own temporary names of
processes that no longer run.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
from pathlib import Path
from typing import Callable, Iterable, Iterator

from cca_cli.errors import OutputError, OutputExistsError, ResourceError, check_interrupt

__all__ = ["disk_usage", 
    "MARKER",
    "KNOWN_OUTPUTS",
    "Owned",
    "temporary_path",
    "is_cca_hdf5",
    "starts_with",
    "foreign_part",
    "folder_complete",
    "write_marker",
    "check_output",
    "prepare_folder",
    "check_folder",
    "remove_stale_temporaries",
    "atomic_path",
    "disk_full",
    "pid_alive",
]

#: Marker file in every folder cca writes (report/): JSON with cca_schema, stage and the files it wrote.
MARKER = ".cca-output.json"
#: Output names whose stale temporaries later runs remove.
KNOWN_OUTPUTS = frozenset({"captures.h5", "raw.h5", "hdr.h5", "registered.h5", "recon.h5", "report", "point.json",
                           "sweep.csv", "sweep.h5", "figures", "cca-probe"})
_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?:tmp|old)-(?P<pid>\d+)$")
_DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)

#: A recogniser of a file cca wrote (for text outputs that carry no schema attribute).
Owned = Callable[[Path], bool]


def pid_alive(pid: int) -> bool:
    """Whether a process with this id exists on this machine."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:
        return True
    return True


def temporary_path(path: Path, kind: str = "tmp") -> Path:
    """``.<name>.tmp-<pid>`` beside ``path``: where this process writes ``path`` before renaming it."""
    return path.with_name(f".{path.name}.{kind}-{os.getpid()}")


def is_cca_hdf5(path: Path) -> bool:
    """Whether ``path`` is an HDF5 file cca wrote (readable, with a ``cca_schema`` attribute)."""
    import h5py

    try:
        if not h5py.is_hdf5(path):
            return False
        with h5py.File(path, "r") as handle:
            schema = handle.attrs.get("cca_schema")
    except (OSError, ValueError):
        return False
    schema = schema.decode(errors="replace") if isinstance(schema, bytes) else str(schema)
    return schema.startswith("cca/")


def starts_with(prefix: str) -> Owned:
    """A recogniser of text files whose first characters are ``prefix``."""
    def owned(path: Path) -> bool:
        try:
            with open(path, "rb") as handle:
                return handle.read(len(prefix.encode())) == prefix.encode()
        except OSError:
            return False
    return owned


def _marker_files(folder: Path) -> set[str] | None:
    """The files a folder's marker lists (None without a valid marker)."""
    try:
        data = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        data = None
    if isinstance(data, dict) and str(data.get("cca_schema", "")).startswith("cca/"):
        return {str(f) for f in data.get("files", [])}
    try:  # a report written before markers existed: report.json with cca provenance lists its figures
        report = json.loads((folder / "report.json").read_text())
    except (OSError, ValueError):
        return None
    if isinstance(report, dict) and str(report.get("provenance", {}).get("cca_schema", "")).startswith("cca/"):
        return {"report.json", *(str(f) for f in report.get("figures", []))}
    return None


def write_marker(folder: Path, stage: str) -> None:
    """Write :data:`MARKER` into ``folder``, listing every file now in it."""
    from cca_cli.io.schema import SCHEMA_VERSION

    files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())
    (folder / MARKER).write_text(json.dumps({"cca_schema": SCHEMA_VERSION, "stage": stage, "files": files}, indent=1))


def folder_complete(folder: Path) -> bool:
    """Whether a folder cca wrote still holds every file its marker lists."""
    listed = _marker_files(folder)
    return listed is not None and all((folder / name).is_file() for name in listed)


def foreign_part(path: Path, owned: Owned | None = None) -> str | None:
    """None when cca wrote ``path`` (and everything in it); else what in it cca did not write."""
    if path.is_dir() and not path.is_symlink():
        listed = _marker_files(path)
        if listed is None:
            return str(path)
        for entry in sorted(path.rglob("*")):
            rel = entry.relative_to(path).as_posix()
            if entry.is_dir() and not entry.is_symlink():
                continue
            if rel != MARKER and rel not in listed:
                return str(entry)
        return None
    if is_cca_hdf5(path) or (owned is not None and owned(path)):
        return None
    return str(path)


def _first_existing(path: Path) -> Path:
    here = path.absolute().parent
    while not os.path.lexists(here) and here != here.parent:
        here = here.parent
    return here


def _resolved(path: Path) -> Path:
    """The absolute path with links followed, as far as they lead (a link that loops is kept as it is, where
    ``Path.resolve`` raises on Python before 3.13)."""
    return Path(os.path.realpath(path))


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return _resolved(a) == _resolved(b)


def _inside(inner: Path, outer: Path) -> bool:
    try:
        _resolved(inner).relative_to(_resolved(outer))
        return True
    except ValueError:
        return False


def _probe(folder: Path, path: Path) -> None:
    probe = folder / f".cca-probe.tmp-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o600)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write in {folder} ({exc.strerror}); choose a folder you can write to") \
            from None


def check_output(path: str | Path, *, force: bool = False, kind: str = "file", inputs: Iterable = (),
                 owned: Owned | None = None, probe: bool = True) -> None:
    """Refuse an output path that would lose data or cannot be written (see the module notes).

    Parameters
    ----------
    path : path
        The output (a file, or a folder for ``kind="folder"``).
    force : bool
        Replace an existing output that cca wrote.
    kind : {"file", "folder"}
        What the output is.
    inputs : iterable of path
        Files the command reads: never written over or replaced.
    owned : callable, optional
        Recognises a text output cca wrote (HDF5 files and marked folders are recognised anyway).
    probe : bool
        Check that the folder can be written by creating and removing a probe file.

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``force`` is not set.
    OutputError
        Any other reason (input, not cca's, wrong kind, parent is a file, not writable).
    """
    path = Path(path)
    shown = str(path) if str(path) not in ("", ".") else "."
    here = Path.cwd()
    if kind == "folder" and (_inside(here, path)):
        raise OutputError(f"{shown}: is the current folder or holds it; give the {kind} a new name")
    for source in inputs:
        source = Path(source)
        if not os.path.lexists(source):
            continue
        if (os.path.lexists(path) and _same_file(path, source)) or _resolved(path) == _resolved(source):
            raise OutputError(f"{shown}: is the input {source}; write the output elsewhere (cca never writes "
                              "over its input)")
        if _inside(source, path):
            raise OutputError(f"{shown}: holds the input {source}; choose another output")
    folder = _first_existing(path)
    if not folder.is_dir():
        raise OutputError(f"{shown}: {folder} is a file, not a folder; choose another output path")
    if path.exists():
        if kind == "file" and path.is_dir():
            raise OutputError(f"{shown}: is a folder; give a file name for the output")
        if kind == "folder" and not path.is_dir():
            raise OutputError(f"{shown}: is a file, not a folder; give a new folder name for the output")
        foreign = foreign_part(path, owned)
        if not force:
            if foreign is not None and foreign == str(path):
                raise OutputExistsError(f"{shown}: already exists and was not written by cca; choose another output")
            raise OutputExistsError(f"{shown}: already exists; use --force (force=True in Python) to overwrite it or choose another output")
        if foreign is not None:
            what = "it" if foreign == str(path) else f"{foreign} in it"
            raise OutputError(f"{shown}: cca did not write {what} (or cannot read it), so --force does not replace "
                              "it; move it away or choose another output")
    if probe:
        _probe(folder, path)


def check_folder(directory: str | Path) -> None:
    """Refuse an output folder that is a file, lies under a file, or cannot be written (it need not exist)."""
    directory = Path(directory)
    if directory.exists():
        if not directory.is_dir():
            raise OutputError(f"{directory}: is a file, not a folder; choose another output folder")
        _probe(directory, directory)
        return
    folder = _first_existing(directory)
    if not folder.is_dir():
        raise OutputError(f"{directory}: {folder} is a file, not a folder; choose another output folder")
    _probe(folder, directory)


def prepare_folder(directory: Path) -> None:
    """Create a run folder, or refuse one that is a file or cannot be written (one line)."""
    check_folder(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{directory}: cannot create the folder ({exc.strerror}); choose another one") from None


def remove_stale_temporaries(directory: str | Path, names: Iterable[str] | None = None) -> list[Path]:
    """Remove ``.<name>.tmp-<pid>`` (and ``.old-<pid>``) entries of processes that no longer run.

    Parameters
    ----------
    directory : path
    names : iterable of str, optional
        Output names whose temporaries are removed; default :data:`KNOWN_OUTPUTS`.

    Returns
    -------
    list of Path
        What was removed.
    """
    directory = Path(directory)
    wanted = KNOWN_OUTPUTS if names is None else set(names) | {"cca-probe"}
    removed = []
    try:
        entries = list(directory.iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = _TEMPORARY.match(entry.name)
        if not match or match["name"] not in wanted:
            continue
        pid = int(match["pid"])
        if pid == os.getpid() or pid_alive(pid):
            continue
        _remove(entry)
        removed.append(entry)
    return removed


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def disk_full(exc: BaseException) -> bool:
    """Whether an error means the disk (or the file size limit or quota) is full."""
    if getattr(exc, "errno", None) in _DISK_FULL:
        return True
    text = str(exc)
    return any(mark in text for mark in ("No space left", "errno = 28", "Disk quota", "File too large",
                                         "errno = 27", "errno = 122"))


def _replace(tmp: Path, path: Path) -> None:
    if path.is_dir() and not path.is_symlink():  # os.replace cannot replace a non-empty folder: swap it
        old = temporary_path(path, "old")
        _remove(old)
        os.replace(path, old)
        try:
            os.replace(tmp, path)
        except BaseException:
            os.replace(old, path)
            raise
        _remove(old)
    else:
        os.replace(tmp, path)


@contextlib.contextmanager
def atomic_path(path: str | Path, *, force: bool = False, kind: str = "file", inputs: Iterable = (),
                owned: Owned | None = None) -> Iterator[Path]:
    """Yield a temporary sibling path; on success rename it onto ``path``.

    The caller creates a file (or, with ``kind="folder"``, a folder) at the
    temporary path. :func:`check_output` runs first. On any error (or Ctrl-C)
    the temporary is removed and ``path`` is untouched; a full disk becomes a
    one-line :class:`~cca_cli.errors.ResourceError`.
    """
    path = Path(path)
    check_output(path, force=force, kind=kind, inputs=inputs, owned=owned, probe=False)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{path}: cannot create its folder ({exc.strerror}); choose another output") from None
    remove_stale_temporaries(path.parent, {path.name})
    tmp = temporary_path(path)
    _remove(tmp)
    existed = path.exists()
    try:
        yield tmp
        check_interrupt()  # an output made while Ctrl-C was pressed is not put in place
        _replace(tmp, path)
    except (OSError, RuntimeError) as exc:  # HDF5 reports some failed writes as RuntimeError
        if disk_full(exc):
            kept = "the previous version is kept" if existed else "nothing was written"
            raise ResourceError(f"{path}: no space left on the device while writing it ({kept}); free some space "
                                "or write elsewhere") from None
        raise
    finally:
        _remove(tmp)


def disk_usage(path: Path) -> int:
    """Bytes a file, or the files under a folder, take (0 for what is missing)."""
    path = Path(path)
    if path.is_file():
        return path.stat().st_size
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())
    return 0
