"""Phase retrieval from multiplexed captures (several sources summed into one image).

The alternating minimization of :mod:`cca_cli.engines.altmin` runs unchanged
over the *virtual captures* (one per camera, pattern and active source); only
the magnitude projection differs: the fields of one measurement are scaled
together so that their summed intensity matches the image,

    ψ_i ← √(I_g / Σ_{j ∈ g} |ψ_j|²) · ψ_i     for every i in measurement g,

and chunks are aligned with measurements so a group is never split.

References
----------
Holloway et al., IEEE Trans. Comput. Imaging 2(3), 2016, Section VII.
:DOI:`10.1109/TCI.2016.2557067`
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.engines.altmin import AlternatingMinimization
from cca_cli.engines.options import AltMinOptions
from cca_cli.engines.problem import MeasuredAmplitudes, sensor_amplitudes, zero_phase_spectrum
from cca_cli.engines.projections import project_grouped_magnitudes
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.multiplex import MultiplexedForwardModel, group_chunk_slices

__all__ = ["MultiplexedProblem", "MultiplexedAlternatingMinimization", "initial_multiplexed_spectrum"]


@dataclass(frozen=True)
class MultiplexedProblem(MeasuredAmplitudes):
    """Multiplexed measurements prepared for the virtual-capture forward model.

    Attributes
    ----------
    model : ForwardModel
        Linear part: one capture per virtual capture (V of them).
    amplitudes : ndarray, float32, (G, m, m)
        ``√I_g`` per measurement, model units, field layout.
    group_offsets : ndarray, int64, (G + 1,)
        Measurement ``g`` is virtual captures ``group_offsets[g]:group_offsets[g + 1]``.
    weights : ndarray, float32, (G, m, m) or None
        Per-pixel confidence of each measurement in [0, 1].
    """

    model: ForwardModel
    amplitudes: np.ndarray
    group_offsets: np.ndarray
    weights: np.ndarray | None = None

    def __post_init__(self):
        offsets = np.asarray(self.group_offsets)
        if offsets.ndim != 1 or offsets[0] != 0 or offsets[-1] != self.model.n_images or np.any(np.diff(offsets) < 1):
            raise ValueError(f"group offsets must rise from 0 to {self.model.n_images} in steps ≥ 1")
        expected = (len(offsets) - 1,) + self.model.field_shape
        if self.amplitudes.shape != expected:
            raise ValueError(f"amplitudes must have shape {expected}, got {self.amplitudes.shape}")
        if self.weights is not None and self.weights.shape != expected:
            raise ValueError(f"weights must have shape {expected}, got {self.weights.shape}")

    @property
    def n_measurements(self) -> int:
        """G."""
        return int(self.amplitudes.shape[0])

    @classmethod
    def from_sensor_images(cls, model: MultiplexedForwardModel, images: np.ndarray,
                           weights: np.ndarray | None = None) -> "MultiplexedProblem":
        """Prepare multiplexed images recorded on the sensor grid.

        Parameters
        ----------
        model : MultiplexedForwardModel
        images : ndarray, (G, N, N)
            One image per (pattern, camera), ordered as ``model.geometry`` numbers measurements.
        weights : ndarray, (G, N, N), optional
            Validity weights in [0, 1] on the same grid.
        """
        amplitudes, resampled = sensor_amplitudes(model.model, images, weights, count=model.n_measurements)
        return cls(model=model.model, amplitudes=amplitudes, group_offsets=model.group_offsets, weights=resampled)


def initial_multiplexed_spectrum(problem: MultiplexedProblem) -> np.ndarray:
    """Start from the mean image per active source, as the single-source engine does.

    Each measurement is divided by its number of sources before averaging, so
    the start has the scale of one virtual capture; with one source per
    measurement this equals :func:`~cca_cli.engines.problem.initial_spectrum`.
    """
    sizes = np.diff(problem.group_offsets).astype(np.float32)
    power = problem.amplitudes.astype(np.float32) ** 2
    return zero_phase_spectrum(problem.model, np.mean(power / sizes[:, None, None], axis=0))


class MultiplexedAlternatingMinimization(AlternatingMinimization):
    """Alternating minimization with the joint (grouped) magnitude projection.

    Parameters
    ----------
    problem : MultiplexedProblem
    options : AltMinOptions
        ``chunk`` counts virtual captures; whole measurements are kept together.
    spectrum : ndarray, complex64, (M, M), optional
        Starting spectrum; default :func:`initial_multiplexed_spectrum`.
    """

    name = "altmin"

    def __init__(self, problem: MultiplexedProblem, options: AltMinOptions = AltMinOptions(),
                 spectrum: np.ndarray | None = None):
        if spectrum is None:
            spectrum = initial_multiplexed_spectrum(problem)
        super().__init__(problem, options, spectrum)

    def _pass_slices(self) -> list[slice]:
        return group_chunk_slices(self.problem.group_offsets, self.options.chunk)

    def _project(self, fields: np.ndarray, images: slice, scratch: np.ndarray) -> float:
        offsets = self.problem.group_offsets
        g0, g1 = (int(v) for v in np.searchsorted(offsets, [images.start, images.stop]))
        local = offsets[g0:g1 + 1] - images.start
        weights = None if self.problem.weights is None else self.problem.weights[g0:g1]
        return project_grouped_magnitudes(fields, self.problem.amplitudes[g0:g1], scratch, local,
                                          weights=weights, eps=self._eps)

