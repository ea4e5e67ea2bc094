"""Reading /measurements with the checks that keep a recovery from running on nothing.

An intensity stack must hold finite, real numbers; no image may have a
negative mean (noise may dip below zero, a signal may not); and not every
image may be all zero or flat, since then there is no contrast to recover an
object from. A weight stack must match the images, lie in [0, 1] and not be
zero everywhere (that would ignore every pixel and return the starting guess).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError
from cca_cli.io.h5 import require

__all__ = ["read_intensity", "read_weight"]

INTENSITY = "/measurements/intensity"
WEIGHT = "/measurements/weight"


def _real(handle: h5py.File, name: str, ndim: int) -> h5py.Dataset:
    dataset = require(handle, name, ndim=ndim)
    if dataset.dtype.kind not in "biuf":
        kind = "complex" if dataset.dtype.kind == "c" else str(dataset.dtype)
        raise InputError(f"{handle.filename}: {name} holds {kind} values, expected real numbers")
    return dataset


def read_intensity(handle: h5py.File, path: Path) -> np.ndarray:
    """/measurements/intensity as float32 (K, N, N'), checked (see the module notes)."""
    intensity = np.asarray(_real(handle, INTENSITY, 3), dtype=np.float32)
    k = intensity.shape[0]
    if k == 0 or intensity.size == 0:
        raise InputError(f"{path}: {INTENSITY} holds no images")
    flat = intensity.reshape(k, -1)
    finite = np.isfinite(flat).all(axis=1)
    if not finite.all():
        bad = int(np.argmin(finite))
        raise InputError(f"{path}: image {bad} of {INTENSITY} contains NaN or Inf; fix or mask it")
    if not flat.any():
        raise InputError(f"{path}: every image of {INTENSITY} is zero; nothing was recorded")
    means = flat.mean(axis=1, dtype=np.float64)
    if (means < 0).any():
        bad = int(np.argmin(means))
        raise InputError(f"{path}: image {bad} of {INTENSITY} has a negative mean ({means[bad]:.3g}); intensities "
                         "are ≥ 0 (noise may dip below zero, the signal may not): check the black level or the sign")
    if (flat.max(axis=1) == flat.min(axis=1)).all():
        raise InputError(f"{path}: every image of {INTENSITY} is flat (one value each), so there is no contrast "
                         "to recover an object from")
    return intensity


def read_weight(handle: h5py.File, path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    """/measurements/weight as float32 (None when absent), checked against the images' ``shape``."""
    if WEIGHT not in handle:
        return None
    dataset = _real(handle, WEIGHT, len(shape))
    if dataset.shape != tuple(shape):
        raise InputError(f"{path}: {WEIGHT} has shape {dataset.shape}, expected {tuple(shape)}")
    weight = np.asarray(dataset, dtype=np.float32)
    if not np.isfinite(weight).all():
        raise InputError(f"{path}: {WEIGHT} contains NaN or Inf; weights are in [0, 1]")
    low, high = float(weight.min()), float(weight.max())
    if low < 0 or high > 1:
        raise InputError(f"{path}: {WEIGHT} spans [{low:.3g}, {high:.3g}]; weights are in [0, 1] "
                         "(0 ignores a pixel)")
    if high == 0:
        raise InputError(f"{path}: {WEIGHT} is 0 everywhere, so every pixel would be ignored; "
                         "give weights in (0, 1] where the data are valid")
    return weight
