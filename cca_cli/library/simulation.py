"""What the geometry's cameras record of an object: the one simulation chain of the API and the command line.

An object's field (on any square grid over the geometry's field of view) is
resampled in Fourier space to the recovery grid; each capture's pupil passes
its disc of the spectrum (optionally with a lens aberration that varies across
the field), the intensity is formed on the band grid, resampled to the stored
grid (the sensor's, or the band grid itself) and noise is added:

- ``gaussian``: ``σ² = var(I)/10^(SNR/10)`` per image, the paper's definition;
- ``poisson``: shot noise of ``photons_per_unit`` photo-electrons per unit
  irradiance plus Gaussian read noise of ``read_noise_e`` electrons;
- ``none``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.optics import fft
from cca_cli.optics.field_aberration import field_varying_intensity
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.noise import MIN_SNR_DB, add_gaussian_noise, add_shot_and_read_noise
from cca_cli.progress import ProgressEvent, ProgressFn, silent
from cca_cli.sampling.capture import object_pixel_m
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import BandLayout, band_layout

__all__ = ["NOISE_MODELS", "Noise", "sensor_pixels", "simulation_layout", "field_spectrum", "simulate", "record"]

NOISE_MODELS = ("gaussian", "poisson", "none")


@dataclass(frozen=True)
class Noise:
    """How a simulated camera's images are noisy.

    Attributes
    ----------
    model : {"gaussian", "poisson", "none"}
    snr_db : float
        Gaussian: SNR per image (≥ :data:`~cca_cli.optics.noise.MIN_SNR_DB`).
    photons_per_unit : float
        Poisson: photo-electrons at irradiance 1.
    read_noise_e : float
        Poisson: read noise (electrons RMS).
    seed : int
    """

    model: str = "gaussian"
    snr_db: float = 30.0
    photons_per_unit: float = 1000.0
    read_noise_e: float = 0.0
    seed: int = 0

    def __post_init__(self):
        if self.model not in NOISE_MODELS:
            raise ValueError(f"noise model must be one of {', '.join(NOISE_MODELS)}, got {self.model!r}")
        if self.model == "gaussian" and not self.snr_db >= MIN_SNR_DB:
            raise ValueError(f"snr_db {self.snr_db:g}: the noise would swamp the signal (σ "
                             f"{10 ** (-self.snr_db / 20):.3g} times each image's standard deviation); use a value "
                             f"of at least {MIN_SNR_DB:g} dB")


def sensor_pixels(geometry: CaptureGeometry) -> int:
    """Pixels across the field on the sensor."""
    return int(round(geometry.field_width_m / object_pixel_m(geometry)))


def simulation_layout(geometry: CaptureGeometry) -> BandLayout:
    """The grids a simulation of ``geometry`` works on (the recovery's: the smallest the band allows)."""
    return band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, sensor_size=sensor_pixels(geometry))


def field_spectrum(field: np.ndarray, size: int) -> np.ndarray:
    """Centred spectrum of a square field, cropped or zero-padded to ``size`` (field values kept), complex64."""
    n = field.shape[-1]
    spectrum = fft.fft2c(np.asarray(field).astype(np.complex64))
    return spectrum if n == size else fft.resize_spectrum(spectrum, (size, size)) * np.float32(size / n)


def simulate(field, geometry: CaptureGeometry, *, noise: Noise = Noise(model="none"), store_size: int | None = None,
             aberration: np.ndarray | None = None, progress: ProgressFn = silent) -> np.ndarray:
    """The images of ``field`` the geometry's cameras record.

    Parameters
    ----------
    field : ndarray, (S, S)
        The object's field over the geometry's field of view (complex, or a real amplitude).
    geometry : CaptureGeometry
    noise : Noise
    store_size : int, optional
        Side of the stored images (default: the sensor's pixels across the field).
    aberration : ndarray, (n, n, modes), optional
        Zernike coefficients (waves) of a lens aberration at ``n x n`` field points
        (:func:`~cca_cli.optics.field_aberration.field_varying_intensity`).
    progress : callable, optional

    Returns
    -------
    ndarray, float32, (K, store_size, store_size)
        Intensities, centred, in the object's units squared (irradiance).

    Raises
    ------
    ValueError
        Images that hold nothing (a black scene, or too few photons).
    """
    layout = simulation_layout(geometry)
    size = sensor_pixels(geometry) if store_size is None else int(store_size)
    spectrum = field_spectrum(field, layout.hires_size)
    if aberration is None:
        band = ForwardModel.unaberrated(layout).sensor_intensity(spectrum)
    else:
        band = field_varying_intensity(spectrum, layout, aberration, size)
    return record(band, size, noise, progress=progress)


def record(band: np.ndarray, size: int, noise: Noise, *, rng: np.random.Generator | None = None,
           progress: ProgressFn = silent, step: int = 16) -> np.ndarray:
    """Band-grid images (K, m, m) → float32 images (K, size, size) with ``noise``, in blocks of ``step`` images.

    The noise is drawn from ``rng`` (default: a generator seeded with ``noise.seed``), image by image, so
    the result does not depend on ``step``. Reports ``simulate/captures`` progress after each block.

    Raises
    ------
    ValueError
        ``photons_per_unit`` too small for the brightest pixel to collect one photo-electron, or every
        image zero.
    """
    k = band.shape[0]
    if noise.model == "poisson" and float(band.max(initial=0.0)) * noise.photons_per_unit < 1:
        raise ValueError(f"photons_per_unit: the brightest pixel would collect "
                         f"{float(band.max(initial=0.0)) * noise.photons_per_unit:.2g} photo-electrons, so the images "
                         "would hold noise only; raise photons_per_unit")
    rng = np.random.default_rng(noise.seed) if rng is None else rng
    intensity = np.empty((k, size, size), np.float32)
    for start in range(0, k, step):
        block = fft.fourier_resample(band[start:start + step], size)
        if noise.model == "gaussian":
            block = add_gaussian_noise(block, noise.snr_db, rng)
        elif noise.model == "poisson":
            block = add_shot_and_read_noise(block, photons_per_unit=noise.photons_per_unit,
                                            read_noise_e=noise.read_noise_e, rng=rng)
        intensity[start:start + step] = block
        progress(ProgressEvent("simulate", "captures", min(start + step, k), k))
    if not intensity.any():
        raise ValueError("every simulated image is zero (a black scene, or too few photons: photons_per_unit); "
                         "nothing could be recovered from it")
    return intensity
