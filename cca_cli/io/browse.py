"""Opening any HDF5 file for reading and walking what it holds (``cca info``)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import h5py

from cca_cli.errors import InputError

__all__ = ["open_hdf5", "visit_datasets", "is_group"]


def open_hdf5(path: Path) -> h5py.File:
    """Open ``path`` read-only, or raise :class:`~cca_cli.errors.InputError` when it is no (readable) HDF5 file."""
    if not h5py.is_hdf5(path):
        raise InputError(f"{path}: not an HDF5 file; give an HDF5 file (one cca wrote: captures.h5, recon.h5 …)")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: cannot open HDF5 file ({exc}); it may be truncated") from None


def visit_datasets(handle: h5py.File, visit: Callable[[str, h5py.Dataset], None]) -> None:
    """Call ``visit(name, dataset)`` for every dataset of an open file, in HDF5's visiting order."""

    def on_item(name, obj):
        if isinstance(obj, h5py.Dataset):
            visit(name, obj)

    handle.visititems(on_item)


def is_group(obj) -> bool:
    """Whether ``obj`` (an item of an open file) is a group."""
    return isinstance(obj, h5py.Group)
