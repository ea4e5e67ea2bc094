"""Reading /measurements with the checks that keep a recovery from running on nothing.

An intensity stack must hold finite, real numbers; no image may have a
negative mean (noise may dip below zero, a signal may not); and not every
image may be all zero or flat, since then there is no contrast to recover an
object from. A weight stack must match the images, lie in [0, 1] and not be
zero everywhere (that would ignore every pixel and return the starting guess).
The same checks serve the Python interface on arrays (:func:`check_intensity`,
:func:`check_weight`). A single image that holds one value is a dead capture
(all zero, or minus the black level, whatever its sign): :func:`constant_images`
finds it, and :func:`cca_cli.workflows.recovery.without_dead_captures` decides
what the recovery does with it.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError
from cca_cli.io.h5 import require

__all__ = ["INTENSITY", "WEIGHT", "check_intensity", "check_weight", "constant_images", "read_intensity",
           "read_weight"]

INTENSITY = "/measurements/intensity"
WEIGHT = "/measurements/weight"


def _real(handle: h5py.File, name: str, ndim: int) -> h5py.Dataset:
    dataset = require(handle, name, ndim=ndim)
    if dataset.dtype.kind not in "biuf":
        kind = "complex" if dataset.dtype.kind == "c" else str(dataset.dtype)
        raise InputError(f"{handle.filename}: {name} holds {kind} values, expected real numbers")
    return dataset


def _prefix(source) -> str:
    return f"{source}: " if source else ""


def check_intensity(intensity: np.ndarray, name: str = INTENSITY, *, source=None, error=InputError) -> None:
    """Refuse an intensity stack (K, H, W) that no recovery can use (see the module notes).

    Parameters
    ----------
    intensity : ndarray, (K, H, W)
        Real images.
    name : str
        What the images are called in messages (the dataset, or an argument of the Python interface).
    source : str or Path, optional
        The file they come from, which the messages begin with.
    error : type
        The exception raised (:class:`~cca_cli.errors.InputError` for files, ``ValueError`` for arrays).
    """
    where = _prefix(source)
    k = intensity.shape[0]
    if k == 0 or intensity.size == 0:
        raise error(f"{where}{name} holds no images")
    flat = intensity.reshape(k, -1)
    finite = np.isfinite(flat).all(axis=1)
    if not finite.all():
        bad = int(np.argmin(finite))
        raise error(f"{where}image {bad} of {name} contains NaN or Inf; fix or mask it")
    if not flat.any():
        raise error(f"{where}every image of {name} is zero; nothing was recorded")
    live = flat.max(axis=1) != flat.min(axis=1)
    if not live.any():
        raise error(f"{where}every image of {name} is flat (one value each), so there is no contrast "
                    "to recover an object from")
    # A constant image (a dead capture, black level subtracted) is judged by constant_images, not here.
    means = np.where(live, flat.mean(axis=1, dtype=np.float64), 0.0)
    if (means < 0).any():
        bad = int(np.argmin(means))
        raise error(f"{where}image {bad} of {name} has a negative mean ({means[bad]:.3g}); intensities "
                    "are ≥ 0 (noise may dip below zero, the signal may not): check the black level or the sign")


def constant_images(intensity: np.ndarray) -> np.ndarray:
    """Indices of the images (K, H, W) whose pixels all hold one value: a dead capture records nothing."""
    flat = intensity.reshape(intensity.shape[0], -1)
    return np.flatnonzero(flat.max(axis=1) == flat.min(axis=1))


def read_intensity(handle: h5py.File, path: Path) -> np.ndarray:
    """/measurements/intensity as float32 (K, N, N'), checked (see the module notes)."""
    intensity = np.asarray(_real(handle, INTENSITY, 3), dtype=np.float32)
    check_intensity(intensity, source=path)
    return intensity


def check_weight(weight: np.ndarray, shape: tuple[int, ...], name: str = WEIGHT, *, source=None,
                 error=InputError) -> None:
    """Refuse weights that do not match the images' ``shape``, leave [0, 1] or are 0 everywhere.

    ``name``, ``source`` and ``error`` are as in :func:`check_intensity`.
    """
    where = _prefix(source)
    if weight.shape != tuple(shape):
        raise error(f"{where}{name} has shape {weight.shape}, expected {tuple(shape)}")
    if not np.isfinite(weight).all():
        raise error(f"{where}{name} contains NaN or Inf; weights are in [0, 1]")
    low, high = float(weight.min()), float(weight.max())
    if low < 0 or high > 1:
        raise error(f"{where}{name} spans [{low:.3g}, {high:.3g}]; weights are in [0, 1] (0 ignores a pixel)")
    if high == 0:
        raise error(f"{where}{name} is 0 everywhere, so every pixel would be ignored; "
                    "give weights in (0, 1] where the data are valid")


def read_weight(handle: h5py.File, path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    """/measurements/weight as float32 (None when absent), checked against the images' ``shape``."""
    if WEIGHT not in handle:
        return None
    dataset = _real(handle, WEIGHT, len(shape))
    if dataset.shape != tuple(shape):
        raise InputError(f"{path}: {WEIGHT} has shape {dataset.shape}, expected {tuple(shape)}")
    weight = np.asarray(dataset, dtype=np.float32)
    check_weight(weight, shape, source=path)
    return weight
