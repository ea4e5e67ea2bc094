"""Image stacks held in one file: a MATLAB variable (v5/v7, or v7.3's HDF5) or a numpy ``.npy`` array.

Public FPM sets are often released so (``source: {mat: FILE, variable: NAME}`` in a manifest). The image axis is
the one as long as the illumination table; where more than one is, MATLAB's last axis (``(H, W, K)``) or
numpy's first (``(K, H, W)``).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError

__all__ = ["read_stack"]


def read_stack(path: Path, variable: str, count: int, *, table: str = "the illumination table") -> np.ndarray:
    """The ``count`` images of a MATLAB variable or a ``.npy`` array, (K, H, W) float32.

    Parameters
    ----------
    path : Path
        A ``.mat`` file (any other suffix is read as one too) or a ``.npy`` file.
    variable : str
        The MATLAB variable (unused for ``.npy``).
    count : int
        How many images the stack holds (rows of the illumination table).
    table : str
        The table's name, for messages.

    Raises
    ------
    InputError
        A missing or unreadable file, a missing variable, values that are not real numbers, or no axis of
        ``count`` images; one line naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found (manifest source.mat); check the path")
    numpy_file = path.suffix.lower() == ".npy"
    stack = _numpy_array(path) if numpy_file else _matlab_variable(path, variable)
    if stack.ndim != 3:
        what, layout = ("the array", "(K, H, W)") if numpy_file else (variable, "(H, W, K)")
        raise InputError(f"{path}: {what} has shape {stack.shape}; expected {layout}, one image per row of {table}")
    axes = [axis for axis in range(3) if stack.shape[axis] == count]
    if not axes:
        raise InputError(f"{path}: no axis of its {stack.shape} stack holds the {count} images {table} lists; check "
                         "the file or the table")
    usual = 0 if numpy_file else 2
    axis = usual if usual in axes else axes[0]
    return np.moveaxis(stack, axis, 0).astype(np.float32)


def _numpy_array(path: Path) -> np.ndarray:
    try:
        stack = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the numpy array ({' '.join(str(exc).split())})") from None
    return _real(stack, path, "the array")


def _matlab_variable(path: Path, variable: str) -> np.ndarray:
    from scipy.io import loadmat

    if h5py.is_hdf5(path):   # MATLAB v7.3
        return _matlab_hdf5_variable(path, variable)
    try:
        data = loadmat(path, variable_names=[variable])
    except Exception as exc:  # noqa: BLE001 - any decoder failure is an unreadable file
        raise InputError(f"{path}: cannot read MATLAB file ({' '.join(str(exc).split())}); cca reads MATLAB's v5, "
                         "v7 and v7.3 files and numpy's .npy") from None
    if variable not in data:
        raise InputError(f"{path}: has no variable {variable!r} (manifest source.variable)")
    return _real(np.asarray(data[variable]), path, variable)


def _matlab_hdf5_variable(path: Path, variable: str) -> np.ndarray:
    """A v7.3 variable, its axes put back in MATLAB's order (HDF5 holds them reversed)."""
    try:
        with h5py.File(path, "r") as handle:
            dataset = handle.get(variable)
            if not isinstance(dataset, h5py.Dataset):
                raise InputError(f"{path}: has no variable {variable!r} (manifest source.variable)")
            return _real(np.asarray(dataset), path, variable).transpose()
    except OSError as exc:
        raise InputError(f"{path}: cannot read MATLAB v7.3 file ({' '.join(str(exc).split())})") from None


def _real(stack: np.ndarray, path: Path, what: str) -> np.ndarray:
    if stack.dtype.kind not in "biuf":
        raise InputError(f"{path}: {what} holds {stack.dtype} values; expected real numbers")
    return stack
