"""HDF5 files of the pipeline: atomic writes, provenance attributes, checked reads."""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from cca_cli import __version__
from cca_cli.errors import InputError, OutputExistsError
from cca_cli.io.schema import SCHEMA_VERSION, spec_for

__all__ = [
    "Provenance",
    "atomic_h5",
    "atomic_path",
    "check_output",
    "file_sha256",
    "open_input",
    "write_dataset",
    "describe",
    "read_provenance",
    "remove_temporaries",
    "require",
]


def file_sha256(path: str | Path, *, block: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes (hex)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(block):
            digest.update(chunk)
    return digest.hexdigest()


class Provenance(dict):
    """Root attributes every output carries: schema, stage, version, time, config, inputs."""

    @classmethod
    def make(cls, stage: str, config_yaml: str, config_hash: str, inputs: list[str | Path] = ()) -> "Provenance":
        """Provenance for a stage run now, hashing its input files."""
        for p in inputs:
            if not Path(p).is_file():
                raise InputError(f"{p}: input file not found; check the path or run the stage that writes it")
        return cls(
            cca_schema=SCHEMA_VERSION,
            stage=stage,
            cca_version=__version__,
            created_utc=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            config=config_yaml,
            config_hash=config_hash,
            inputs=json.dumps([{"path": str(p), "sha256": file_sha256(p)} for p in inputs]),
        )


def check_output(path: Path, *, force: bool) -> None:
    """Refuse to overwrite an existing output unless ``force``."""
    if path.exists() and not force:
        raise OutputExistsError(f"{path}: already exists; use --force to overwrite it or choose another output")


@contextlib.contextmanager
def atomic_path(path: str | Path, *, force: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling path; on success rename it onto ``path``.

    The caller may create a file or a directory at the temporary path; an
    existing directory at ``path`` (overwritten with ``force``) is replaced whole.
    On any error (or Ctrl-C) the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    check_output(path, force=force)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        yield tmp
        if tmp.is_dir() and path.is_dir():  # os.replace cannot replace a non-empty directory
            shutil.rmtree(path)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink()


def remove_temporaries(directory: str | Path) -> None:
    """Remove what interrupted :func:`atomic_path` writes left in ``directory`` (their temporary siblings)."""
    for stale in Path(directory).glob(".*.tmp-*"):
        if stale.is_dir():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            stale.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_h5(path: str | Path, provenance: Provenance, *, force: bool = False) -> Iterator[h5py.File]:
    """Open a new HDF5 file for writing that appears at ``path`` only when complete."""
    with atomic_path(path, force=force) as tmp:
        with h5py.File(tmp, "w") as handle:
            for key, value in provenance.items():
                handle.attrs[key] = value
            yield handle


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
    chunks = (1,) + data.shape[1:] if data.ndim == 3 and data.nbytes > (1 << 24) else None
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
    if not h5py.is_hdf5(path):
        raise InputError(f"{path}: not an HDF5 file; give a file written by cca (captures.h5, recon.h5 …)")
    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: cannot open HDF5 file ({exc}); it may be truncated — re-run the stage") from None
    if handle.attrs.get("cca_schema") != SCHEMA_VERSION:
        handle.close()
        raise InputError(f"{path}: not a cca file (no cca_schema={SCHEMA_VERSION} attribute)")
    if stage is not None and stage not in str(handle.attrs.get("stage", "")).split(","):
        actual = handle.attrs.get("stage")
        handle.close()
        raise InputError(f"{path}: written by stage {actual!r}, expected {stage!r}")
    return handle


def require(handle: h5py.File, path: str, *, ndim: int | None = None) -> h5py.Dataset:
    """A dataset that must exist (and have ``ndim`` dimensions), else a one-line InputError."""
    if path not in handle:
        raise InputError(f"{handle.filename}: missing dataset {path}; the file is incomplete or from another stage")
    dataset = handle[path]
    if ndim is not None and dataset.ndim != ndim:
        raise InputError(f"{handle.filename}: {path} has shape {dataset.shape}, expected {ndim} dimensions")
    return dataset


def read_provenance(path: str | Path) -> dict[str, Any]:
    """Root attributes of a pipeline file (empty dict if unreadable)."""
    try:
        with h5py.File(path, "r") as handle:
            return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in handle.attrs.items()}
    except (OSError, ValueError):
        return {}
