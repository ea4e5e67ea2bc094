"""No-reference sharpness of real captures (no ground truth).

Two figures of merit, both computed on a common grid so an observed image
and a recovery of a different size compare fairly:

* :func:`spectral_energy_beyond` — the share of an intensity image's
  spectral power (DC excluded) that lies beyond a radius, e.g. the
  single-aperture intensity cutoff ``2 R``. A coherent image through one
  pupil of radius ``R`` has no intensity spectrum beyond ``2 R`` (only noise
  and aliasing); a synthetic-aperture recovery fills the band out to
  ``2 R_synthetic``.
* :func:`gradient_sharpness` — the RMS intensity gradient per object pixel
  over the mean intensity (a normalised Tenengrad): it rises when edges get
  steeper.
"""

from __future__ import annotations

import numpy as np

__all__ = ["spectral_energy_beyond", "gradient_sharpness", "rms_frequency"]


def spectral_energy_beyond(image, radius_px: float) -> float:
    """Fraction of the (DC-removed) power spectrum of ``image`` beyond ``radius_px``.

    Parameters
    ----------
    image : array_like, (N, N)
        Intensity image.
    radius_px : float
        Radius in spectrum pixels of the N x N grid (cycles per field width).

    Returns
    -------
    float
        Share in [0, 1]; 0 for a flat image.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image has shape {img.shape}; expected (N, N)")
    power = np.abs(np.fft.fftshift(np.fft.fft2(img - img.mean()))) ** 2
    h, w = img.shape
    fy = np.arange(h)[:, None] - h // 2
    fx = np.arange(w)[None, :] - w // 2
    total = float(power.sum())
    if total <= 0:
        return 0.0
    return float(power[np.hypot(fy, fx) > radius_px].sum() / total)


def gradient_sharpness(image) -> float:
    """RMS of the intensity gradient (per pixel) divided by the mean intensity.

    Parameters
    ----------
    image : array_like, (N, N)

    Returns
    -------
    float
        ``sqrt(mean(|∇I|²)) / mean(I)`` with central differences; 0 for a flat or dark image.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image has shape {img.shape}; expected (N, N)")
    mean = float(img.mean())
    if mean <= 0:
        return 0.0
    gy, gx = np.gradient(img)
    return float(np.sqrt(np.mean(gy * gy + gx * gx)) / mean)


def rms_frequency(image, pixel_m: float = 1.0) -> float:
    """RMS spatial frequency of an image's (DC-removed) power spectrum.

    ``sqrt(Σ |f|² P(f) / Σ P(f))`` in cycles per unit of ``pixel_m`` (cycles/m
    for a pixel given in metres; divide by 1000 for lp/mm). It measures how
    far out the image's spectrum reaches independent of its contrast: a
    blurred image has a small value, a sharper one of the same scene a
    larger one.

    Parameters
    ----------
    image : array_like, (N, N)
    pixel_m : float
        Pixel size at the object.

    Returns
    -------
    float
        0 for a flat image.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image has shape {img.shape}; expected (N, N)")
    power = np.abs(np.fft.fft2(img - img.mean())) ** 2
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    total = float(power.sum())
    if total <= 0:
        return 0.0
    return float(np.sqrt((power * (fy * fy + fx * fx)).sum() / total) / pixel_m)
