"""The data an engine works on: forward model, measured amplitudes, validity weights."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cca_cli.engines.illumination import PositionModel, StageModel
from cca_cli.engines.side_by_side import run_side_by_side
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel, to_model_layout, to_sensor_layout

__all__ = ["MeasuredAmplitudes", "PhaseRetrievalProblem", "initial_spectrum", "zero_phase_spectrum",
           "sensor_amplitudes"]


class MeasuredAmplitudes:
    """What every engine needs from measured amplitudes ``self.amplitudes``, computed once."""

    @cached_property
    def capture_energies(self) -> np.ndarray:
        """``Σ A²`` of each capture (float64, (K,)), summed without a double-precision copy of the data."""
        flat = self.amplitudes.reshape(self.amplitudes.shape[0], -1)
        return np.einsum("ki,ki->k", flat, flat, dtype=np.float64)

    @cached_property
    def energy(self) -> float:
        """``Σ A²`` over all measurements (float64): the norm the data misfit is relative to."""
        return float(self.capture_energies.sum())

    @cached_property
    def amplitude_floor(self) -> float:
        """Floor on modelled magnitudes in the projections: 1e-6 of the mean measured amplitude."""
        return float(1e-6 * np.mean(self.amplitudes)) or 1e-12


@dataclass(frozen=True)
class PhaseRetrievalProblem(MeasuredAmplitudes):
    """Measurements prepared for the forward model.

    Attributes
    ----------
    model : ForwardModel
    amplitudes : ndarray, float32, (K, m, m)
        ``√I`` in model units and field layout.
    weights : ndarray, float32, (K, m, m) or None
        Per-pixel confidence in [0, 1] (0: the pixel does not constrain the
        magnitude update), field layout; None means all pixels count fully.
    pupil_index : ndarray, int, (K,) or None
        Camera (pupil) of each capture for engines that recover one pupil per
        camera; None: every capture through the same lens.
    position_model : PositionModel or None
        How the whole set of pupil centres may move (an LED array's shift,
        rotation and height; a stage's shift, rotation and scale), for engines
        that calibrate positions; None: a stage model of the nominal centres.
    aberration : ndarray, (n_modes,) or (P, n_modes), or None
        Known Zernike phase coefficients (waves, modes of
        :func:`~cca_cli.optics.zernike.zernike_modes`) of the pupil(s),
        e.g. a known defocus; engines start from it.
    initial_pupil : ndarray, complex, (n, n), or None
        A known pupil (aberration and apodisation) with the objective's NA disc
        inscribed in the array, for every camera; engines start from it.
    """

    model: ForwardModel
    amplitudes: np.ndarray
    weights: np.ndarray | None = None
    pupil_index: np.ndarray | None = None
    position_model: PositionModel | None = None
    aberration: np.ndarray | None = None
    initial_pupil: np.ndarray | None = None

    def __post_init__(self):
        expected = (self.model.n_images,) + self.model.field_shape
        if self.amplitudes.shape != expected:
            raise ValueError(f"amplitudes must have shape {expected}, got {self.amplitudes.shape}")
        if self.weights is not None and self.weights.shape != expected:
            raise ValueError(f"weights must have shape {expected}, got {self.weights.shape}")
        if self.pupil_index is not None:
            index = np.asarray(self.pupil_index)
            if index.shape != (self.model.n_images,) or index.dtype.kind not in "iu" or index.min() < 0:
                raise ValueError(f"pupil_index must hold one non-negative integer per capture, got {index!r}")
        if self.position_model is None:
            object.__setattr__(self, "position_model", StageModel(self.model.layout.centres_px))

    def pupil_indices(self) -> np.ndarray:
        """Pupil (camera) of each capture, compacted to ``0 … P-1`` (all 0 when none are given)."""
        if self.pupil_index is None:
            return np.zeros(self.model.n_images, np.int64)
        return np.unique(np.asarray(self.pupil_index), return_inverse=True)[1].astype(np.int64).ravel()

    @classmethod
    def from_sensor_images(cls, model: ForwardModel, images: np.ndarray, weights: np.ndarray | None = None, *,
                           threads: int = 1, **calibration) -> "PhaseRetrievalProblem":
        """Prepare captures recorded on the sensor grid.

        Parameters
        ----------
        model : ForwardModel
        images : ndarray, (K, N, N)
            Sensor intensities (irradiance units, centred sensor layout). When
            ``N`` exceeds the model grid m they are reduced exactly by Fourier
            cropping (the intensity band fits in m); negative values (noise)
            are clipped to 0.
        weights : ndarray, (K, N, N), optional
            Validity weights in [0, 1] on the same grid (resampled by area when N > m).
        threads : int
            Threads that resample the weights (the same result for any count).
        **calibration
            ``pupil_index``, ``position_model``, ``aberration``, ``initial_pupil`` (see the class).
        """
        amplitudes, resampled_weights = sensor_amplitudes(model, images, weights, count=model.n_images,
                                                          threads=threads)
        return cls(model=model, amplitudes=amplitudes, weights=resampled_weights, **calibration)

    def sensor_intensities(self) -> np.ndarray:
        """Measured intensities back in sensor units and layout on the model grid (K, m, m)."""
        return to_sensor_layout(self.amplitudes.astype(np.float32) ** 2) / np.float32(self.model.intensity_scale)


def sensor_amplitudes(model: ForwardModel, images: np.ndarray, weights: np.ndarray | None = None, *,
                      count: int | None = None, threads: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """Sensor images (and weights) → amplitudes ``√I`` in model units and field layout on the m grid.

    Parameters
    ----------
    model : ForwardModel
        Supplies the grid m and the intensity scale.
    images : ndarray, (k, N, N)
        Sensor intensities, centred; reduced exactly by Fourier cropping when
        ``N > m``; negative values (noise) are clipped to 0.
    weights : ndarray, (k, N, N), optional
        Validity weights in [0, 1], resampled by area when ``N > m``.
    count : int, optional
        Required number of images k.
    threads : int
        Threads that convert the images and resample the weights, a contiguous share of the images each (the
        same result for any count).

    Returns
    -------
    amplitudes : ndarray, float32, (k, m, m)
    weights : ndarray, float32, (k, m, m) or None
    """
    images = np.asarray(images)
    m = model.layout.lowres_size
    k = images.shape[0] if count is None else count
    if images.ndim != 3 or images.shape[0] != k or images.shape[1] != images.shape[2]:
        raise ValueError(f"captures must have shape ({k}, N, N), got {images.shape}")
    if images.shape[-1] < m:
        raise ValueError(f"captures are {images.shape[-1]} px, smaller than the model grid {m}")
    amplitudes = np.empty((k, m, m), np.float32)
    scale = np.float32(model.intensity_scale)
    # Small blocks keep the transient full-size spectra well below the capture stack itself.
    block_size = 8
    blocks = np.array_split(np.arange(0, k, block_size), max(1, min(int(threads), -(-k // block_size))))

    def share(t: int) -> None:   # numpy lets go of the GIL on whole blocks
        for start in blocks[t]:
            block = fft.fourier_resample(images[start:start + block_size], m)
            np.clip(block, 0, None, out=block)
            amplitudes[start:start + block_size] = to_model_layout(np.sqrt(block * scale))

    run_side_by_side(share, len(blocks))
    resampled_weights = None
    if weights is not None:
        resampled_weights = _weights_in_model_layout(np.asarray(weights, np.float32), m, threads)
    return amplitudes, resampled_weights


def _weights_in_model_layout(weights: np.ndarray, size: int, threads: int = 1, block_size: int = 8) -> np.ndarray:
    """Weights clipped to [0, 1], resampled by area to ``size`` when larger, in field layout (float32).

    A few images at a time into one array, a contiguous share of them per thread: whole-stack temporaries
    would each take fresh pages.
    """
    n = weights.shape[-1]
    out = np.empty((len(weights), size, size), np.float32)
    blocks = np.array_split(np.arange(0, len(weights), block_size),
                            max(1, min(int(threads), -(-len(weights) // block_size))))
    if n != size:
        from scipy import ndimage

    def resampled(image: np.ndarray) -> np.ndarray:
        return ndimage.zoom(image, size / n, order=1, grid_mode=True, mode="nearest")[:size, :size]

    def share(t: int) -> None:   # numpy and scipy.ndimage let go of the GIL
        for start in blocks[t]:
            block = weights[start:start + block_size]
            if n != size:
                block = np.stack([resampled(image) for image in block])
            out[start:start + block_size] = to_model_layout(np.clip(block, 0, 1))

    run_side_by_side(share, len(blocks))
    return out


def initial_spectrum(problem: PhaseRetrievalProblem) -> np.ndarray:
    """The paper's start: the scaled Fourier transform of the mean low-resolution image.

    The amplitude ``√mean(I)`` is interpolated (band-limited) to the M x M grid,
    given zero phase and transformed; its scale matches the measurements.

    Returns
    -------
    ndarray, complex64, (M, M)
    """
    return zero_phase_spectrum(problem.model, np.mean(problem.amplitudes.astype(np.float32) ** 2, axis=0))


def zero_phase_spectrum(model: ForwardModel, power: np.ndarray) -> np.ndarray:
    """Spectrum of the zero-phase object whose low-resolution image is ``power``.

    Parameters
    ----------
    model : ForwardModel
    power : ndarray, float32, (m, m)
        Image ``|ψ|²`` in model units and field layout.

    Returns
    -------
    ndarray, complex64, (M, M)
        ``fft2c`` of ``√I`` band-limited-interpolated to the M x M grid, ``I`` the image in sensor units.
    """
    intensity = to_sensor_layout(power) / model.intensity_scale
    amplitude = np.sqrt(np.clip(fft.fourier_resample(intensity[None], model.layout.hires_size)[0], 0, None))
    return fft.fft2c(amplitude.astype(np.complex64)).astype(np.complex64)
