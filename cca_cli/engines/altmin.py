"""The paper's alternating minimization with a closed-form Tikhonov Fourier update.

Each iteration computes every capture's sensor field from the current
spectrum, replaces its magnitude with the measured one, and solves

    S = argmin Σ_i ‖A_i S − ψ_i‖² + τ ‖S‖²  =  Σ_i A_iᴴ ψ_i / (Σ_i |P_i|² + τ)

in closed form (the normal operator is diagonal).

References
----------
Holloway et al., IEEE Trans. Comput. Imaging 2(3), 2016, Section IV.
:DOI:`10.1109/TCI.2016.2557067`
"""

from __future__ import annotations

import numpy as np

from cca_cli.engines.base import IterativeEngine
from cca_cli.engines.options import AltMinOptions
from cca_cli.engines.passes import ChunkedPass
from cca_cli.engines.problem import PhaseRetrievalProblem, initial_spectrum
from cca_cli.engines.projections import project_magnitudes
from cca_cli.engines.stopping import StoppingPolicy
from cca_cli.optics import kernels

__all__ = ["AltMinOptions", "AlternatingMinimization"]


class AlternatingMinimization(IterativeEngine):
    """Alternating minimization (magnitude projection + Tikhonov least squares).

    Parameters
    ----------
    problem : PhaseRetrievalProblem
    options : AltMinOptions
    spectrum : ndarray, complex64, (M, M), optional
        Starting spectrum; default :func:`~cca_cli.engines.problem.initial_spectrum`.
    """

    name = "altmin"

    def __init__(self, problem: PhaseRetrievalProblem, options: AltMinOptions = AltMinOptions(),
                 spectrum: np.ndarray | None = None):
        self.problem = problem
        self.options = options
        model = problem.model
        self._spectrum = (initial_spectrum(problem) if spectrum is None else spectrum).astype(np.complex64)
        self._next = np.empty_like(self._spectrum)
        self._inverse_normal = (1.0 / (model.normal_diagonal() + np.float32(options.tau + 1e-30))).astype(np.float32)
        self._pass = ChunkedPass(model, chunk=options.chunk, threads=options.threads, slices=self._pass_slices())
        self._data_norm = problem.energy
        self._eps = problem.amplitude_floor
        self.stopping = StoppingPolicy(max_iterations=options.max_iterations, tol=options.tol, plateau=options.plateau,
                                       plateau_window=options.plateau_window)

    def _pass_slices(self) -> list[slice] | None:
        """Capture ranges processed together (None: plain chunks); subclasses keep groups whole."""
        return None

    def _project(self, fields: np.ndarray, images: slice, scratch: np.ndarray) -> float:
        weights = None if self.problem.weights is None else self.problem.weights[images]
        return project_magnitudes(fields, self.problem.amplitudes[images], scratch, weights=weights, eps=self._eps)

    def update(self) -> tuple[float, float]:
        """One iteration: project every capture, then the closed-form Fourier update."""
        misfit = self._pass.run(self._spectrum, self._project, self._next)
        squared_change, norm = kernels.tikhonov_update(self._next, self._inverse_normal, self._spectrum)
        change = float(np.sqrt(squared_change / max(norm, 1e-30)))
        self._spectrum, self._next = self._next, self._spectrum
        self.stopping.record(misfit, change)
        return float(np.sqrt(misfit / max(self._data_norm, 1e-30))), change

    def spectrum(self) -> np.ndarray:
        """Current spectrum estimate (complex64, M x M)."""
        return self._spectrum

    def state(self) -> dict:
        """The spectrum and the stopping counters: all an iteration depends on."""
        return {"spectrum": self._spectrum, **self.stopping.state()}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state`."""
        self._spectrum[...] = state["spectrum"]
        self.stopping.restore(state)

    def close(self) -> None:
        """Stop worker threads."""
        self._pass.close()
