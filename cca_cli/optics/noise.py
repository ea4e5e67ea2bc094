"""Sensor noise models. Every function takes an explicit ``numpy.random.Generator``."""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_SNR_DB", "gaussian_noise_sigma", "add_gaussian_noise", "add_shot_and_read_noise"]

#: Lowest Gaussian SNR a simulation takes. Below it the noise (σ over 3 times an image's own standard
#: deviation) swamps the images: the means of dim (dark-field) images fall below zero, which no intensity can have.
MIN_SNR_DB = -10.0


def gaussian_noise_sigma(images: np.ndarray, snr_db: float) -> np.ndarray:
    """Per-image noise standard deviation for a given SNR.

    Notes
    -----
    SNR follows the paper's simulations: for image ``I_i``,
    ``SNR_dB = 10 log10(var(I_i) / σ_i²)``, i.e. ``σ_i² = var(I_i) / 10^(SNR/10)``,
    the variance taken over the image's pixels.

    Returns
    -------
    ndarray, float64, (K,)
    """
    images = np.asarray(images)
    variance = images.reshape(images.shape[0], -1).var(axis=1, dtype=np.float64)
    return np.sqrt(variance / 10.0 ** (snr_db / 10.0))


def add_gaussian_noise(images: np.ndarray, snr_db: float, rng: np.random.Generator) -> np.ndarray:
    """Add white Gaussian noise at ``snr_db`` to each image (float32, new array).

    Parameters
    ----------
    images : ndarray, (K, H, W)
        Noise-free intensities.
    snr_db : float
        Signal-to-noise ratio in dB, defined per image as in :func:`gaussian_noise_sigma`.
    rng : numpy.random.Generator
    """
    images = np.asarray(images, dtype=np.float32)
    sigma = gaussian_noise_sigma(images, snr_db).astype(np.float32)
    out = np.empty_like(images)
    for i in range(images.shape[0]):
        noise = rng.standard_normal(images.shape[1:], dtype=np.float32)
        np.multiply(noise, sigma[i], out=noise)
        np.add(images[i], noise, out=out[i])
    return out


def add_shot_and_read_noise(images: np.ndarray, *, photons_per_unit: float, read_noise_e: float,
                            rng: np.random.Generator) -> np.ndarray:
    """Poisson shot noise plus Gaussian read noise, returned in the input's intensity units.

    Parameters
    ----------
    images : ndarray, (K, H, W)
        Noise-free intensities (irradiance units).
    photons_per_unit : float
        Photo-electrons collected per pixel for an intensity of 1.
    read_noise_e : float
        Read noise standard deviation (electrons).
    rng : numpy.random.Generator
    """
    images = np.asarray(images, dtype=np.float32)
    if photons_per_unit <= 0:
        raise ValueError(f"photons_per_unit must be positive, got {photons_per_unit}")
    out = np.empty_like(images)
    for i in range(images.shape[0]):
        electrons = rng.poisson(np.clip(images[i], 0, None) * photons_per_unit).astype(np.float32)
        electrons += rng.standard_normal(images.shape[1:], dtype=np.float32) * np.float32(read_noise_e)
        out[i] = electrons / np.float32(photons_per_unit)
    return out
