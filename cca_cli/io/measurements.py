"""Reading /measurements with the checks that keep a recovery from running on nothing.

An intensity stack must hold finite, real numbers; no image may have a
mean below zero by more than its noise allows (noise may dip below zero, a
signal may not); and not every
image may be all zero or flat, since then there is no contrast to recover an
object from. A weight stack must match the images, lie in [0, 1] and not be
zero everywhere (that would ignore every pixel and return the starting guess).
The checks are the library's (:func:`cca_cli.library.data.check_intensity`,
:func:`~cca_cli.library.data.check_weight`), which the Python interface runs on
arrays; here they name the file and raise :class:`~cca_cli.errors.InputError`.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError
from cca_cli.io.h5 import require
from cca_cli.io.schema import INTENSITY, WEIGHT
from cca_cli.library.data import check_intensity, check_weight

__all__ = ["INTENSITY", "WEIGHT", "read_intensity", "read_weight"]



def _real(handle: h5py.File, name: str, ndim: int) -> h5py.Dataset:
    dataset = require(handle, name, ndim=ndim)
    if dataset.dtype.kind not in "biuf":
        kind = "complex" if dataset.dtype.kind == "c" else str(dataset.dtype)
        raise InputError(f"{handle.filename}: {name} holds {kind} values, expected real numbers")
    return dataset


def _prefix(source) -> str:
    return f"{source}: " if source else ""


def read_intensity(handle: h5py.File, path: Path) -> np.ndarray:
    """/measurements/intensity as float32 (K, N, N'), checked (see the module notes)."""
    intensity = np.asarray(_real(handle, INTENSITY, 3), dtype=np.float32)
    labels = handle["/capture/labels"].asstr()[()].tolist() if "/capture/labels" in handle else None
    if labels is not None and len(labels) != len(intensity):
        labels = None
    check_intensity(intensity, INTENSITY, source=path, error=InputError, labels=labels)
    return intensity


def read_weight(handle: h5py.File, path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    """/measurements/weight as float32 (None when absent), checked against the images' ``shape``."""
    if WEIGHT not in handle:
        return None
    dataset = _real(handle, WEIGHT, len(shape))
    if dataset.shape != tuple(shape):
        raise InputError(f"{path}: {WEIGHT} has shape {dataset.shape}, expected {tuple(shape)}")
    weight = np.asarray(dataset, dtype=np.float32)
    check_weight(weight, shape, WEIGHT, source=path, error=InputError)
    return weight
