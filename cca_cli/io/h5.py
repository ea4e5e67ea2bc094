"""HDF5 files of the pipeline: atomic writes, provenance attributes, checked reads."""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from cca_cli.version import __version__
from cca_cli.errors import InputError, short
from cca_cli.io.outputs import atomic_path, check_output, remove_stale_temporaries
from cca_cli.io.schema import SCHEMA_VERSION, spec_for

__all__ = [
    "Provenance",
    "atomic_h5",
    "atomic_path",
    "check_input_file",
    "check_output",
    "missing_dataset",
    "unique_paths",
    "file_sha256",
    "open_input",
    "write_dataset",
    "describe",
    "read_provenance",
    "remove_temporaries",
    "require",
    "require_attr",
    "read_finite",
]


def file_sha256(path: str | Path, *, block: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(block):
            digest.update(chunk)
    return digest.hexdigest()


def unique_paths(paths) -> list:
    """``paths`` with each file once (compared resolved), in the order first given, as given."""
    first: dict[str, str | Path] = {}
    for p in paths:
        try:
            key = os.path.realpath(p)
        except (OSError, RuntimeError):   # a link that loops: its own name (the input check names the loop)
            key = os.path.abspath(p)
        first.setdefault(key, p)
    return list(first.values())


class Provenance(dict):
    """Root attributes every output carries: schema, stage, version, time, config, inputs."""

    @classmethod
    def make(cls, stage: str, config_yaml: str, config_hash: str, inputs: list[str | Path] = ()) -> "Provenance":
        """Provenance for a stage run now, hashing its input files (each once, in the order first given)."""
        inputs = unique_paths(inputs)
        for p in inputs:
            check_input_file(p)
        return cls(
            cca_schema=SCHEMA_VERSION,
            stage=stage,
            cca_version=__version__,
            created_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            config=config_yaml,
            config_hash=config_hash,
            inputs=json.dumps([{"path": str(p), "sha256": file_sha256(p)} for p in inputs]),
        )


def check_input_file(path: str | Path, *, listed_in: str | Path | None = None) -> Path:
    """``path`` as a Path if it is an existing regular file, else a one-line InputError.

    ``listed_in`` names the file (a manifest) that lists ``path``, for the message.
    """
    path = Path(path)
    if not path.exists():
        if path.is_symlink():
            named = f" (listed in {listed_in})" if listed_in is not None else ""
            raise InputError(f"{path}: is a symbolic link that leads nowhere{named}: it loops, or what it points to "
                             "is gone; fix the link or give the file itself")
        if listed_in is not None:
            raise InputError(f"{path}: listed in {listed_in} but not found; check the path there")
        raise InputError(f"{path}: input file not found; check the path or run the stage that writes it")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a file")
    if not path.is_file():
        raise InputError(f"{path}: is not a regular file (a pipe or device); give a file")
    return path


def remove_temporaries(directory: str | Path) -> None:
    """Remove what interrupted writes of dead processes left in ``directory`` (cca's own temporary names only)."""
    remove_stale_temporaries(directory)


class _DiskSink:
    """The file object HDF5 writes through: a write that fails (a full disk) is recorded, not passed on.

    HDF5 cannot recover from a failed write: closing such a file crashes the
    interpreter (a segmentation fault in H5Fclose, also at exit). Through this
    sink every write seems to succeed, so HDF5 always closes cleanly; the first
    error is kept in :attr:`error` and raised once the file is closed, and the
    temporary file, now incomplete, is discarded.
    """

    def __init__(self, path: Path):
        self._file = open(path, "w+b", buffering=0)
        self.error: OSError | None = None

    def write(self, data) -> int:
        if self.error is None:
            view = memoryview(data).cast("B")
            try:
                while view:
                    view = view[self._file.write(view):]
            except OSError as exc:
                self.error = exc
        return memoryview(data).nbytes

    def truncate(self, size=None):
        if self.error is None:
            try:
                return self._file.truncate(size)
            except OSError as exc:
                self.error = exc
        return size

    def read(self, size=-1) -> bytes:
        return self._file.read(size)

    def readinto(self, buffer) -> int:
        return self._file.readinto(buffer)

    def seek(self, offset, whence=0) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if not self._file.closed:
            try:
                self._file.close()
            except OSError as exc:
                self.error = self.error or exc


@contextlib.contextmanager
def atomic_h5(path: str | Path, provenance: Provenance, *, force: bool = False) -> Iterator[h5py.File]:
    """Open a new HDF5 file for writing that appears at ``path`` only when complete.

    A write that fails (a full disk) raises a one-line
    :class:`~cca_cli.errors.ResourceError` once the file is closed; the
    previous ``path`` is kept and the temporary file removed.
    """
    with atomic_path(path, force=force) as tmp:
        sink = _DiskSink(tmp)
        try:
            with h5py.File(sink, "w") as handle:
                for key, value in provenance.items():
                    handle.attrs[key] = value
                yield handle
        finally:
            sink.close()
        if sink.error is not None:
            raise sink.error


_CHUNK_SIDE = 512


def write_dataset(group: h5py.Group, path: str, data, *, units: str | None = None, description: str | None = None,
                  **attrs: Any) -> h5py.Dataset:
    """Write a dataset with its units and description (from the schema unless given).

    Text (a sequence of ``str``) is stored as UTF-8 strings.
    """
    data = np.asarray(data)
    if data.dtype.kind in "UO":
        data = np.array([str(v) for v in data.ravel()], dtype=object).reshape(data.shape)
        dtype = h5py.string_dtype("utf-8")
    else:
        dtype = None
    # Large image stacks are stored in image tiles of at most 512² px: a whole image reads as fast, and a tile
    # of a wide frame (a tiled reconstruction) reads only the chunks it overlaps.
    chunks = None
    if data.ndim == 3 and data.nbytes > (1 << 24):
        chunks = (1, min(data.shape[1], _CHUNK_SIDE), min(data.shape[2], _CHUNK_SIDE))
    dataset = group.create_dataset(path, data=data, dtype=dtype, chunks=chunks)
    describe(dataset, units=units, description=description)
    for key, value in attrs.items():
        dataset.attrs[key] = value
    return dataset


def describe(dataset: h5py.Dataset, *, units: str | None = None, description: str | None = None) -> h5py.Dataset:
    """Set a dataset's ``units`` and ``description`` attributes, from the schema unless given."""
    spec = spec_for(dataset.name)
    dataset.attrs["units"] = units if units is not None else (spec.units if spec else "")
    if description is not None or spec is not None:
        dataset.attrs["description"] = description if description is not None else spec.meaning
    return dataset


def open_input(path: str | Path, *, stage: str | None = None) -> h5py.File:
    """Open a pipeline HDF5 file for reading, with one-line errors.

    Parameters
    ----------
    path : path
        The file.
    stage : str, optional
        Required producing stage (``simulate``, ``reconstruct`` …) — checked
        against the file's ``stage`` attribute when given.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found; check the path or run the stage that writes it")
    check_input_file(path)
    if not h5py.is_hdf5(path):
        raise InputError(f"{path}: not an HDF5 file; give a file written by cca (captures.h5, recon.h5 …)")
    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: cannot open HDF5 file ({exc}); it may be truncated — re-run the stage") from None
    schema = handle.attrs.get("cca_schema")
    if schema != SCHEMA_VERSION:
        handle.close()
        if isinstance(schema, str) and schema.startswith("cca/"):
            raise InputError(f"{path}: written in schema {short(schema, 20)}, but this cca reads {SCHEMA_VERSION}; "
                             "use the cca version that wrote it")
        raise InputError(f"{path}: not a cca file (no cca_schema={SCHEMA_VERSION} attribute)")
    if stage is not None and stage not in str(handle.attrs.get("stage", "")).split(","):
        actual = handle.attrs.get("stage")
        handle.close()
        raise _wrong_stage(path, actual, stage)
    return handle


#: What to give a command that reads the output of ``stage``, by that stage.
_STAGE_OUTPUTS = {"reconstruct": "the recon.h5 that cca reconstruct writes",
                  "ingest": "the raw.h5 that cca ingest writes (exposure brackets, /raw/frames)"}

#: Stages whose files hold captures: what cca reconstruct reads.
_CAPTURE_STAGES = ("simulate", "ingest", "hdr", "register", "api")


def _wrong_stage(path: str | Path, actual: object, stage: str) -> InputError:
    """The one-line error for a file of stage ``actual`` given where one of ``stage`` is read, naming the fix.

    Parameters
    ----------
    path : path
        The file given.
    actual : object
        Its ``stage`` attribute (None when it has none).
    stage : str
        The stage whose output the command reads.
    """
    wanted = _STAGE_OUTPUTS.get(stage, f"a file that cca {stage} writes")
    fix = f"give {wanted}"
    if stage == "reconstruct" and str(actual) in _CAPTURE_STAGES:
        fix += "; this file holds captures, so run cca reconstruct on it first"
    return InputError(f"{path}: written by stage {actual!r}, expected {stage!r}; {fix}")


def missing_dataset(handle: h5py.File, path: str) -> InputError:
    """The one-line error for a dataset ``path`` the open file lacks (exposure brackets not yet merged named so)."""
    if path.startswith("/measurements") and "/raw/frames" in handle:
        return InputError(f"{handle.filename}: exposure brackets (/raw/frames) and no {path}: merge them first "
                          "with cca hdr (or cca run with the hdr stage)")
    return InputError(f"{handle.filename}: missing dataset {path}; the file is incomplete or from another stage")


def require(handle: h5py.File, path: str, *, ndim: int | None = None) -> h5py.Dataset:
    """A dataset that must exist (and have ``ndim`` dimensions), else a one-line InputError."""
    if path not in handle:
        raise missing_dataset(handle, path)
    dataset = handle[path]
    if not isinstance(dataset, h5py.Dataset):
        raise InputError(f"{handle.filename}: {path} is a group, expected a dataset; the file is not a cca file")
    if ndim is not None and dataset.ndim != ndim:
        raise InputError(f"{handle.filename}: {path} has shape {dataset.shape}, expected {ndim} dimensions")
    return dataset


def read_finite(handle: h5py.File, path: str, *, ndim: int | None = None, dtype=None) -> np.ndarray:
    """:func:`require` then read, refusing NaN or Inf (and complex values where ``dtype`` is real)."""
    dataset = require(handle, path, ndim=ndim)
    if dataset.dtype.kind not in "biufc":
        raise InputError(f"{handle.filename}: {path} holds {dataset.dtype} values, expected numbers")
    if dtype is not None and dataset.dtype.kind == "c" and np.dtype(dtype).kind != "c":
        raise InputError(f"{handle.filename}: {path} holds complex values, expected real ones")
    data = np.asarray(dataset, dtype=dtype)
    if not np.all(np.isfinite(data)):
        raise InputError(f"{handle.filename}: {path} contains NaN or Inf; the file is damaged — re-run the stage "
                         "that wrote it")
    return data


def require_attr(obj: h5py.HLObject, name: str, kind: type = float):
    """Attribute ``name`` of a group or dataset, converted to ``kind``; a one-line InputError if missing or wrong."""
    where = obj.name if obj.name != "/" else "the file"
    if name not in obj.attrs:
        raise InputError(f"{obj.file.filename}: {where} lacks the attribute {name}; the file is incomplete — "
                         "re-run the stage that wrote it")
    value = obj.attrs[name]
    try:
        if kind is str:
            return value.decode(errors="replace") if isinstance(value, bytes) else str(value)
        number = kind(value)
        if kind is float and not np.isfinite(number):
            raise ValueError
        return number
    except (TypeError, ValueError):
        raise InputError(f"{obj.file.filename}: {where} attribute {name} is {short(value)}, expected "
                         f"{'a finite number' if kind is float else 'an integer'}") from None


def read_provenance(path: str | Path) -> dict[str, Any]:
    """Root attributes of a pipeline file (empty dict if unreadable)."""
    try:
        with h5py.File(path, "r") as handle:
            return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in handle.attrs.items()}
    except (OSError, ValueError):
        return {}
