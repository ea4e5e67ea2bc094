"""A sequential engine with momentum (rPIE/mPIE style) on the paper's operators.

Captures are visited centre-out (by distance of their pupil from DC) in small
batches, in shells that grow away from DC (:mod:`cca_cli.engines.schedule`).
Within a shell, captures whose pupil boxes lie wholly above (or left of) a line
never touch those wholly below (or right of) it, so two threads update those
groups side by side and the result equals visiting them one after the other.
With numba and FFTW each thread's run of batches is a single GIL-free call
(:func:`~cca_cli.optics.kernels.sequential_lane`).

For each batch the fields ``ψ_i = A_i S`` are computed from the current
spectrum, the data step ``ψ'_i − ψ_i`` is formed (magnitude replacement, or a
Poisson-likelihood gradient step), and the spectrum is updated at once
(rPIE's regularised step, summed over the batch):

    S += β Σ_i R_iᵀ P_i* F(ψ'_i − ψ_i) / ((1 − α) D_B + α max D_B + τ),
    D_B = Σ_{i∈B} R_iᵀ |P_i|²

so a batch of one capture is exactly rPIE. After each pass over all captures
the spectrum takes a momentum step (mPIE):

    v ← η v + (S − S_prev),   S ← S + η v

where ``S_prev`` is the spectrum after the previous momentum step. (mPIE
allows momentum every ``T`` positions; with the dense overlap of a camera
array, steps more often than once a pass were found to diverge.) One iteration is one pass
over all captures; it costs the same FFTs as one iteration of
:class:`~cca_cli.engines.altmin.AlternatingMinimization` (two per capture).

Optionally the engine refines sub-pixel aperture positions as it goes
(:mod:`cca_cli.engines.calibration`), after ``calibration_start`` iterations
and every ``calibration_every`` iterations, each change accepted only where it
lowers the data misfit.

Pupil recovery (``pupil_recovery="shared"``) fits one Zernike phase shared by
all captures. Its quadratic part starts from
:func:`~cca_cli.engines.calibration.estimate_quadratic_aberration` (the shifts
between neighbouring captures); then every pass also accumulates, from the
same batch residuals ``G_i = F(ψ'_i − ψ_i)`` that update the object, the
Gauss-Newton system of the linearised pupil fit ``i P_i S_i Σ_j δa_j B_j ≈ G_i``:

    H_jl = Σ_i Σ_k |P_i S_i|² B_j B_l,    r_j = Σ_i Σ_k B_j Im(conj(P_i S_i) G_i)

(EPRY's pupil step projected onto the Zernike modes), and the coefficients take
the step ``β_p H⁻¹ r`` at the end of the pass. A step after which the next
pass fits the data worse is undone and ``β_p`` halved, so recovery on data
from a perfect pupil stays at (nearly) zero aberration.

References
----------
Maiden & Rodenburg, Ultramicroscopy 109 (2009) (ePIE); Maiden, Johnson & Li,
Optica 4(7) (2017) (rPIE, mPIE).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from cca_cli.engines import calibration as cal
from cca_cli.engines.base import IterativeEngine, check_options
from cca_cli.engines.problem import PhaseRetrievalProblem, initial_spectrum
from cca_cli.engines.schedule import build_schedule
from cca_cli.optics import fft, kernels
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils

__all__ = ["MomentumOptions", "Calibration", "SequentialMomentum"]

_COSTS = ("amplitude", "poisson")
_PUPILS = ("none", "shared")
#: Largest change of any pupil coefficient in one pass (waves): the linearisation holds within ~0.05.
_MAX_PUPIL_STEP = 0.1


@dataclass(frozen=True)
class MomentumOptions:
    """Options of the sequential momentum engine.

    Attributes
    ----------
    tau : float
        Added to the update denominator (pupil-power units, as AltMin's τ).
    max_iterations : int
        Cap on passes over all captures.
    tol : float
        Stop when the relative spectrum change of a pass falls below it.
    alpha : float
        rPIE regularisation α in [0, 1]: 0 divides by the batch's pupil power
        (ePIE-like full projection), 1 by its maximum (small, uniform steps).
    beta : float
        Step size β in (0, 2).
    eta : float
        Momentum η in [0, 1); 0 gives plain (batched) rPIE.
    batch : int
        Captures updated together (1: strictly one aperture at a time). Shells
        of 2, 2, 4, 4, 8, … batches are visited in turn.
    cost : str
        ``"amplitude"`` (magnitude replacement) or ``"poisson"`` (a gradient
        step on the Poisson likelihood, ``ψ' = ψ (1 − μ (1 − I/|ψ|²))``).
    poisson_step : float
        μ of the Poisson step; 0.5 makes the magnitude update a Newton step
        towards ``√I``.
    position_refinement : bool
        Refine sub-pixel aperture positions.
    position_steps : tuple of float
        Trial steps (pixels) of each position refinement round.
    calibration_start : int
        Iterations before the first calibration round (let the object settle first).
    calibration_every : int
        Iterations between calibration rounds.
    pupil_recovery : str
        ``"none"`` or ``"shared"`` (one Zernike pupil phase for all captures).
    pupil_order : int
        Highest Zernike radial order recovered: 2 (defocus, astigmatism ×2),
        3 (+ coma ×2, trefoil ×2) or 4 (+ spherical and four more).
    pupil_step : float
        Initial Gauss-Newton step fraction β_p in (0, 1].
    pupil_estimate : bool
        Start the quadratic modes from the neighbour-shift estimate (else from zero).
    threads : int or None
        Worker threads; None uses every core (at most 2 are used). The result
        does not depend on it beyond float rounding.
    """

    tau: float = 1e-3
    max_iterations: int = 200
    tol: float = 1e-5
    alpha: float = 0.1
    beta: float = 1.0
    eta: float = 0.7
    batch: int = 12
    cost: str = "amplitude"
    poisson_step: float = 0.5
    position_refinement: bool = False
    position_steps: tuple[float, ...] = (1.0, 0.5, 0.25, 0.125, 0.0625)
    calibration_start: int = 3
    calibration_every: int = 2
    pupil_recovery: str = "none"
    pupil_order: int = 2
    pupil_step: float = 1.0
    pupil_estimate: bool = True
    threads: int | None = None

    def __post_init__(self):
        check_options([
            (self.tau >= 0, f"tau must be ≥ 0, got {self.tau}"),
            (self.max_iterations >= 1, f"max_iterations must be ≥ 1, got {self.max_iterations}"),
            (self.tol >= 0, f"tol must be ≥ 0, got {self.tol}"),
            (0 <= self.alpha <= 1, f"alpha must be in [0, 1], got {self.alpha}"),
            (0 < self.beta < 2, f"beta must be in (0, 2), got {self.beta}"),
            (0 <= self.eta < 1, f"eta must be in [0, 1), got {self.eta}"),
            (self.batch >= 1, f"batch must be ≥ 1, got {self.batch}"),
            (self.cost in _COSTS, f"cost must be one of {', '.join(_COSTS)}, got {self.cost!r}"),
            (0 < self.poisson_step <= 1, f"poisson_step must be in (0, 1], got {self.poisson_step}"),
            (len(self.position_steps) >= 1 and all(s > 0 for s in self.position_steps),
             f"position_steps must be positive, got {self.position_steps}"),
            (self.calibration_start >= 0, f"calibration_start must be ≥ 0, got {self.calibration_start}"),
            (self.calibration_every >= 1, f"calibration_every must be ≥ 1, got {self.calibration_every}"),
            (self.pupil_recovery in _PUPILS,
             f"pupil_recovery must be one of {', '.join(_PUPILS)}, got {self.pupil_recovery!r}"),
            (self.pupil_order in (2, 3, 4), f"pupil_order must be 2, 3 or 4, got {self.pupil_order}"),
            (0 < self.pupil_step <= 1, f"pupil_step must be in (0, 1], got {self.pupil_step}"),
        ])
        object.__setattr__(self, "position_steps", tuple(float(s) for s in self.position_steps))


@dataclass(frozen=True)
class Calibration:
    """The model calibration an engine arrived at (original capture order).

    Attributes
    ----------
    offsets : ndarray, float64, (K, 2)
        Pupil-centre offsets ``[dy, dx]`` from the nominal positions (spectrum pixels).
    pupils : ndarray, complex64, (K, b, b)
        The pupils in use.
    coefficients : ndarray, float64, (n_modes,) or None
        Recovered shared Zernike coefficients (waves, modes of
        :func:`~cca_cli.engines.calibration.zernike_modes`), None without pupil recovery.
    """

    offsets: np.ndarray
    pupils: np.ndarray
    coefficients: np.ndarray | None = None


class SequentialMomentum(IterativeEngine):
    """Centre-out batched rPIE with mPIE momentum and optional model calibration.

    Parameters
    ----------
    problem : PhaseRetrievalProblem
    options : MomentumOptions
    spectrum : ndarray, complex64, (M, M), optional
        Starting spectrum; default :func:`~cca_cli.engines.problem.initial_spectrum`.
    """

    name = "momentum"

    def __init__(self, problem: PhaseRetrievalProblem, options: MomentumOptions = MomentumOptions(),
                 spectrum: np.ndarray | None = None):
        self.problem = problem
        self.options = options
        model = problem.model
        layout = model.layout
        k = model.n_images
        cores = options.threads or fft.cpu_count()
        self._threads = 2 if cores > 1 and k > 1 else 1
        distances = np.hypot(layout.centres_px[:, 0], layout.centres_px[:, 1])
        self._schedule = build_schedule(layout.box_origins, layout.box_size, distances, options.batch)
        self._order = order = self._schedule.order
        self._layout = replace(layout, centres_px=layout.centres_px[order],
                               box_origins=layout.box_origins[order], box_centres=layout.box_centres[order])
        self._origin_array = np.ascontiguousarray(self._layout.box_origins, dtype=np.int64)
        self._amplitudes = np.ascontiguousarray(problem.amplitudes[order], dtype=np.float32)
        self._weights = None if problem.weights is None else np.ascontiguousarray(problem.weights[order], np.float32)
        self._intensities = np.square(self._amplitudes) if options.cost == "poisson" else None
        self._data_norm = problem.energy
        self._eps = problem.amplitude_floor

        self._spectrum = (initial_spectrum(problem) if spectrum is None else spectrum).astype(np.complex64)
        self._velocity = np.zeros_like(self._spectrum)
        self._anchor = self._spectrum.copy()

        capacity = max(sl.stop - sl.start for sl in self._schedule.batches)
        self._workspaces = [model.workspace(capacity, threads=1) for _ in range(self._threads)]
        self._scratch = [np.empty((capacity,) + model.field_shape, np.float32) for _ in range(self._threads)]
        self._pool = ThreadPoolExecutor(self._threads - 1) if self._threads > 1 else None
        self._calibration_workspace = None
        # The fused lane does the amplitude step only; Poisson steps and the pupil fit's sums run step by step.
        fusable = options.cost == "amplitude" and options.pupil_recovery == "none"
        self._fused_plans = [ws.box_fft.raw_plans() if fusable and ws.box_fft is not None else None
                             for ws in self._workspaces]
        if not all(kernels.can_fuse_lanes(raw) for raw in self._fused_plans):
            self._fused_plans = [None] * self._threads

        self._offsets = np.zeros((k, 2), np.float64)
        self._recover_pupil = options.pupil_recovery == "shared"
        self._coefficients = None
        if self._recover_pupil:
            n_modes = len(cal.zernike_modes(options.pupil_order))
            self._coefficients = np.zeros(n_modes)
            if options.pupil_estimate:
                self._coefficients[:3] = cal.estimate_quadratic_aberration(self._layout, self._amplitudes,
                                                                           self._weights)
            self._pupil_rhs = np.zeros((self._threads, n_modes))
            self._pupil_normal = np.zeros((self._threads, n_modes, n_modes))
            self._pupil_step = options.pupil_step
            self._pupil_previous = None  # (coefficients before the last step, misfit of the pass that made it)
            self._set_basis()
            self._set_model(self._pupils())
        else:
            self._set_model(model.pupils[order])
        self._iteration = 0
        self._change = np.inf

    # ------------------------------------------------------------ model state
    def _set_model(self, pupils: np.ndarray) -> None:
        """Use ``pupils`` (capture order of the engine) and precompute each capture's update factor."""
        self._model = model = ForwardModel(self._layout, pupils)
        layout = self._layout
        b, opts = layout.box_size, self.options
        power = np.abs(model.pupils) ** 2
        coverage = np.zeros(model.spectrum_shape, np.float32)
        factors = np.empty(model.pupils.shape, np.complex64)
        origins = self._origin_array
        scale = np.float32(opts.beta / layout.lowres_size)
        for sl in self._schedule.batches:
            for i in range(sl.start, sl.stop):
                y0, x0 = origins[i]
                coverage[y0:y0 + b, x0:x0 + b] += power[i]
            boxes = np.stack([coverage[y0:y0 + b, x0:x0 + b] for y0, x0 in origins[sl]])
            peak = float(np.max(boxes))
            denominator = (1.0 - opts.alpha) * boxes + opts.alpha * peak + opts.tau + 1e-30
            factors[sl] = scale * np.conj(model.pupils[sl]) / denominator
            for i in range(sl.start, sl.stop):
                y0, x0 = origins[i]
                coverage[y0:y0 + b, x0:x0 + b] = 0
        self._factors = factors

    def _pupils(self) -> np.ndarray:
        return cal.pupil_functions(self._layout, offsets=self._offsets, coefficients=self._coefficients,
                                   order=self.options.pupil_order)

    def _set_basis(self) -> None:
        """Zernike modes on each capture's (offset) disc, flattened per mode: (n_modes, K, b²)."""
        layout = self._layout
        centres = layout.box_centres + self._offsets
        disc = circular_pupils(layout.box_size, centres, layout.pupil_radius_px)
        basis = cal.zernike_basis(layout.box_size, centres, layout.pupil_radius_px, order=self.options.pupil_order)
        self._basis = (basis * disc).reshape(basis.shape[0], layout.n_images, -1)

    # ------------------------------------------------------------- data steps
    def _difference(self, fields: np.ndarray, images: slice, scratch: np.ndarray) -> float:
        """Replace ``fields`` by the data step ``ψ' − ψ``; return the squared amplitude misfit."""
        amplitudes = self._amplitudes[images]
        weights = None if self._weights is None else self._weights[images]
        if self.options.cost == "amplitude":
            return kernels.magnitude_step(fields, amplitudes, scratch, weights=weights, eps=self._eps)
        magnitude = np.abs(fields, out=scratch)
        misfit = magnitude - amplitudes
        if weights is not None:
            misfit *= np.sqrt(weights)
        squared = float(np.vdot(misfit.ravel(), misfit.ravel()))
        # Poisson cost: ψ' − ψ = −μ ψ (1 − I/|ψ|²); the floor on |ψ|² bounds the step where the model
        # is dark.
        np.square(magnitude, out=magnitude)
        np.maximum(magnitude, self._eps * self._eps + 1e-3 * self._intensities[images].mean(), out=magnitude)
        factor = np.divide(self._intensities[images], magnitude, out=magnitude)
        factor -= 1.0
        factor *= np.float32(self.options.poisson_step)
        if weights is not None:
            factor *= weights
        fields *= factor
        return squared

    def _half_batch(self, t: int, images: slice) -> float:
        """Fields → data step → spectrum-domain update boxes, in workspace ``t``."""
        if images.stop <= images.start:
            return 0.0
        ws = self._workspaces[t]
        k = images.stop - images.start
        fields = self._model.forward_into(self._spectrum, images, ws)
        misfit = self._difference(fields, images, self._scratch[t][:k])
        ws.forward(k)
        if self._recover_pupil:
            s, b = self._layout.lowres_box_start, self._layout.box_size
            self._accumulate_pupil(t, images, ws.fields[:k, s:s + b, s:s + b])
        return misfit

    def _accumulate_pupil(self, t: int, images: slice, residual: np.ndarray) -> None:
        """Add this batch's terms of the Gauss-Newton pupil system (see module notes)."""
        b = self._layout.box_size
        k = images.stop - images.start
        seen = np.stack([self._spectrum[y0:y0 + b, x0:x0 + b] for y0, x0 in self._origin_array[images]])
        seen *= self._model.pupils[images]
        # The raw transform of the workspace is m times the orthonormal one.
        gradient = np.imag(np.conj(seen) * residual).reshape(k, -1) / np.float32(self._layout.lowres_size)
        power = np.square(np.abs(seen)).reshape(k, -1)
        basis = self._basis[:, images].reshape(self._basis.shape[0], -1)
        self._pupil_rhs[t] += basis @ gradient.ravel()
        self._pupil_normal[t] += (basis * power.ravel()) @ basis.T

    def _update_pupil(self, misfit: float) -> None:
        """End-of-pass pupil step, undoing the previous one if this pass fit the data worse."""
        rhs, normal = self._pupil_rhs.sum(axis=0), self._pupil_normal.sum(axis=0)
        self._pupil_rhs[:] = 0
        self._pupil_normal[:] = 0
        previous = self._pupil_previous
        if previous is not None and misfit > previous[1]:
            self._coefficients = previous[0]
            self._pupil_step *= 0.5
            self._pupil_previous = None
            self._set_model(self._pupils())
            return
        trace = float(np.trace(normal))
        if not trace > 0:
            return
        damped = normal + 1e-3 * trace / normal.shape[0] * np.eye(normal.shape[0])
        step = self._pupil_step * np.linalg.solve(damped, rhs)
        largest = float(np.max(np.abs(step)))
        if largest > _MAX_PUPIL_STEP:
            step *= _MAX_PUPIL_STEP / largest
        self._pupil_previous = (self._coefficients.copy(), misfit)
        self._coefficients = self._coefficients + step
        self._set_model(self._pupils())

    def _scatter(self, t: int, images: slice) -> None:
        """Add the batch's weighted update boxes (workspace ``t``) to the spectrum."""
        k = images.stop - images.start
        if k > 0:
            kernels.scatter_boxes(self._workspaces[t].fields[:k], self._origin_array, self._factors, self._spectrum,
                                  images.start)

    # ------------------------------------------------------------ calibration
    def _calibrate(self) -> None:
        """One position-refinement round against the current spectrum; the model follows the new offsets."""
        opts = self.options
        if self._calibration_workspace is None:
            self._calibration_workspace = self._model.workspace(min(32, self._model.n_images), threads=1)
        self._offsets, _ = cal.refine_positions(
            self._layout, self._spectrum, self._amplitudes, self._weights, self._offsets,
            steps=opts.position_steps, coefficients=self._coefficients, order=opts.pupil_order,
            workspace=self._calibration_workspace)
        if self._recover_pupil:
            self._set_basis()
        self._set_model(self._pupils())

    def _run_lane(self, t: int, batches: tuple[slice, ...]) -> float:
        """Run ``batches`` one after the other on thread ``t``; returns their summed misfit."""
        raw = self._fused_plans[t]
        if raw is not None:  # one compiled call for the whole lane: the threads never wait for the interpreter
            bounds = np.array([[sl.start, sl.stop] for sl in batches], dtype=np.int64).reshape(-1, 2)
            return kernels.sequential_lane(raw, bounds, self._spectrum, self._origin_array, self._model.pupil_boxes,
                                           self._factors, self._workspaces[t].fields, self._amplitudes,
                                           self._weights, self._eps)
        misfit = 0.0
        for sl in batches:
            misfit += self._half_batch(t, sl)
            self._scatter(t, sl)
        return misfit

    @staticmethod
    def _lane_size(batches: tuple[slice, ...]) -> int:
        return sum(sl.stop - sl.start for sl in batches)

    def _shared_batch(self, sl: slice) -> float:
        """One batch computed by both threads (half each), then scattered in order."""
        middle = sl.start + (sl.stop - sl.start + 1) // 2
        first, second = slice(sl.start, middle), slice(middle, sl.stop)
        future = self._pool.submit(self._half_batch, 1, second)
        misfit = self._half_batch(0, first)
        misfit += future.result()
        self._scatter(0, first)
        self._scatter(1, second)
        return misfit

    def _pass(self) -> tuple[float, float]:
        """One pass over all captures plus the momentum step; returns the misfit and the relative change."""
        misfit = 0.0
        for phase in self._schedule.phases:
            if self._pool is None:
                misfit += sum(self._run_lane(0, lane) for lane in phase.lanes)
            elif len(phase.lanes) == 1:
                for sl in phase.lanes[0]:
                    misfit += self._shared_batch(sl)
            else:
                # Lanes touch disjoint parts of the spectrum: running them together equals running them in turn.
                # The calling thread takes the longer lane: it waits least for the interpreter between kernels.
                own, other = phase.lanes
                if self._lane_size(other) > self._lane_size(own):
                    own, other = other, own
                future = self._pool.submit(self._run_lane, 1, other)
                misfit += self._run_lane(0, own) + future.result()
        change, norm = kernels.momentum_step(self._spectrum, self._anchor, self._velocity, self.options.eta)
        if self._recover_pupil:
            self._update_pupil(misfit)
        return misfit, float(np.sqrt(change / max(norm, 1e-30)))

    def _calibration_due(self) -> bool:
        opts = self.options
        if not opts.position_refinement:
            return False
        since = self._iteration - opts.calibration_start
        return since >= 0 and since % opts.calibration_every == 0

    # ------------------------------------------------------------------ loop
    def update(self) -> tuple[float, float]:
        """One pass over all captures (with a calibration round first when one is due)."""
        if self._calibration_due():
            self._calibrate()
        misfit, self._change = self._pass()
        self._iteration += 1
        return float(np.sqrt(misfit / max(self._data_norm, 1e-30))), self._change

    def done(self) -> bool:
        """Stop at ``max_iterations`` or when a pass changes the spectrum by less than ``tol``."""
        return self._iteration >= self.options.max_iterations or self._change < self.options.tol

    def spectrum(self) -> np.ndarray:
        """Current spectrum estimate (complex64, M x M)."""
        return self._spectrum

    def calibration(self) -> Calibration:
        """The current position offsets and pupils, in the problem's capture order."""
        inverse = np.empty_like(self._order)
        inverse[self._order] = np.arange(self._order.size)
        return Calibration(offsets=self._offsets[inverse].copy(),
                           pupils=np.asarray(self._model.pupils)[inverse].copy(),
                           coefficients=None if self._coefficients is None else self._coefficients.copy())

    def close(self) -> None:
        """Stop worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
