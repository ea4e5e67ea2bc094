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

from dataclasses import dataclass

import numpy as np

from cca_cli.engines.base import IterativeEngine, check_options
from cca_cli.engines.passes import ChunkedPass
from cca_cli.engines.problem import PhaseRetrievalProblem, initial_spectrum
from cca_cli.engines.projections import project_magnitudes
from cca_cli.optics import kernels

__all__ = ["AltMinOptions", "AlternatingMinimization"]


@dataclass(frozen=True)
class AltMinOptions:
    """Options of the alternating-minimization engine.

    Attributes
    ----------
    tau : float
        Tikhonov weight τ added to ``Σ |P_i|²`` (same units: pupil power; a
        spectrum pixel seen by one capture has ``Σ |P_i|² = 1``).
    max_iterations : int
        Iteration cap (paper: 1000).
    tol : float
        Stop when the relative spectrum change ``‖ΔS‖/‖S‖`` falls below it (paper: 1e-5).
    chunk : int
        Captures processed together (cache-sized).
    threads : int or None
        Worker threads; None uses every core.
    """

    tau: float = 1e-3
    max_iterations: int = 1000
    tol: float = 1e-5
    chunk: int = 16
    threads: int | None = None

    def __post_init__(self):
        check_options([
            (0 <= self.tau < np.inf, f"tau must be a finite number ≥ 0, got {self.tau}"),
            (self.max_iterations >= 1, f"max_iterations must be ≥ 1, got {self.max_iterations}"),
            (0 <= self.tol < np.inf, f"tol must be a finite number ≥ 0, got {self.tol}"),
            (_is_count(self.chunk), f"chunk must be an integer ≥ 1, got {self.chunk!r}"),
            (self.threads is None or _is_count(self.threads),
             f"threads must be an integer ≥ 1 or null, got {self.threads!r}"),
        ])


def _is_count(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1


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
        self._iteration = 0
        self._change = np.inf

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
        self._change = float(np.sqrt(squared_change / max(norm, 1e-30)))
        self._spectrum, self._next = self._next, self._spectrum
        self._iteration += 1
        return float(np.sqrt(misfit / max(self._data_norm, 1e-30))), self._change

    def done(self) -> bool:
        """Stop at ``max_iterations`` or when the relative change drops below ``tol``."""
        return self._iteration >= self.options.max_iterations or self._change < self.options.tol

    def spectrum(self) -> np.ndarray:
        """Current spectrum estimate (complex64, M x M)."""
        return self._spectrum

    def state(self) -> dict:
        """The spectrum, the iteration count and the last change: all an iteration depends on."""
        return {"spectrum": self._spectrum, "iteration": self._iteration, "change": self._change}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state`."""
        self._spectrum[...] = state["spectrum"]
        self._iteration = int(state["iteration"])
        self._change = float(state["change"])

    def close(self) -> None:
        """Stop worker threads."""
        self._pass.close()
