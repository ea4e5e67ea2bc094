"""A sequential engine with momentum (rPIE/mPIE style) and model calibration, on the paper's operators.

Captures are visited centre-out (by distance of their pupil from DC) in small
batches, in shells that grow away from DC (:mod:`cca_cli.engines.schedule`).
Within a shell, captures whose pupil boxes lie wholly above (or left of) a line
never touch those wholly below (or right of) it, so two threads update those
groups side by side and the result equals visiting them one after the other
(up to float rounding). With numba and FFTW each thread's run of batches is a
single GIL-free call (:func:`~cca_cli.optics.kernels.sequential_lane`).

For each batch the fields ``ψ_i = A_i S`` are computed from the current
spectrum, the data step ``ψ'_i − ψ_i`` is formed (magnitude replacement, or a
Poisson-likelihood gradient step), and the spectrum is updated at once
(rPIE's regularised step, summed over the batch):

    S += β Σ_i R_iᵀ P_i* F(ψ'_i − ψ_i) / ((1 − α) D_B + α max D_B + τ),
    D_B = Σ_{i∈B} R_iᵀ |P_i|²

so a batch of one capture is exactly rPIE. After each pass over all captures
the spectrum takes a momentum step (mPIE):

    v ← η v + (S − S_prev),   S ← S + η v

where ``S_prev`` is the spectrum after the previous momentum step. A pass that
fits the data worse than the one before resets the velocity (adaptive
restart), so momentum cannot run away on data the model does not explain
exactly. One iteration is one pass over all captures; it costs the same FFTs
as one iteration of :class:`~cca_cli.engines.altmin.AlternatingMinimization`.

Calibration (all optional) absorbs what real captures do that the ideal model
does not:

- *pupil recovery* (:mod:`cca_cli.engines.pupil_recovery`): one pupil shared by
  all captures or one per camera, as a full complex map inside the NA (EPRY)
  or as Zernike modes; its Gauss–Newton step is formed from the same batch
  residuals that update the object and taken at the end of each pass;
- *positions* and *brightness* (:mod:`cca_cli.engines.illumination`): after
  ``calibration_start`` passes and every ``calibration_every`` passes, a global
  position model (LED array shift / rotation / height, or stage shift /
  rotation / scale) and then each capture's own offset take Gauss–Newton steps
  kept only where the misfit drops, and each capture's brightness its shrunk
  least-squares value.

The run stops at ``max_iterations``, when a pass changes the spectrum by less
than ``tol``, or when the misfit has fallen by less than ``plateau`` (relative)
over the last ``plateau_window`` passes. With ``batch_growth`` a plateau first
makes the batches larger (until a batch may hold every capture), and only a
plateau at the largest batch ends the run: on recorded data,
which the model never explains exactly, fixed small batches settle into a
cycle between the captures' constraints rather than at a minimum of the
whole misfit.

References
----------
Maiden & Rodenburg, Ultramicroscopy 109 (2009) (ePIE); Maiden, Johnson & Li,
Optica 4(7) (2017) (rPIE, mPIE); O'Donoghue & Candès, Found. Comput. Math. 15
(2015) (adaptive restart).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from cca_cli.engines import calibration as cal
from cca_cli.engines import illumination as ill
from cca_cli.engines.base import IterativeEngine, check_options
from cca_cli.engines.problem import PhaseRetrievalProblem, initial_spectrum
from cca_cli.engines.pupil_recovery import PUPIL_MODELS, PupilEstimate, PupilRecovery, resample_pupil
from cca_cli.engines.schedule import build_schedule
from cca_cli.optics import fft, kernels
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import BandLayout, band_layout

__all__ = ["MomentumOptions", "Calibration", "SequentialMomentum"]

_COSTS = ("amplitude", "poisson")
_PUPILS = ("none", "shared", "per_camera")
#: Captures with less than this share of the brightest capture's energy are left out of the aberration estimate.
_ESTIMATE_LIGHT = 0.01
#: Relative misfit drop a capture's position step must bring to be kept.
_CLEAR_GAIN = 1e-2


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
    plateau : float
        Stop when the data misfit fell by less than this fraction over the last
        ``plateau_window`` passes (0: never).
    plateau_window : int
        Passes the plateau test looks back.
    alpha : float
        rPIE regularisation α in [0, 1]: 0 divides by the batch's pupil power
        (ePIE-like full projection), 1 by its maximum (small, uniform steps).
    beta : float
        Step size β in (0, 2).
    eta : float
        Momentum η in [0, 1); 0 gives plain (batched) rPIE.
    restart : bool
        Reset the momentum whenever a pass fits the data worse than the previous one.
    batch : int
        Captures updated together (1: strictly one aperture at a time). Shells
        of 2, 2, 4, 4, 8, … batches are visited in turn.
    batch_growth : int
        Each time the misfit reaches a plateau (``plateau`` > 0), the batch
        grows by this factor, until a batch may hold every capture; only then
        does a plateau end the run. 1: the batch stays fixed. Small batches
        make fast progress at first, but on data the model does not explain
        exactly they end in a cycle between the captures' constraints; growing
        batches take the run to a stationary point of the whole misfit.
    cost : str
        ``"amplitude"`` (magnitude replacement) or ``"poisson"`` (a gradient
        step on the Poisson likelihood, ``ψ' = ψ (1 − μ (1 − I/|ψ|²))``).
    poisson_step : float
        μ of the Poisson step; 0.5 makes the magnitude update a Newton step
        towards ``√I``.
    pupil_recovery : str
        ``"none"``, ``"shared"`` (one pupil for all captures: a scanned camera or
        an LED-array microscope) or ``"per_camera"`` (one pupil per camera of a
        camera array; the same as ``shared`` when the captures name no cameras).
    pupil_model : str
        ``"full"`` (complex map inside the NA, amplitude and phase) or
        ``"zernike"`` (phase in Zernike modes up to ``pupil_order``).
    pupil_order : int
        Highest Zernike radial order fitted (``zernike``) or reported (``full``): 2, 3 or 4.
    pupil_amplitude : bool
        ``full`` model: recover the pupil's amplitude as well as its phase.
    pupil_start : int
        Passes before the first pupil step.
    pupil_step : float
        Initial pupil step fraction in (0, 1].
    pupil_estimate : bool
        Start the quadratic modes from the neighbour-shift estimate
        (:func:`~cca_cli.engines.calibration.estimate_quadratic_aberration`)
        unless the captures come with a known aberration.
    position_refinement : str or bool
        ``"none"``, ``"global"`` (a few parameters of the whole LED array or
        stage), ``"per_image"`` (each capture's own offset) or ``"both"``
        (global, then per image).
    brightness : bool
        Fit each capture's illumination brightness.
    calibration_start : int
        Passes before the first position / brightness round.
    calibration_every : int
        Passes between position / brightness rounds.
    threads : int or None
        Worker threads; None uses every core (at most 2 are used). The result
        does not depend on it beyond float rounding.
    """

    tau: float = 1e-3
    max_iterations: int = 200
    tol: float = 1e-5
    plateau: float = 0.0
    plateau_window: int = 5
    alpha: float = 0.1
    beta: float = 1.0
    eta: float = 0.7
    restart: bool = True
    batch: int = 12
    cost: str = "amplitude"
    poisson_step: float = 0.5
    pupil_recovery: str = "none"
    pupil_model: str = "zernike"
    pupil_order: int = 4
    pupil_amplitude: bool = True
    pupil_start: int = 1
    pupil_step: float = 1.0
    pupil_estimate: bool = True
    position_refinement: str | bool = "none"
    brightness: bool = False
    calibration_start: int = 3
    calibration_every: int = 2
    threads: int | None = None
    batch_growth: int = 1

    def __post_init__(self):
        if isinstance(self.position_refinement, bool):  # older configs: true / false
            object.__setattr__(self, "position_refinement", "both" if self.position_refinement else "none")
        check_options([
            (0 <= self.tau < np.inf, f"tau must be a finite number ≥ 0, got {self.tau}"),
            (self.max_iterations >= 1, f"max_iterations must be ≥ 1, got {self.max_iterations}"),
            (0 <= self.tol < np.inf, f"tol must be a finite number ≥ 0, got {self.tol}"),
            (0 <= self.plateau < 1, f"plateau must be in [0, 1), got {self.plateau}"),
            (self.plateau_window >= 1, f"plateau_window must be ≥ 1, got {self.plateau_window}"),
            (0 <= self.alpha <= 1, f"alpha must be in [0, 1], got {self.alpha}"),
            (0 < self.beta < 2, f"beta must be in (0, 2), got {self.beta}"),
            (0 <= self.eta < 1, f"eta must be in [0, 1), got {self.eta}"),
            (self.batch >= 1, f"batch must be ≥ 1, got {self.batch}"),
            (self.batch_growth >= 1, f"batch_growth must be ≥ 1, got {self.batch_growth}"),
            (self.cost in _COSTS, f"cost must be one of {', '.join(_COSTS)}, got {self.cost!r}"),
            (0 < self.poisson_step <= 1, f"poisson_step must be in (0, 1], got {self.poisson_step}"),
            (self.pupil_recovery in _PUPILS,
             f"pupil_recovery must be one of {', '.join(_PUPILS)}, got {self.pupil_recovery!r}"),
            (self.pupil_model in PUPIL_MODELS,
             f"pupil_model must be one of {', '.join(PUPIL_MODELS)}, got {self.pupil_model!r}"),
            (self.pupil_order in (2, 3, 4), f"pupil_order must be 2, 3 or 4, got {self.pupil_order}"),
            (self.pupil_start >= 0, f"pupil_start must be ≥ 0, got {self.pupil_start}"),
            (0 < self.pupil_step <= 1, f"pupil_step must be in (0, 1], got {self.pupil_step}"),
            (self.position_refinement in ill.POSITION_MODES,
             f"position_refinement must be one of {', '.join(ill.POSITION_MODES)}, "
             f"got {self.position_refinement!r}"),
            (self.calibration_start >= 0, f"calibration_start must be ≥ 0, got {self.calibration_start}"),
            (self.calibration_every >= 1, f"calibration_every must be ≥ 1, got {self.calibration_every}"),
        ])


@dataclass(frozen=True)
class Calibration:
    """The model calibration an engine arrived at (the problem's capture order).

    Attributes
    ----------
    centres_px : ndarray, float64, (K, 2)
        Pupil centres ``[y, x]`` in use (spectrum pixels from DC).
    offsets : ndarray, float64, (K, 2)
        ``centres_px`` minus the nominal centres (spectrum pixels).
    pupils : ndarray, complex64, (K, b, b)
        Every capture's pupil on its box.
    pupil_index : ndarray, int64, (K,)
        Pupil (camera) each capture uses.
    pupil : PupilEstimate or None
        The recovered pupils (None without pupil recovery).
    brightness : ndarray, float64, (K,)
        Illumination brightness of each capture (1 without brightness fitting).
    position_model : str or None
        ``"led_array"`` or ``"stage"`` when a global position model was fitted.
    position_parameters : dict or None
        Its parameters by name.
    """

    centres_px: np.ndarray
    offsets: np.ndarray
    pupils: np.ndarray
    pupil_index: np.ndarray
    pupil: PupilEstimate | None
    brightness: np.ndarray
    position_model: str | None = None
    position_parameters: dict | None = None

    @property
    def coefficients(self) -> np.ndarray | None:
        """Zernike coefficients (waves) of the first pupil, None without pupil recovery."""
        return None if self.pupil is None else self.pupil.coefficients[0]


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
        self._nominal = model.layout
        k = model.n_images
        cores = options.threads or fft.default_threads()
        self._threads = 2 if cores > 1 and k > 1 else 1
        self._data_norm = problem.energy
        self._eps = problem.amplitude_floor
        self._spectrum = (initial_spectrum(problem) if spectrum is None else spectrum).astype(np.complex64)
        self._velocity = np.zeros_like(self._spectrum)
        self._anchor = self._spectrum.copy()
        self._pool = ThreadPoolExecutor(self._threads - 1) if self._threads > 1 else None
        self._capacity = 0
        self._evaluation_workspace = None
        self._coverage = np.zeros(model.spectrum_shape, np.float32)  # work array of the update factors

        # Calibration state, in the problem's capture order.
        self._pupil_index = problem.pupil_indices()
        if options.pupil_recovery == "shared":
            self._pupil_index = np.zeros(k, np.int64)
        self._brightness = np.ones(k)
        self._offsets = np.zeros((k, 2))
        self._position_model = problem.position_model if options.position_refinement in ("global", "both") else None
        self._parameters = None if self._position_model is None else self._position_model.initial
        self._fixed_coefficients = self._starting_coefficients()
        self._fixed_map = None
        if problem.initial_pupil is not None:
            self._fixed_map = resample_pupil(problem.initial_pupil, self._nominal.box_size,
                                             self._nominal.pupil_radius_px)
            self._fixed_coefficients = None
        self._recovery = None
        if options.pupil_recovery != "none":
            self._recovery = PupilRecovery(
                self._nominal, self._pupil_index, model=options.pupil_model, order=options.pupil_order,
                coefficients=self._fixed_coefficients, amplitude=options.pupil_amplitude,
                step=options.pupil_step, threads=self._threads, maps=self._fixed_map)
        self._iteration = 0
        self._change = np.inf
        self._misfits: list[float] = []
        self._previous_misfit = np.inf
        self._batch = options.batch
        self._plateau_from = 0
        self._arrange()

    def _starting_coefficients(self) -> np.ndarray | None:
        """Zernike coefficients per pupil to start from: the captures' known aberration, or the shift estimate."""
        opts, problem = self.options, self.problem
        n_modes = len(cal.zernike_modes(opts.pupil_order))
        n_pupils = int(self._pupil_index.max()) + 1
        if problem.aberration is not None:
            known = np.zeros((n_pupils, n_modes))
            given = np.atleast_2d(np.asarray(problem.aberration, np.float64))
            known[:, :min(n_modes, given.shape[1])] = given[:, :n_modes]
            return known
        if opts.pupil_recovery == "none" or not opts.pupil_estimate:
            return None
        estimate = np.zeros((n_pupils, n_modes))
        # Shifts are measured on the captures with light to spare: noise-dominated dark-field images only add cost.
        energy = np.sum(np.square(problem.amplitudes, dtype=np.float64), axis=(1, 2))
        lit = energy >= _ESTIMATE_LIGHT * energy.max()
        for p in range(n_pupils):
            members = np.flatnonzero((self._pupil_index == p) & lit)
            layout = _subset(self._nominal, members)
            weights = None if problem.weights is None else problem.weights[members]
            estimate[p, :3] = cal.estimate_quadratic_aberration(layout, problem.amplitudes[members], weights)
        return estimate

    # ------------------------------------------------------------ model state
    def _centres(self, parameters=None, offsets=None) -> np.ndarray:
        """Pupil centres (problem order) for global parameters and per-image offsets."""
        parameters = self._parameters if parameters is None else parameters
        offsets = self._offsets if offsets is None else offsets
        base = self._nominal.centres_px if parameters is None else self._position_model.centres(parameters)
        return base + offsets

    def _layout_for(self, centres: np.ndarray) -> BandLayout:
        nominal = self._nominal
        return band_layout(centres, nominal.pupil_radius_px, hires_size=nominal.hires_size,
                           lowres_size=nominal.lowres_size)

    def _pupils_for(self, layout: BandLayout, index: np.ndarray) -> np.ndarray:
        """Pupils of captures laid out by ``layout`` that use pupils ``index``."""
        if self._recovery is not None:
            return self._recovery.pupils_at(layout, index)
        if self._fixed_map is not None:
            return circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px) * self._fixed_map
        coefficients = None
        if self._fixed_coefficients is not None:
            coefficients = self._fixed_coefficients[index]
        return cal.pupil_functions(layout, coefficients=coefficients, order=self.options.pupil_order)

    def _arrange(self) -> None:
        """Lay out the captures at their current centres and (re)build the visiting order and the model."""
        opts = self.options
        layout = self._layout_for(self._centres())
        distances = np.hypot(layout.centres_px[:, 0], layout.centres_px[:, 1])
        self._schedule = build_schedule(layout.box_origins, layout.box_size, distances, self._batch)
        self._order = order = self._schedule.order
        self._layout = _subset(layout, order)
        self._origin_array = np.ascontiguousarray(self._layout.box_origins, dtype=np.int64)
        self._amplitudes = np.ascontiguousarray(self.problem.amplitudes[order], dtype=np.float32)
        self._weights = None if self.problem.weights is None else np.ascontiguousarray(self.problem.weights[order],
                                                                                        np.float32)
        self._set_targets()
        capacity = max(sl.stop - sl.start for sl in self._schedule.batches)
        if capacity > self._capacity:
            self._capacity = capacity
            model = self.problem.model
            self._workspaces = [model.workspace(capacity, threads=1) for _ in range(self._threads)]
            self._scratch = [np.empty((capacity,) + model.field_shape, np.float32) for _ in range(self._threads)]
            # The fused lane does the amplitude step only; Poisson steps and the pupil fit's sums run step by step.
            fusable = opts.cost == "amplitude" and self._recovery is None
            self._fused_plans = [ws.box_fft.raw_plans() if fusable and ws.box_fft is not None else None
                                 for ws in self._workspaces]
            if not all(kernels.can_fuse_lanes(raw) for raw in self._fused_plans):
                self._fused_plans = [None] * self._threads
        if self._recovery is not None:
            self._recovery.set_geometry(self._layout, self._pupil_index[order])
        self._set_model(self._pupils_for(self._layout, self._pupil_index[order]))

    def _set_targets(self) -> None:
        """Measured amplitudes divided by each capture's brightness (engine order)."""
        scale = (1.0 / np.sqrt(self._brightness[self._order])).astype(np.float32)
        self._targets = self._amplitudes if np.all(scale == 1) else self._amplitudes * scale[:, None, None]
        self._intensities = np.square(self._targets) if self.options.cost == "poisson" else None

    def _set_model(self, pupils: np.ndarray) -> None:
        """Use ``pupils`` (engine order) and precompute each capture's update factor."""
        self._model = model = ForwardModel(self._layout, pupils)
        opts = self.options
        bounds = np.array([[sl.start, sl.stop] for sl in self._schedule.batches], np.int64)
        self._factors = np.empty(model.pupils.shape, np.complex64)
        kernels.rpie_factors(model.pupils, self._origin_array, bounds, alpha=opts.alpha, tau=opts.tau,
                             scale=opts.beta / self._layout.lowres_size, coverage=self._coverage, out=self._factors)

    # ------------------------------------------------------------- data steps
    def _difference(self, fields: np.ndarray, images: slice, scratch: np.ndarray) -> float:
        """Replace ``fields`` by the data step ``ψ' − ψ``; return the squared amplitude misfit."""
        amplitudes = self._targets[images]
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
        if self._recovery is not None:
            self._recovery.accumulate(t, images, self._spectrum, self._origin_array, ws.fields[:k], self._model.pupils)
        return misfit

    def _scatter(self, t: int, images: slice) -> None:
        """Add the batch's weighted update boxes (workspace ``t``) to the spectrum."""
        k = images.stop - images.start
        if k > 0:
            kernels.scatter_boxes(self._workspaces[t].fields[:k], self._origin_array, self._factors, self._spectrum,
                                  images.start)

    def _run_lane(self, t: int, batches: tuple[slice, ...]) -> float:
        """Run ``batches`` one after the other on thread ``t``; returns their summed misfit."""
        raw = self._fused_plans[t]
        if raw is not None:  # one compiled call for the whole lane: the threads never wait for the interpreter
            bounds = np.array([[sl.start, sl.stop] for sl in batches], dtype=np.int64).reshape(-1, 2)
            return kernels.sequential_lane(raw, bounds, self._spectrum, self._origin_array, self._model.pupil_boxes,
                                           self._factors, self._workspaces[t].fields, self._targets,
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

    def _pass(self) -> float:
        """One pass over all captures; returns the summed misfit."""
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
        return misfit

    def _momentum(self, misfit: float) -> float:
        """The end-of-pass momentum step (after a restart check); returns the pass's relative change."""
        eta = self.options.eta
        if self.options.restart and misfit > self._previous_misfit:
            self._velocity[:] = 0
            eta = 0.0
        change, norm = kernels.momentum_step(self._spectrum, self._anchor, self._velocity, eta)
        return float(np.sqrt(change / max(norm, 1e-30)))

    def _pupil_step(self, misfit: float) -> None:
        """End-of-pass pupil update; the spectrum takes over the pupils' common scale and tilt."""
        if self._recovery is None or self._iteration + 1 < self.options.pupil_start:
            return
        normalisation = self._recovery.step(misfit)
        if normalisation is None:
            return
        scale, tilt = normalisation
        if scale != 1 or np.any(tilt):
            grid = np.arange(self._spectrum.shape[0], dtype=np.float64)
            factor = np.outer(scale * np.exp(1j * tilt[0] * grid), np.exp(1j * tilt[1] * grid)).astype(np.complex64)
            for array in (self._spectrum, self._anchor, self._velocity):
                array *= factor
        self._set_model(self._recovery.pupils())

    # ------------------------------------------------------------ calibration
    def _evaluate(self, *, parameters=None, offsets=None, positions: bool = False) -> ill.CaptureStatistics:
        """Per-capture statistics of the current spectrum at the given positions (problem order)."""
        layout = self._layout_for(self._centres(parameters, offsets))
        model = ForwardModel(layout, self._pupils_for(layout, self._pupil_index))
        if self._evaluation_workspace is None:
            self._evaluation_workspace = model.workspace(min(32, model.n_images), threads=1, effort="measure")
        derivatives = self._pupil_derivatives(layout) if positions else None
        scale = 1.0 / np.sqrt(self._brightness)
        return ill.capture_statistics(model, self._spectrum, self.problem.amplitudes, self.problem.weights,
                                      pupil_derivatives=derivatives, workspace=self._evaluation_workspace,
                                      scale=scale)

    def _pupil_derivatives(self, layout: BandLayout, step: float = 1e-3) -> np.ndarray:
        """``∂P_i/∂c_i`` along y and x by central differences of the pupils, complex64 (2, K, b, b)."""
        out = []
        for axis in range(2):
            shift = np.zeros(2)
            shift[axis] = step
            up = self._pupils_for(replace(layout, box_centres=layout.box_centres + shift), self._pupil_index)
            down = self._pupils_for(replace(layout, box_centres=layout.box_centres - shift), self._pupil_index)
            out.append((up - down) / np.float32(2 * step))
        return np.stack(out).astype(np.complex64)

    def _calibrate(self) -> None:
        """One round of brightness and position calibration against the current spectrum."""
        opts = self.options
        moved = False
        if self._position_model is not None:
            moved |= self._global_position_step()
        if opts.position_refinement in ("per_image", "both"):
            moved |= self._per_image_position_step()
        if opts.brightness:
            statistics = self._evaluate()
            self._brightness = ill.shrunk_brightness(statistics, self._brightness)
            if not moved:
                self._set_targets()
        if moved:
            self._arrange()

    def _global_position_step(self) -> bool:
        statistics = self._evaluate(positions=True)
        step = ill.global_step(self._position_model, self._parameters, self._offsets, statistics)
        before = float(statistics.misfit.sum())
        for _ in range(3):
            trial = self._parameters + step
            if self._total_misfit(parameters=trial) < before:
                self._parameters = trial
                return True
            step = step / 2
        return False

    def _total_misfit(self, **positions) -> float:
        """Misfit at trial positions; infinite where the pupils would leave the spectrum grid."""
        try:
            return float(self._evaluate(**positions).misfit.sum())
        except ValueError:
            return np.inf

    def _per_image_position_step(self) -> bool:
        statistics = self._evaluate(positions=True)
        trial = self._offsets + ill.per_image_steps(statistics)
        limit = self._offset_limit()
        trial = np.clip(trial, -limit, limit)
        try:  # keep a capture's move only where it lowers that capture's misfit clearly (not just its noise)
            better = self._evaluate(offsets=trial).misfit < (1 - _CLEAR_GAIN) * statistics.misfit
        except ValueError:  # a pupil would leave the spectrum grid
            return False
        if not np.any(better):
            return False
        self._offsets[better] = trial[better]
        return True

    def _offset_limit(self) -> float:
        """Per-image offsets stay within a pupil radius's eighth (and at least a pixel)."""
        return max(1.0, self._nominal.pupil_radius_px / 8)

    def _calibration_due(self) -> bool:
        opts = self.options
        if opts.position_refinement == "none" and not opts.brightness:
            return False
        since = self._iteration - opts.calibration_start
        return since >= 0 and since % opts.calibration_every == 0

    # ------------------------------------------------------------------ loop
    def update(self) -> tuple[float, float]:
        """One pass over all captures (with a calibration round first when one is due)."""
        if self._calibration_due():
            self._calibrate()
        misfit = self._pass()
        self._change = self._momentum(misfit)
        self._pupil_step(misfit)
        self._previous_misfit = misfit
        self._misfits.append(misfit)
        self._iteration += 1
        if self._can_grow() and self._misfit_flat():
            self._grow_batch()
        return float(np.sqrt(misfit / max(self._data_norm, 1e-30))), self._change

    def _can_grow(self) -> bool:
        return self.options.batch_growth > 1 and self._batch < self.problem.model.n_images

    def _grow_batch(self) -> None:
        """Take larger batches from the next pass on; the plateau test starts afresh."""
        self._batch = min(self._batch * self.options.batch_growth, self.problem.model.n_images)
        self._plateau_from = len(self._misfits)
        self._velocity[:] = 0
        self._arrange()

    def _misfit_flat(self) -> bool:
        """Whether the misfit fell by less than ``plateau`` over the last ``plateau_window`` passes at this batch."""
        opts = self.options
        window = opts.plateau_window
        if opts.plateau <= 0 or len(self._misfits) - self._plateau_from <= window:
            return False
        then, now = self._misfits[-1 - window], self._misfits[-1]
        return (then - now) < opts.plateau * now

    @property
    def batch(self) -> int:
        """Captures per batch now (``batch``, grown by ``batch_growth`` at each plateau)."""
        return self._batch

    def on_plateau(self) -> bool:
        """Whether the run has reached its plateau: the misfit is flat and the batch can grow no more."""
        return not self._can_grow() and self._misfit_flat()

    def done(self) -> bool:
        """Stop at ``max_iterations``, when a pass changes the spectrum by less than ``tol``, or on a plateau."""
        return (self._iteration >= self.options.max_iterations or self._change < self.options.tol
                or self.on_plateau())

    def spectrum(self) -> np.ndarray:
        """Current spectrum estimate (complex64, M x M)."""
        return self._spectrum

    def calibration(self) -> Calibration:
        """The current positions, pupils and brightness, in the problem's capture order."""
        inverse = np.empty_like(self._order)
        inverse[self._order] = np.arange(self._order.size)
        centres = self._centres()
        position_parameters = None
        if self._position_model is not None:
            position_parameters = dict(zip(self._position_model.names, map(float, self._parameters)))
        return Calibration(
            centres_px=centres, offsets=centres - self._nominal.centres_px,
            pupils=np.asarray(self._model.pupils)[inverse].copy(), pupil_index=self._pupil_index.copy(),
            pupil=None if self._recovery is None else self._recovery.estimate(),
            brightness=self._brightness.copy(),
            position_model=None if self._position_model is None else self._position_model.kind,
            position_parameters=position_parameters)

    def state(self) -> dict:
        """Spectrum, momentum and calibration state (problem order), and the pass counters.

        Not kept: the pupil recovery's record of its last step (after a restore the
        next pass cannot undo that step if it fits worse; the step size is kept).
        """
        out = {"spectrum": self._spectrum, "velocity": self._velocity, "anchor": self._anchor,
               "misfits": np.asarray(self._misfits, np.float64), "brightness": self._brightness,
               "offsets": self._offsets, "iteration": self._iteration, "change": self._change,
               "previous_misfit": self._previous_misfit, "batch": self._batch, "plateau_from": self._plateau_from}
        if self._parameters is not None:
            out["parameters"] = np.asarray(self._parameters, np.float64)
        if self._recovery is not None:
            out.update(pupil_maps=self._recovery.maps, pupil_coefficients=self._recovery.coefficients,
                       pupil_step=self._recovery._step)
        return out

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state`; the layout, visiting order and pupils are rebuilt from it."""
        for name in ("spectrum", "velocity", "anchor"):
            getattr(self, f"_{name}")[...] = state[name]
        self._misfits = [float(v) for v in state["misfits"]]
        self._brightness = np.array(state["brightness"], np.float64)
        self._offsets = np.array(state["offsets"], np.float64)
        self._iteration = int(state["iteration"])
        self._change = float(state["change"])
        self._previous_misfit = float(state["previous_misfit"])
        self._batch = int(state.get("batch", self.options.batch))
        self._plateau_from = int(state.get("plateau_from", 0))
        if self._parameters is not None and "parameters" in state:
            self._parameters = np.array(state["parameters"], np.float64)
        if self._recovery is not None and "pupil_maps" in state:
            self._recovery.maps = np.array(state["pupil_maps"], np.complex64)
            self._recovery.coefficients = np.array(state["pupil_coefficients"], np.float64)
            self._recovery._step = float(state["pupil_step"])
            self._recovery._previous = None
        self._arrange()

    def close(self) -> None:
        """Stop worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


def _subset(layout: BandLayout, index: np.ndarray) -> BandLayout:
    """The layout of captures ``index`` (in that order)."""
    return replace(layout, centres_px=layout.centres_px[index], box_origins=layout.box_origins[index],
                   box_centres=layout.box_centres[index])
