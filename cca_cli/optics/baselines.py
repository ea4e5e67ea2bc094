"""Baseline images: what a single lens (coherent or incoherent light) would record.

All images are computed with FFTs on the object's own grid: an ``M`` x ``M``
object of width ``W`` has spectrum pixels of ``λ z / W`` metres of aperture
plane, so a lens of diameter ``D`` passes a disc of radius ``D W / (2 λ z)``
spectrum pixels (:meth:`cca_cli.units.FourierScale.pupil_radius_px`).

* Coherent light: the image is ``|F⁻¹{P · F{o}}|²``.
* Incoherent light: the image is ``F⁻¹{OTF · F{|o|²}}`` with the optical
  transfer function the normalised autocorrelation of the pupil; for a circ
  pupil of cut-off ``f_c`` (the coherent cut-off), ``OTF(f) = (2/π)(arccos ρ −
  ρ √(1 − ρ²))`` with ``ρ = f / (2 f_c)``.
"""

from __future__ import annotations

import numpy as np

from cca_cli.optics import fft
from cca_cli.optics.pupil import centred_disc
from cca_cli.sampling.grid import smallest_fft_size

__all__ = ["circ_otf", "incoherent_otf", "coherent_image", "incoherent_image"]


def _radius_grid(size: int) -> np.ndarray:
    k = np.arange(size, dtype=np.float64) - size // 2
    return np.hypot(k[:, None], k[None, :])


def circ_otf(size: int, radius_px: float) -> np.ndarray:
    """Closed-form incoherent OTF of a circ pupil of radius ``radius_px`` (centred, float64).

    ``(2/π)(arccos ρ − ρ √(1 − ρ²))`` for ``ρ = f / (2 radius_px) < 1``, else 0.
    """
    rho = np.clip(_radius_grid(size) / (2.0 * radius_px), 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(rho) - rho * np.sqrt(1.0 - rho * rho))


def incoherent_otf(pupil: np.ndarray, *, size: int | None = None) -> np.ndarray:
    """Normalised autocorrelation of a centred pupil, computed with FFTs.

    Parameters
    ----------
    pupil : ndarray, (P, P)
        Centred pupil (complex or real) on a spectrum grid.
    size : int, optional
        Side of the returned OTF (default ``P``); the autocorrelation is
        computed on a grid large enough not to wrap and then cropped.

    Returns
    -------
    ndarray, float64, (size, size)
        Real part of the OTF, 1 at DC (index ``size // 2``).
    """
    pupil = np.asarray(pupil)
    p = pupil.shape[-1]
    size = p if size is None else int(size)
    support = np.argwhere(np.abs(pupil) > 0)
    reach = int(np.max(np.abs(support - p // 2))) + 1 if support.size else 1
    work = max(smallest_fft_size(4 * reach + 4), size, p)
    padded = np.zeros((work, work), np.complex128)
    lo = work // 2 - p // 2
    padded[lo:lo + p, lo:lo + p] = pupil
    amplitude_psf = fft.ifft2c(padded)
    otf = fft.fft2c(np.abs(amplitude_psf) ** 2)
    otf = otf / otf[work // 2, work // 2]
    lo = work // 2 - size // 2
    return otf[lo:lo + size, lo:lo + size].real.copy()


def coherent_image(field: np.ndarray, radius_px: float) -> np.ndarray:
    """Intensity image of a complex object through a circ pupil under coherent light (float32).

    Parameters
    ----------
    field : ndarray, complex, (M, M)
        Object field.
    radius_px : float
        Pupil radius in spectrum pixels of the object grid.
    """
    field = np.asarray(field, np.complex64)
    spectrum = fft.fft2c(field) * centred_disc(field.shape[-1], radius_px)
    return (np.abs(fft.ifft2c(spectrum)) ** 2).astype(np.float32)


def incoherent_image(field: np.ndarray, radius_px: float) -> np.ndarray:
    """Intensity image of an object through a circ pupil under spatially incoherent light (float32).

    The object intensity ``|field|²`` is filtered by the circ pupil's OTF;
    negative ringing from the band limit is clipped to 0.
    """
    intensity = np.abs(np.asarray(field)) ** 2
    otf = circ_otf(intensity.shape[-1], radius_px)
    image = fft.ifft2c(fft.fft2c(intensity.astype(np.complex64)) * otf).real
    return np.clip(image, 0.0, None).astype(np.float32)
