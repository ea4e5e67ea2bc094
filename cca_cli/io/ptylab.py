"""PtyLab's FPM datasets: one HDF5 file holding an LED-array microscope's images and its geometry.

PtyLab (Loetgering et al., Opt. Express 31(9), 2023) stores an FPM measurement as the datasets
``ptychogram`` (the images, ``(J, N, N)``), ``encoder`` (each LED's ``[y, x]`` position in its plane,
metres, ``(J, 2)``), ``zled`` (the LED plane's distance from the sample, m), ``wavelength`` (m), ``dxd``
(the camera's pixel, m), ``magnification`` and, optionally, ``NA``. An LED's light reaches the sample at
``sin θ = encoder / √(|encoder|² + zled²)``, and PtyLab places frame ``j``'s pupil at ``−(W/λ) sin θ_j``
(``W`` the frame's width at the sample): cca's ``sign: -1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError

__all__ = ["PtyLabSet", "is_ptylab_file", "read_ptylab", "read_ptylab_images", "REQUIRED"]

#: The datasets an FPM file must hold (``NA`` may be given in the manifest instead).
REQUIRED = ("ptychogram", "encoder", "zled", "wavelength", "dxd", "magnification")


@dataclass(frozen=True)
class PtyLabSet:
    """What a PtyLab FPM file holds, in cca's terms.

    Attributes
    ----------
    sines_yx : ndarray, float64, (J, 2)
        ``[sin θy, sin θx]`` of each image's LED.
    wavelength_m, pixel_pitch_object_m, led_distance_m : float
    numerical_aperture : float or None
        None where the file has no ``NA``.
    images : int
    notes : tuple of str
    """

    sines_yx: np.ndarray
    wavelength_m: float
    pixel_pitch_object_m: float
    led_distance_m: float
    numerical_aperture: float | None
    images: int
    notes: tuple[str, ...] = ()

    def illumination(self) -> dict:
        """The manifest's ``illumination`` keys the file gives."""
        keys = {"wavelength_m": self.wavelength_m, "pixel_pitch_object_m": self.pixel_pitch_object_m,
                "led_distance_m": self.led_distance_m, "sign": -1}
        if self.numerical_aperture is not None:
            keys["numerical_aperture"] = self.numerical_aperture
        return keys


def is_ptylab_file(path: Path) -> bool:
    """Whether ``path`` is an HDF5 file with a ``ptychogram`` dataset."""
    path = Path(path)
    try:
        if not (path.is_file() and h5py.is_hdf5(path)):
            return False
        with h5py.File(path, "r") as handle:
            return isinstance(handle.get("ptychogram"), h5py.Dataset)
    except OSError:
        return False


def read_ptylab(path: Path) -> PtyLabSet:
    """The geometry of a PtyLab FPM file (not its images: :func:`read_ptylab_images`).

    Raises
    ------
    InputError
        The file cannot be read, lacks one of :data:`REQUIRED`, or holds values that make no geometry;
        one line naming the file and the dataset.
    """
    path = Path(path)
    try:
        with h5py.File(path, "r") as handle:
            missing = [name for name in REQUIRED if not isinstance(handle.get(name), h5py.Dataset)]
            if missing:
                raise InputError(f"{path}: not a PtyLab FPM dataset: it lacks {', '.join(missing)} (an FPM file "
                                 f"holds {', '.join(REQUIRED)} and, optionally, NA)")
            shape = handle["ptychogram"].shape
            encoder = np.asarray(handle["encoder"][()], np.float64)
            scalars = {name: _scalar(handle, name, path) for name in ("zled", "wavelength", "dxd", "magnification")}
            na = _scalar(handle, "NA", path) if isinstance(handle.get("NA"), h5py.Dataset) else None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the HDF5 file ({' '.join(str(exc).split())})") from None
    notes = []
    if encoder.ndim != 2 or 2 not in encoder.shape:
        raise InputError(f"{path}: encoder has shape {encoder.shape}; expected (J, 2) LED positions [y, x] in metres")
    if encoder.shape[1] != 2:
        # stored the other way round (MATLAB): read as PtyLab reads it, centred on the positions' mean
        encoder = encoder.T - encoder.T.mean(axis=0)
        notes.append("encoder is stored as (2, J): read transposed and centred on its mean, as PtyLab reads it")
    count = encoder.shape[0]
    if count not in shape or len(shape) != 3:
        raise InputError(f"{path}: ptychogram has shape {shape}; expected ({count}, N, N), one image per encoder row")
    if not np.isfinite(encoder).all():
        raise InputError(f"{path}: encoder holds NaN or infinite positions; fix the file")
    for name, value in {**scalars, "NA": na}.items():
        if value is not None and not (np.isfinite(value) and value > 0):
            raise InputError(f"{path}: {name} is {value!r}; expected a positive number")
    if na is not None and na >= 1:
        raise InputError(f"{path}: NA is {na!r}; expected the objective's numerical aperture, under 1")
    radius = np.sqrt(np.sum(encoder ** 2, axis=1) + scalars["zled"] ** 2)
    return PtyLabSet(sines_yx=encoder / radius[:, None], wavelength_m=scalars["wavelength"],
                     pixel_pitch_object_m=scalars["dxd"] / scalars["magnification"],
                     led_distance_m=scalars["zled"], numerical_aperture=na, images=count, notes=tuple(notes))


def read_ptylab_images(path: Path, count: int) -> np.ndarray:
    """The ``count`` images of a PtyLab file's ``ptychogram``, (J, H, W) float32 (a ``(H, W, J)`` stack is turned)."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as handle:
            stack = np.asarray(handle["ptychogram"][()])
    except (OSError, KeyError) as exc:
        raise InputError(f"{path}: cannot read ptychogram ({' '.join(str(exc).split())})") from None
    if stack.dtype.kind not in "biuf":
        raise InputError(f"{path}: ptychogram holds {stack.dtype} values; expected real numbers")
    if stack.shape[0] != count:
        stack = np.moveaxis(stack, stack.shape.index(count), 0)
    return stack.astype(np.float32)


def _scalar(handle, name: str, path: Path) -> float:
    value = np.asarray(handle[name][()], np.float64).ravel()
    if value.size != 1:
        raise InputError(f"{path}: {name} holds {value.size} values; expected one number")
    return float(value[0])
