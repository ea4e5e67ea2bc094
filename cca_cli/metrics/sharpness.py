"""No-reference sharpness of real captures (no ground truth).

Two figures of merit, both computed on a common grid so an observed image
and a recovery of a different size compare fairly:

* :func:`spectral_energy_beyond` — the share of an intensity image's
  spectral power (DC excluded) that lies beyond a radius, e.g. the
  single-aperture intensity cutoff ``2 R``. A coherent image through one
  pupil of radius ``R`` has no intensity spectrum beyond ``2 R`` (only noise
  and aliasing); a synthetic-aperture recovery fills the band out to
  ``2 R_synthetic``.
* :func:`spectral_reach` — the spatial frequency within which a given share
  (99%) of that power lies: how far out the image's detail reaches. It is
  the sharpness gain the report quotes (recovered / observed).
* :func:`rms_frequency` — the RMS spatial frequency of the same power
  spectrum. It is dominated by where most of the power sits (the low and
  middle frequencies), so a recovery that adds fine detail but also changes
  the mid-frequency contrast (a defocused capture's fringes, for example)
  can leave it unchanged.

Noise and artefacts reach far too: read these figures next to the data
residual, never alone.
"""

from __future__ import annotations

import numpy as np

__all__ = ["spectral_energy_beyond", "spectral_reach", "rms_frequency"]


def _power_spectrum(image) -> np.ndarray:
    """``|fft2(I - mean(I))|²`` of a 2-D image (uncentred, float64)."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image has shape {img.shape}; expected (N, N)")
    return np.abs(np.fft.fft2(img - img.mean())) ** 2


def spectral_energy_beyond(image, radius_px: float) -> float:
    """Fraction of the (DC-removed) power spectrum of ``image`` beyond ``radius_px``.

    Parameters
    ----------
    image : array_like, (N, N) or (H, W)
        Intensity image.
    radius_px : float
        Radius in spectrum pixels of the N x N grid (cycles per field width;
        for a rectangle, cycles per image width along both axes).

    Returns
    -------
    float
        Share in [0, 1]; 0 for a flat image.
    """
    power = np.fft.fftshift(_power_spectrum(image))
    h, w = power.shape
    fy = (np.arange(h)[:, None] - h // 2) * (w / h)  # cycles per image width on both axes
    fx = np.arange(w)[None, :] - w // 2
    total = float(power.sum())
    if total <= 0:
        return 0.0
    return float(power[np.hypot(fy, fx) > radius_px].sum() / total)


def spectral_reach(image, pixel_m: float = 1.0, share: float = 0.99) -> float:
    """Spatial frequency within which ``share`` of an image's (DC-removed) power lies.

    Parameters
    ----------
    image : array_like, (H, W)
        Intensity image.
    pixel_m : float
        Pixel size at the object (the result is in cycles per unit of it).
    share : float
        Share of the power enclosed, in (0, 1).

    Returns
    -------
    float
        Radius of the smallest centred disc of frequencies holding ``share`` of the
        power; 0 for a flat image.
    """
    if not 0 < share < 1:
        raise ValueError(f"share must be in (0, 1), got {share}")
    power = _power_spectrum(image)
    fy = np.fft.fftfreq(power.shape[0])[:, None]
    fx = np.fft.fftfreq(power.shape[1])[None, :]
    radius = np.hypot(fy, fx).ravel()
    order = np.argsort(radius, kind="stable")
    cumulative = np.cumsum(power.ravel()[order])
    if cumulative[-1] <= 0:
        return 0.0
    index = int(np.searchsorted(cumulative, share * cumulative[-1]))
    return float(radius[order][min(index, radius.size - 1)] / pixel_m)


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
    power = _power_spectrum(image)
    fy = np.fft.fftfreq(power.shape[0])[:, None]
    fx = np.fft.fftfreq(power.shape[1])[None, :]
    total = float(power.sum())
    if total <= 0:
        return 0.0
    return float(np.sqrt((power * (fy * fy + fx * fx)).sum() / total) / pixel_m)
