"""The engines in batched form, written against an array module: numpy on the CPU, CuPy on a GPU.

The CPU engines (:mod:`~cca_cli.engines.altmin`, :mod:`~cca_cli.engines.momentum`)
keep a few captures in cache at a time and run compiled loops over them. A GPU
wants the opposite: as many captures per call as memory allows, and no Python
loop over captures. The engines here do every step for a whole batch of
captures at once, in complex64, with the array module ``xp`` they are given
(:mod:`cca_cli.optics.backend`):

* gather each capture's pupil box from the spectrum by fancy indexing, multiply
  by its pupil, place it in the middle of an m x m field, batched inverse FFT;
* the data step (magnitude projection or Poisson step) on all fields at once;
* batched forward FFT, multiply by the adjoint pupil (or the rPIE factor), and
  scatter-add the boxes back into the spectrum.

On CuPy the gather and placement of the boxes, the amplitude data step, a shared map pupil's
sums and the scatter-add run as one fused kernel each (:mod:`cca_cli.engines.fused`; the scatter-add
takes each spectrum pixel's terms in capture order, so a GPU run repeats bit for bit), and the
rPIE factors are formed on the device (:class:`RpieFactors`): a pupil step of a map model sends
only the pupil maps across. A call of a few captures costs more in launching than in arithmetic, so
the transforms run through cuFFT plans kept per batch shape (:class:`~cca_cli.optics.backend.PlannedFFT2`)
and the momentum engine sums its data misfit once a pass, not once a call.

They read the same problem (:class:`~cca_cli.engines.problem.PhaseRetrievalProblem`),
take the same options, stop by the same :class:`~cca_cli.engines.stopping.StoppingPolicy`
and keep the engine interface (update / spectrum / state / restore / close), so
:func:`~cca_cli.library.recovery.drive_engine`, checkpoints and the report work
unchanged; their states are those of the CPU engines, so a run checkpointed on
one device continues on the other.

:class:`BatchedAlternatingMinimization` is the paper's update, the same
arithmetic as :class:`~cca_cli.engines.altmin.AlternatingMinimization` (the
spectra agree to float32 rounding). :class:`BatchedMomentum` visits the
batches of :class:`~cca_cli.engines.momentum.SequentialMomentum`'s schedule
and runs the lanes of a phase, whose boxes never overlap, in one call; with
``lanes=2`` it visits the captures in the CPU engine's order with one or two
threads. It recovers pupils (``shared`` or ``per_camera``, every pupil model);
it holds captures back (``hold_back``) as the CPU engine does, their misfit
formed on the host once a pass; position refinement and brightness stay on
the CPU, and asking for them here is an error naming the option
(:func:`unsupported_options`).
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from cca_cli.engines import fused
from cca_cli.engines.base import IterativeEngine
from cca_cli.engines.momentum import MAX_LANES, MAX_THREADS, MomentumBase, lanes_for
from cca_cli.engines.options import AltMinOptions, EngineOptions, MomentumOptions
from cca_cli.engines.problem import PhaseRetrievalProblem, initial_spectrum
from cca_cli.engines.schedule import Schedule
from cca_cli.engines.stopping import StoppingPolicy
from cca_cli.optics import backend
from cca_cli.optics.backend import DeviceUnavailable
from cca_cli.sampling.grid import BandLayout

__all__ = ["FIELD_BYTES", "BoxOperator", "capture_groups", "unsupported_options", "check_options", "merged_steps", "RpieFactors",
           "BatchedAlternatingMinimization", "BatchedMomentum"]

#: Most bytes of complex64 fields one batched call holds (the FFTs need about as much again).
FIELD_BYTES = 1 << 29


def unsupported_options(options: EngineOptions) -> list[str]:
    """The options (``name: value``) the batched engines cannot run, with what to set instead.

    Returns
    -------
    list of str
        Empty when everything in ``options`` runs batched.
    """
    if not isinstance(options, MomentumOptions):
        return []
    found = []
    if options.position_refinement != "none":
        found.append(f"position_refinement: {options.position_refinement} (set none)")
    if options.brightness:
        found.append("brightness: true (set false; captures whose frame_scale is per_frame turn it on, "
                     "and they need it: run those on the CPU)")
    if options.background:
        found.append("background: true (set false; captures whose dark-field images never fall near zero turn it "
                     "on, and they need it: run those on the CPU)")
    return found


def check_options(options: EngineOptions) -> None:
    """Raise :class:`~cca_cli.optics.backend.DeviceUnavailable` (one line) for options the GPU engines lack."""
    found = unsupported_options(options)
    if found:
        raise DeviceUnavailable(f"the GPU engine does not run {'; '.join(found)}; or use device cpu")


def _squared_norm(xp: ModuleType, array) -> float:
    """``‖array‖²`` summed in float64."""
    return float(xp.sum(xp.square(xp.abs(array)), dtype=xp.float64))


def capture_groups(count: int, size: int) -> list[slice]:
    """``range(count)`` in contiguous groups whose m x m complex64 fields fit :data:`FIELD_BYTES`."""
    per_call = max(1, FIELD_BYTES // (size * size * 8))
    return [slice(start, min(start + per_call, count)) for start in range(0, count, per_call)]


class BoxOperator:
    """The forward operator and its adjoint for batches of captures, on the device of ``xp``.

    Capture ``i`` sees the spectrum's ``b x b`` box at ``layout.box_origins[i]``; its field is that box
    times the pupil, placed on an ``m x m`` grid centred at ``m // 2`` and inverse transformed (raw,
    unnormalised FFTs: the scaling lives in the pupils, as in :class:`~cca_cli.optics.forward.ForwardModel`).

    Parameters
    ----------
    xp : module
        numpy or CuPy.
    layout : BandLayout
        Grids and boxes of the captures, in the order the engine indexes them.
    """

    def __init__(self, xp: ModuleType, layout: BandLayout):
        self.xp = xp
        self.m, self.b, self.size = layout.lowres_size, layout.box_size, layout.hires_size
        self.start = self.m // 2 - self.b // 2
        origins = np.asarray(layout.box_origins, np.int64).reshape(-1, 2)
        if origins.size and (origins.min() < 0 or origins.max() + self.b > self.size):
            raise ValueError(f"a pupil box leaves the {self.size} x {self.size} spectrum")
        corners = backend.to_device(origins, xp)   # the (K, b, b) index is made where it is used
        offsets = xp.arange(self.b, dtype=xp.int64)
        #: Flat spectrum index of every box pixel, (K, b, b).
        self.index = ((corners[:, 0, None, None] + offsets[None, :, None]) * self.size
                      + corners[:, 1, None, None] + offsets[None, None, :])
        #: Whether the steps run as fused kernels (:mod:`cca_cli.engines.fused`: CuPy only).
        self.fused = fused.available(xp)
        self._fft = backend.PlannedFFT2(xp)

    def boxes(self, spectrum, captures):
        """The spectrum's boxes of ``captures`` (a slice or an index array), complex64 (k, b, b)."""
        return spectrum.reshape(-1)[self.index[captures]]

    def fields(self, spectrum, captures, pupils):
        """Fields ``F⁻¹{pupil · box}`` of the spectrum's boxes of ``captures``, complex64 (k, m, m).

        ``pupils`` (k, b, b) are the captures' pupil boxes (field layout, see ForwardModel).
        """
        xp, s, b = self.xp, self.start, self.b
        if self.fused:
            fields = fused.box_fields(xp, spectrum, xp.ascontiguousarray(self.index[captures]),
                                      xp.ascontiguousarray(pupils), self.m)
        else:
            boxes = self.boxes(spectrum, captures)
            fields = xp.zeros((boxes.shape[0], self.m, self.m), xp.complex64)
            fields[:, s:s + b, s:s + b] = boxes * pupils
        return self._fft.inverse(fields)

    def spectra(self, fields):
        """The boxes of the raw forward FFTs of ``fields`` (destroyed), complex64 (k, b, b)."""
        s, b = self.start, self.b
        return self._fft.forward(fields)[:, s:s + b, s:s + b]

    def gather_plan(self, captures) -> fused.GatherPlan | None:
        """The order in which :meth:`scatter` adds the boxes of ``captures`` (fused kernels only, else None).

        Making it waits for the GPU, so a recorded pass takes plans made beforehand.
        """
        return fused.gather_plan(self.xp, self.index[captures]) if self.fused else None

    def scatter(self, boxes, captures, out, factors, plan: fused.GatherPlan | None = None) -> None:
        """Add ``boxes · factors`` (k, b, b) into the spectrum ``out`` at the boxes of ``captures``.

        Each spectrum pixel takes its terms in capture order, so the sums repeat bit for bit; on CuPy
        ``plan`` (:meth:`gather_plan` of the same ``captures``) says which terms, made here when None.
        """
        if self.fused:
            fused.gather_add(self.xp, out, self.gather_plan(captures) if plan is None else plan, boxes, factors)
        else:
            backend.scatter_add(self.xp, out, self.index[captures], boxes * factors)


def project(xp: ModuleType, fields, amplitudes, weights, eps: float, *, keep: bool):
    """``ψ ← (w (A/max(|ψ|, ε) − 1) + keep) ψ`` in place; returns ``Σ w (|ψ| − A)²`` (a float64 device scalar).

    ``keep`` True is the magnitude projection ``w A ψ/|ψ| + (1 − w) ψ``; False the data step ``ψ' − ψ``.
    """
    magnitude = xp.abs(fields)
    misfit = magnitude - amplitudes
    if weights is not None:
        misfit *= xp.sqrt(weights)
    squared = xp.sum(xp.square(misfit), dtype=xp.float64)
    xp.maximum(magnitude, xp.float32(eps), out=magnitude)
    factor = xp.divide(amplitudes, magnitude, out=magnitude)
    if keep:
        if weights is not None:
            factor *= weights
            factor += 1.0 - weights
    else:
        factor -= 1.0
        if weights is not None:
            factor *= weights
    fields *= factor
    return squared


class BatchedAlternatingMinimization(IterativeEngine):
    """The paper's alternating minimization, whole batches of captures per call.

    Parameters
    ----------
    problem : PhaseRetrievalProblem
    options : AltMinOptions
        ``chunk`` and ``threads`` are the CPU engine's business and are not read.
    spectrum : ndarray, complex64, (M, M), optional
        Starting spectrum; default :func:`~cca_cli.engines.problem.initial_spectrum`.
    xp : module
        numpy or CuPy: where the arrays live and the work runs.
    graphs : bool
        On CuPy, record an iteration as one CUDA graph and replay it
        (:class:`~cca_cli.optics.backend.GraphedWork`). False launches every step from Python.
    """

    name = "altmin"

    def __init__(self, problem: PhaseRetrievalProblem, options: AltMinOptions = AltMinOptions(),
                 spectrum: np.ndarray | None = None, *, xp: ModuleType = np, graphs: bool = True):
        check_options(options)
        self.problem, self.options, self.xp = problem, options, xp
        model = problem.model
        start = initial_spectrum(problem) if spectrum is None else spectrum
        self._spectrum = backend.to_device(np.asarray(start, np.complex64), xp)
        self._operator = BoxOperator(xp, model.layout)
        self._pupils = backend.to_device(model.pupil_boxes, xp)
        self._adjoint = xp.conj(self._pupils)
        inverse_normal = (1.0 / (model.normal_diagonal() + np.float32(options.tau + 1e-30))).astype(np.float32)
        self._inverse_normal = backend.to_device(inverse_normal, xp)
        self._amplitudes = backend.to_device(problem.amplitudes, xp, xp.float32)
        self._weights = None if problem.weights is None else backend.to_device(problem.weights, xp, xp.float32)
        self._groups = capture_groups(model.n_images, model.layout.lowres_size)
        self._plans = [self._operator.gather_plan(group) for group in self._groups]
        self._data_norm = problem.energy
        self._eps = problem.amplitude_floor
        self._numerator = xp.zeros_like(self._spectrum)
        self._graphed = backend.GraphedWork(xp, self._iterate, enabled=graphs)
        self.stopping = StoppingPolicy(max_iterations=options.max_iterations, tol=options.tol, plateau=options.plateau,
                                       plateau_window=options.plateau_window)

    def _iterate(self) -> tuple:
        """Queue one iteration, the new spectrum written over the old; device scalars (misfit, ‖new − old‖², ‖old‖²).

        The work :class:`~cca_cli.optics.backend.GraphedWork` records: it never waits for the GPU.
        """
        xp, operator, spectrum, numerator = self.xp, self._operator, self._spectrum, self._numerator
        numerator.fill(0)
        misfit = None
        for group, plan in zip(self._groups, self._plans):
            fields = operator.fields(spectrum, group, self._pupils[group])
            weights = None if self._weights is None else self._weights[group]
            squared = project(xp, fields, self._amplitudes[group], weights, self._eps, keep=True)
            misfit = squared if misfit is None else misfit + squared
            operator.scatter(operator.spectra(fields), group, numerator, self._adjoint[group], plan)
        numerator *= self._inverse_normal
        change = xp.sum(xp.square(xp.abs(numerator - spectrum)), dtype=xp.float64)
        norm = xp.sum(xp.square(xp.abs(spectrum)), dtype=xp.float64)
        spectrum[...] = numerator
        return misfit, change, norm

    def update(self) -> tuple[float, float]:
        """One iteration: project every capture, then the closed-form Fourier update."""
        misfit, change, norm = self._graphed()
        change = float(np.sqrt(float(change) / max(float(norm), 1e-30)))
        misfit = 0.0 if misfit is None else float(misfit)
        self.stopping.record(misfit, change)
        return float(np.sqrt(misfit / max(self._data_norm, 1e-30))), change

    def spectrum(self) -> np.ndarray:
        """Current spectrum estimate (complex64, M x M), on the host."""
        return backend.to_host(self._spectrum)

    def state(self) -> dict:
        """The spectrum (on the host) and the stopping counters, as the CPU engine's state."""
        return {"spectrum": self.spectrum(), **self.stopping.state()}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state` (this engine's, or the CPU engine's)."""
        self._spectrum[...] = backend.to_device(np.asarray(state["spectrum"], np.complex64), self.xp)
        self.stopping.restore(state)


def merged_steps(schedule: Schedule) -> list[np.ndarray]:
    """The schedule's batches as calls: the ``j``-th batch of every lane of a phase in one, phase by phase.

    Lanes of a phase touch disjoint parts of the spectrum, so one call for their ``j``-th batches gives
    what running them in turn gives.

    Returns
    -------
    list of ndarray, int64
        Positions in the schedule's order, one array per call.
    """
    steps = []
    for phase in schedule.phases:
        for j in range(max(len(lane) for lane in phase.lanes)):
            parts = [np.arange(lane[j].start, lane[j].stop) for lane in phase.lanes if j < len(lane)]
            steps.append(np.concatenate(parts).astype(np.int64))
    return steps


def _as_slice(positions: np.ndarray) -> slice | np.ndarray:
    """A run of consecutive positions as a slice (views instead of copies), anything else as it is."""
    if positions.size and np.array_equal(positions, np.arange(positions[0], positions[0] + positions.size)):
        return slice(int(positions[0]), int(positions[0]) + positions.size)
    return positions


class RpieFactors:
    """Each capture's rPIE factor, formed on the device from the pupils (as :func:`~cca_cli.optics.kernels.rpie_factors`).

    The factor of capture ``i`` in batch ``B`` is ``scale · P_i* / ((1 − α) D_B + α max D_B + τ)``, ``D_B`` the
    pupil power ``Σ_{j∈B} |P_j|²`` of its batch on the spectrum grid. Every batch gets its own power map, so
    the batches of a pass are formed together (in groups whose maps fit :data:`FIELD_BYTES`), with no host
    round trip.

    Parameters
    ----------
    xp : module
        numpy or CuPy.
    operator : BoxOperator
        The captures' boxes (engine order).
    batches : list of slice
        The visiting order's batches (positions in engine order).
    alpha, tau, scale : float
    """

    def __init__(self, xp: ModuleType, operator: BoxOperator, batches: list[slice], *, alpha: float, tau: float,
                 scale: float):
        self.xp = xp
        self._alpha, self._tau, self._scale = np.float32(alpha), np.float32(tau), np.float32(scale)
        area = operator.size * operator.size
        batches = [batch for batch in batches if batch.stop > batch.start]
        per_group = max(1, FIELD_BYTES // (area * 4))
        self._groups = []
        for first in range(0, len(batches), per_group):
            group = batches[first:first + per_group]
            lengths = np.array([batch.stop - batch.start for batch in group], np.int64)
            positions = np.concatenate([np.arange(batch.start, batch.stop) for batch in group]).astype(np.int64)
            local = np.repeat(np.arange(len(group), dtype=np.int64), lengths)   # each position's batch in the group
            members = np.full((len(group), lengths.max()), positions.size, np.int64)   # padded: a zero-power slot
            for j, start in enumerate(np.cumsum(lengths) - lengths):
                members[j, :lengths[j]] = np.arange(start, start + lengths[j])
            selection = _as_slice(positions)
            if not isinstance(selection, slice):
                selection = backend.to_device(selection, xp)
            target = backend.to_device(local[:, None, None] * area, xp) + operator.index[selection]
            plan = fused.gather_plan(xp, target) if operator.fused else None   # sums in capture order
            self._groups.append((selection, len(group) * area, target, plan, backend.to_device(members, xp),
                                 backend.to_device(local, xp)))

    def __call__(self, pupils):
        """The factors of ``pupils`` (complex64 (K, b, b), on the device), complex64 (K, b, b)."""
        xp = self.xp
        factors = xp.zeros_like(pupils)
        for selection, size, target, plan, members, local in self._groups:
            group = pupils[selection]
            coverage = xp.zeros(size, xp.float32)
            if plan is None:
                backend.scatter_add(xp, coverage, target, xp.square(xp.abs(group)))
            else:
                fused.gather_add(xp, coverage, plan, xp.square(xp.abs(group)))
            boxes = coverage[target]
            peaks = xp.concatenate([boxes.reshape(boxes.shape[0], -1).max(axis=1), xp.zeros(1, xp.float32)])
            peak = peaks[members].max(axis=1)[local]
            boxes *= 1 - self._alpha
            boxes += (self._alpha * peak + (self._tau + np.float32(1e-30)))[:, None, None]
            factors[selection] = xp.conj(group) * xp.divide(self._scale, boxes)
        return factors


class BatchedMomentum(MomentumBase):
    """Batched rPIE with mPIE momentum (and map-model pupil recovery), the lanes of a phase in one call.

    Parameters
    ----------
    problem : PhaseRetrievalProblem
    options : MomentumOptions
        As :class:`~cca_cli.engines.momentum.SequentialMomentum` reads them, except those
        :func:`unsupported_options` names (refused); ``threads`` only sets the default ``lanes``.
    spectrum : ndarray, complex64, (M, M), optional
        Starting spectrum; default :func:`~cca_cli.engines.problem.initial_spectrum`.
    xp : module
        numpy or CuPy.
    lanes : {1, 2, 4, 8}, optional
        How far the schedule splits the spectrum (:func:`~cca_cli.engines.schedule.build_schedule`): more
        lanes put more captures in one call. 2 visits the captures as the CPU engine with one or two
        threads does. Default: as the CPU engine would for ``options.threads`` when that is set (the same
        visiting order, so the two agree to float32 rounding), else 8.
    graphs : bool
        On CuPy, record a pass's calls as one CUDA graph and replay it
        (:class:`~cca_cli.optics.backend.GraphedWork`; recorded afresh whenever batches grow or the
        captures are laid out again). False launches every step from Python (the same arithmetic).
    """

    name = "momentum"

    def __init__(self, problem: PhaseRetrievalProblem, options: MomentumOptions = MomentumOptions(),
                 spectrum: np.ndarray | None = None, *, xp: ModuleType = np, lanes: int | None = None,
                 graphs: bool = True):
        check_options(options)
        if lanes is None:
            # the CPU engine's rule (momentum.SequentialMomentum), so that the two visit the captures alike
            threads = max(1, min(options.threads, MAX_THREADS, problem.model.n_images)) if options.threads else 0
            lanes = lanes_for(threads) if threads else MAX_LANES
        self.xp, self._lanes, self._graphs = xp, lanes, graphs
        self._start(problem, options, spectrum, threads=1)
        self._arrange()

    # ------------------------------------------------------------ the model of a pass
    def _arrange(self) -> None:
        """Lay out the captures, build the visiting order and calls, and move the pass's data to the device."""
        xp, problem, calibrator = self.xp, self.problem, self.calibrator
        order = self._lay_out()
        self._pupils = None   # new arrays for the new arrangement
        self._graphed = backend.GraphedWork(xp, self._calls, enabled=self._graphs)
        self._operator = BoxOperator(xp, self._layout)
        steps = merged_steps(self._schedule)
        self._steps = [_as_slice(step) for step in steps]
        self._steps = [step if isinstance(step, slice) else backend.to_device(step, xp) for step in self._steps]
        self._plans = [self._operator.gather_plan(step) for step in self._steps]
        # The fused data step writes each call's per-pixel misfit into its rows of one buffer, summed once a pass.
        ends = np.cumsum([step.size for step in steps])
        self._misfit_rows = [slice(int(end - step.size), int(end)) for step, end in zip(steps, ends)]
        self._misfit_pixels = None
        if self._operator.fused and self.options.cost == "amplitude":
            m = self._layout.lowres_size
            self._misfit_pixels = xp.empty((int(ends[-1]) if len(ends) else 0, m, m), xp.float32)
        # The captures go to the device once, in the problem's order; each arrangement reorders them there.
        if getattr(self, "_measured", None) is None:
            self._measured = backend.to_device(problem.amplitudes, xp, xp.float32)
            self._confidence = None if problem.weights is None else backend.to_device(problem.weights, xp, xp.float32)
        on_device = backend.to_device(order, xp)
        scale = calibrator.target_scale(order)
        if np.all(scale == 1):
            self._targets = xp.take(self._measured, on_device, axis=0)
        else:
            self._targets = xp.take(self._measured, on_device, axis=0) * backend.to_device(scale, xp)[:, None, None]
        self._weights = None if self._confidence is None else xp.take(self._confidence, on_device, axis=0)
        self._intensities = self._floors = None
        if self.options.cost == "poisson":
            targets = problem.amplitudes[order] * scale[:, None, None]
            intensities = np.square(targets, dtype=np.float32)
            eps = problem.amplitude_floor
            floors = np.empty(order.size, np.float32)
            for batch in self._schedule.batches:   # the floor on |ψ|² of a capture is its batch's, as on the CPU
                floors[batch] = eps * eps + 1e-3 * intensities[batch].mean()
            self._intensities = backend.to_device(intensities, xp)
            self._floors = backend.to_device(floors[:, None, None], xp)
        opts = self.options
        self._rpie = RpieFactors(xp, self._operator, self._schedule.batches, alpha=opts.alpha, tau=opts.tau,
                                 scale=opts.beta / self._layout.lowres_size)
        recovery = calibrator.recovery
        if recovery is not None:
            recovery.set_geometry(self._layout, calibrator.pupil_index[order])
            self._prepare_pupil_sums(recovery)
            self._set_recovered_model()
        else:
            self._set_model(calibrator.pupils_for(self._layout, calibrator.pupil_index[order]))

    def _prepare_pupil_sums(self, recovery) -> None:
        """The pupil fit's sums on the device, and what forming them needs (discs, modes, pupil of each capture)."""
        xp, b = self.xp, self._layout.box_size
        zernike = recovery.zernike_sums(0)
        if zernike is None:
            discs, index, _, _ = recovery.lane_sums(0)
            first = xp.zeros((recovery.n_pupils, b, b), xp.complex128)   # Σ conj(D S) · residual
            self._basis = None
            self._map_index = backend.to_device(index, xp)
        else:
            discs, basis, index, rhs, _ = zernike
            n_modes = basis.shape[0]
            first = xp.zeros(rhs.shape, xp.float64)                     # Σ modes · phase gradient
            self._basis = backend.to_device(np.ascontiguousarray(basis.reshape(n_modes, len(index), b * b)
                                                                 .transpose(1, 0, 2)), xp)
            modes = np.arange(n_modes, dtype=np.int64)
            self._mode_index = backend.to_device(index[:, None] * n_modes + modes, xp)
        self._discs = backend.to_device(discs, xp)
        self._pupil_sums = (first, xp.zeros((recovery.n_pupils, b, b), xp.float64))
        pixels = xp.arange(b * b, dtype=xp.int64).reshape(b, b)
        self._pupil_index = backend.to_device(np.asarray(index, np.int64), xp)[:, None, None] * (b * b) + pixels

    def _set_model(self, pupils: np.ndarray) -> None:
        """Use ``pupils`` (engine order, on the host)."""
        self._use_pupils(backend.to_device(np.ascontiguousarray(pupils, np.complex64), self.xp))

    def _set_recovered_model(self) -> None:
        """Use the pupil recovery's current pupils; a map model's are built on the device from its maps."""
        recovery = self.calibrator.recovery
        parts = recovery.map_parts()
        if parts is None:
            self._set_model(recovery.pupils())
            return
        maps = backend.to_device(parts[1], self.xp)
        self._use_pupils(self._discs * maps[self._map_index])

    def _use_pupils(self, pupils) -> None:
        """Use ``pupils`` (complex64 (K, b, b), on the device): the forward pupils and each capture's rPIE factor.

        Within one arrangement they are written into the same arrays (a recorded pass reads them there).
        """
        xp, scale = self.xp, self.xp.float32(1.0 / self._layout.lowres_size)
        if self._pupils is not None and self._pupils.shape == pupils.shape:
            self._pupils[...] = pupils
            xp.multiply(pupils, scale, out=self._pupil_boxes)
            self._factors[...] = self._rpie(pupils)
            return
        self._pupils = pupils
        self._pupil_boxes = pupils * scale
        self._factors = self._rpie(pupils)

    def _engine_pupils(self) -> np.ndarray:
        """The pupils the passes use now (engine order), copied to the host."""
        return backend.to_host(self._pupils)

    # ------------------------------------------------------------ the update rule
    def _data_step(self, fields, step, rows: slice):
        """Replace ``fields`` by the data step ``ψ' − ψ``; return the squared misfit (a device scalar).

        With the fused kernel the call's per-pixel misfit goes to ``rows`` of the pass's buffer instead
        (:meth:`_pass` sums it) and None is returned.
        """
        xp = self.xp
        weights = None if self._weights is None else self._weights[step]
        if self.options.cost == "amplitude":
            if self._misfit_pixels is not None:
                return fused.data_step(xp, fields, self._targets[step], weights, self.problem.amplitude_floor,
                                       squared=self._misfit_pixels[rows])
            return project(xp, fields, self._targets[step], weights, self.problem.amplitude_floor, keep=False)
        magnitude = xp.abs(fields)
        misfit = magnitude - self._targets[step]
        if weights is not None:
            misfit *= xp.sqrt(weights)
        squared = xp.sum(xp.square(misfit), dtype=xp.float64)
        # Poisson cost: ψ' − ψ = −μ ψ (1 − I/|ψ|²), |ψ|² floored as the CPU engine does.
        power = xp.maximum(xp.square(magnitude), self._floors[step])
        factor = xp.divide(self._intensities[step], power, out=power)
        factor -= 1.0
        factor *= xp.float32(self.options.poisson_step)
        if weights is not None:
            factor *= weights
        fields *= factor
        return squared

    def _accumulate_pupil(self, step, residuals) -> None:
        """Add a call's terms of the pupil fit (as :meth:`~cca_cli.engines.pupil_recovery.PupilRecovery.accumulate`).

        Map models: ``Σ conj(D S) · r`` and ``Σ |D S|²`` per pupil pixel; Zernike: the phase gradient
        ``Im(conj(P S) · r)`` on each capture's modes, and ``Σ |D S|²``.
        """
        xp, operator = self.xp, self._operator
        sums_first, sums_power = self._pupil_sums
        if operator.fused and self._basis is None and sums_first.shape[0] == 1:
            fused.add_pupil_sums(xp, sums_first[0], sums_power[0], self._discs[step], self._spectrum,
                                 xp.ascontiguousarray(operator.index[step]), residuals, 1.0 / self._layout.lowres_size)
            return
        seen = operator.boxes(self._spectrum, step)   # the spectrum is updated after this call's sums
        residuals = residuals * xp.float32(1.0 / self._layout.lowres_size)
        lit = self._discs[step] * seen
        power = xp.square(xp.abs(lit))
        if self._basis is None:
            first, index = xp.conj(lit) * residuals, self._pupil_index[step]
        else:
            gradient = xp.imag(xp.conj(self._pupils[step] * seen) * residuals)
            # a product and a sum, not einsum: cuBLAS calls cannot be recorded into a CUDA graph
            first = (self._basis[step] * gradient.reshape(gradient.shape[0], 1, -1)).sum(axis=2)
            index = self._mode_index[step]
        if sums_first.shape[0] == 1:
            sums_first[0] += first.sum(axis=0, dtype=sums_first.dtype)
            sums_power[0] += power.sum(axis=0, dtype=xp.float64)
        else:
            backend.scatter_add(xp, sums_first, index, first.astype(sums_first.dtype))
            backend.scatter_add(xp, sums_power, self._pupil_index[step], power.astype(xp.float64))

    def _calls(self):
        """Queue every call of the schedule, updating the spectrum in place; the misfit (device scalar) or None.

        None when the fused data step writes the misfit to the pass's buffer instead. This is the work
        :class:`~cca_cli.optics.backend.GraphedWork` records: it never waits for the GPU, and every
        array it reads stays in place until the next :meth:`_arrange`.
        """
        operator, spectrum = self._operator, self._spectrum
        recovery = self.calibrator.recovery
        misfit = None
        for step, rows, plan in zip(self._steps, self._misfit_rows, self._plans):
            fields = operator.fields(spectrum, step, self._pupil_boxes[step])
            squared = self._data_step(fields, step, rows)
            if squared is not None:
                misfit = squared if misfit is None else misfit + squared
            residuals = operator.spectra(fields)
            if recovery is not None:
                self._accumulate_pupil(step, residuals)
            operator.scatter(residuals, step, spectrum, self._factors[step], plan)
        return misfit

    def _pass(self) -> float:
        """One pass over every call of the schedule, updating the spectrum in place; returns the misfit."""
        recovery = self.calibrator.recovery
        misfit = self._graphed()
        if recovery is not None:   # the pass's sums join the recovery's own (host) sums
            zernike = recovery.zernike_sums(0)
            first, power = (recovery.lane_sums(0)[2:] if zernike is None else zernike[3:])
            first += backend.to_host(self._pupil_sums[0])
            power += backend.to_host(self._pupil_sums[1])
            for sums in self._pupil_sums:
                sums.fill(0)
        if self._misfit_pixels is not None:
            misfit = self._misfit_pixels.sum(dtype=self.xp.float64)
        return 0.0 if misfit is None else float(misfit)

    def _momentum(self, misfit: float) -> float:
        """The end-of-pass momentum step (after a restart check); returns the pass's relative change."""
        xp = self.xp
        eta = self.options.eta
        if self.options.restart and misfit > self._previous_misfit:
            self._velocity.fill(0)
            eta = 0.0
        norm = _squared_norm(xp, self._anchor)
        self._velocity *= xp.float32(eta)
        self._velocity += self._spectrum - self._anchor
        self._spectrum += xp.float32(eta) * self._velocity
        change = _squared_norm(xp, self._spectrum - self._anchor)
        self._anchor[...] = self._spectrum
        return float(np.sqrt(change / max(norm, 1e-30)))

    def _to_host(self, array):
        return backend.to_host(array)

    def _to_device(self, array: np.ndarray):
        return backend.to_device(array, self.xp)

    def update(self) -> tuple[float, float]:
        """One pass over all captures, the momentum step and the pupil step."""
        return self._end_pass(self._pass())
