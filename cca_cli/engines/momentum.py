"""A sequential engine with momentum (rPIE/mPIE style) and model calibration, on the paper's operators.

Captures are visited centre-out (by distance of their pupil from DC) in small
batches, in shells that grow away from DC (:mod:`cca_cli.engines.schedule`).
Within a shell, captures whose pupil boxes lie wholly above (or left of) a line
never touch those wholly below (or right of) it, so two threads update those
groups side by side and the result equals visiting them one after the other
(up to float rounding).

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

Calibration (all optional: pupils, positions, brightness) absorbs what real
captures do that the ideal model does not; a
:class:`~cca_cli.engines.calibrator.Calibrator` keeps it, and its pupil step is
formed from the same batch residuals that update the object. The batches and
the threads that run them are :class:`~cca_cli.engines.passes.SequentialPass`'s
business.

The run stops (:class:`~cca_cli.engines.stopping.StoppingPolicy`) at
``max_iterations``, when a pass changes the spectrum by less than ``tol``, or
when the misfit has fallen by less than ``plateau`` (relative) over the last
``plateau_window`` passes. With ``batch_growth`` a plateau (over the last
``growth_window`` passes) first makes the batches larger (until a batch may
hold every capture), and only a plateau at the largest batch ends the run: on
recorded data, which the model never explains exactly, fixed small batches
settle into a cycle between the captures' constraints rather than at a minimum
of the whole misfit.

References
----------
Maiden & Rodenburg, Ultramicroscopy 109 (2009) (ePIE); Maiden, Johnson & Li,
Optica 4(7) (2017) (rPIE, mPIE); O'Donoghue & Candès, Found. Comput. Math. 15
(2015) (adaptive restart).
"""

from __future__ import annotations

import numpy as np

from cca_cli.engines.background import less_background
from cca_cli.engines.base import CalibratingEngine
from cca_cli.engines.calibrator import Calibration, Calibrator, subset_layout
from cca_cli.engines.held_back import HeldBack, held_back_captures
from cca_cli.engines.options import MomentumOptions
from cca_cli.engines.passes import BatchTargets, SequentialPass
from cca_cli.engines.problem import PhaseRetrievalProblem, initial_spectrum
from cca_cli.engines.schedule import build_schedule
from cca_cli.engines.stopping import StoppingPolicy
from cca_cli.optics import fft, kernels
from cca_cli.optics.forward import ForwardModel

__all__ = ["DEFAULT_THREADS", "MAX_THREADS", "MAX_LANES", "lanes_for", "MomentumOptions", "Calibration", "MomentumBase", "SequentialMomentum", "held_back_captures"]

#: Most threads a pass uses; a larger ``threads`` runs as this many. Threads beyond a phase's lanes split the
#: lanes' batches (:func:`~cca_cli.engines.passes.thread_groups`). On a 16-core machine the blood smear's
#: passes took 0.054, 0.055, 0.062 and 0.072 s with 2, 4, 8 and 16 threads (benchmarks/bench_threads.py):
#: beyond four the hand-overs between threads cost more than the split saves.
MAX_THREADS = 4
#: Threads a pass uses when the options name none (fewer where the process may use fewer cores). On the
#: 16-core machine, with every thread the run's own, the blood smear's whole default run took 2.47 s with
#: 2 threads and 2.80 s with 4 (2026-11-27, ``benchmarks/bench_threads.py``): more lanes only add hand-overs.
#: It also makes the default result the same on every machine with two cores or more.
DEFAULT_THREADS = 2
#: Most lanes a phase is split into.
MAX_LANES = 8


def lanes_for(threads: int) -> int:
    """Lanes a phase is split into for ``threads`` threads: the largest power of two up to them, 2 to :data:`MAX_LANES`.

    One and two threads visit the captures in the same order.
    """
    return min(MAX_LANES, max(2, 1 << (max(1, threads).bit_length() - 1)))


class MomentumBase(CalibratingEngine):
    """What every momentum engine shares beside its pass: the end of a pass, growing batches, results, checkpoints.

    A subclass keeps ``_spectrum``, ``_velocity`` and ``_anchor`` (on its device), ``_previous_misfit``,
    ``_batch``, ``_held`` (:class:`~cca_cli.engines.held_back.HeldBack`), ``_lanes`` (how far the
    schedule splits the spectrum), ``_model``, a :class:`~cca_cli.engines.calibrator.Calibrator` and a
    :class:`~cca_cli.engines.stopping.StoppingPolicy`, and provides ``_momentum`` (the momentum step),
    ``_arrange`` (:meth:`_lay_out`, then the model) and ``_set_model`` (pupils in engine order); one that
    keeps no host ``_model`` overrides ``_engine_pupils``.
    ``_to_host`` / ``_to_device`` move arrays where the engine keeps them elsewhere (a GPU).
    """

    #: The most threads a run of this engine uses when its options name none (:data:`DEFAULT_THREADS`):
    #: the problem's set-up, the FFTs and the fit report then take no more either.
    max_threads = DEFAULT_THREADS

    def _start(self, problem: PhaseRetrievalProblem, options: MomentumOptions, spectrum: np.ndarray | None,
               threads: int) -> None:
        """The state every momentum engine starts from (the subclass has set ``_to_device``'s needs)."""
        self.problem, self.options = problem, options
        start = initial_spectrum(problem) if spectrum is None else spectrum
        self._spectrum = self._to_device(np.array(start, np.complex64))
        self._velocity = self._spectrum.copy()
        self._velocity[...] = 0
        self._anchor = self._spectrum.copy()
        self._previous_misfit = np.inf
        self._before_step = None   # spectrum, anchor, velocity and misfit the last pupil step was taken from
        self._batch = options.batch
        self._held = HeldBack(problem, options.hold_back)
        self.held_back, self._trained = self._held.captures, self._held.trained
        self._data_norm = self._held.trained_norm
        self.calibrator = Calibrator(problem, options, threads)
        self.calibrator.exclude(self.held_back)
        self.stopping = StoppingPolicy(max_iterations=options.max_iterations, tol=options.tol,
                                       plateau=options.plateau, plateau_window=options.plateau_window,
                                       growth_window=options.growth_window, can_grow=self._can_grow,
                                       held_back_patience=options.hold_back_patience if len(self._held) else 0)

    def _lay_out(self) -> np.ndarray:
        """Lay the captures out at their current centres and build the visiting order; returns that order.

        Sets ``_schedule``, ``_order`` (capture indices in visiting order), ``_all_layout`` (every
        capture) and ``_layout`` (the trained captures in visiting order).
        """
        layout = self.calibrator.layout_for(self.calibrator.centres())
        distances = np.hypot(layout.centres_px[:, 0], layout.centres_px[:, 1])
        trained = self._trained
        self._schedule = build_schedule(layout.box_origins[trained], layout.box_size, distances[trained], self._batch,
                                        lanes=self._lanes)
        self._order = order = trained[self._schedule.order]
        self._all_layout = layout
        self._layout = subset_layout(layout, order)
        return order

    def _to_host(self, array):
        return array

    def _to_device(self, array: np.ndarray):
        return array

    def _end_pass(self, misfit: float) -> tuple[float, float]:
        """After a pass: momentum, pupil step, held-back misfit, stopping and batch growth; the pass's figures."""
        change = self._momentum(misfit)
        restored = self._pupil_step(misfit)
        self._previous_misfit = misfit if restored is None else restored
        if len(self._held):
            self.held_back_residual = self._held.misfit(self.spectrum(), self.calibrator, self._all_layout)
        if self.stopping.record(misfit, change, self.held_back_residual):
            self._grow_batch()
        best = self._held.keep_best(self.stopping, self.spectrum, self.calibrator)
        if best is not None:
            self._spectrum[...] = self._to_device(best)
            self._arrange()
        return float(np.sqrt(misfit / max(self._data_norm, 1e-30))), change

    def _pupil_step(self, misfit: float) -> float | None:
        """End-of-pass pupil update; the spectrum takes over the pupils' common scale and tilt.

        The spectrum, anchor and velocity a step is taken from are kept: when the next pass's misfit leaps
        and the step is undone (``undone_sharply``), they come back, and the misfit of the pass they
        ended is returned (None otherwise).
        """
        recovery = self.calibrator.recovery
        keep = recovery is not None and recovery.undoes_leaps   # the only steps a leap takes back with the spectrum
        before = (self._spectrum.copy(), self._anchor.copy(), self._velocity.copy(), misfit) if keep else None
        normalisation = self.calibrator.pupil_step(misfit, self.stopping.iteration)
        if recovery is not None and recovery.undone_sharply and self._before_step is not None:
            *arrays, restored = self._before_step
            for array, kept in zip((self._spectrum, self._anchor, self._velocity), arrays):
                array[...] = kept
            self._before_step = None
            self._set_recovered_model()
            return restored
        if normalisation is None:
            return None
        self._before_step = before if keep and recovery.stepped else None
        scale, tilt = normalisation
        if np.any(tilt):
            grid = np.arange(self._spectrum.shape[0], dtype=np.float64)
            factor = np.outer(scale * np.exp(1j * tilt[0] * grid), np.exp(1j * tilt[1] * grid)).astype(np.complex64)
            factor = self._to_device(factor)
        else:  # the same products as a flat array of ``scale`` gives, without building one
            factor = np.complex64(scale)
        if scale != 1 or np.any(tilt):
            for array in (self._spectrum, self._anchor, self._velocity):
                array *= factor
        self._set_recovered_model()
        return None

    def _set_recovered_model(self) -> None:
        """Use the pupil recovery's current pupils."""
        self._set_model(self.calibrator.recovery.pupils())

    # ------------------------------------------------------------ growing batches
    def _can_grow(self) -> bool:
        return self.options.batch_growth > 1 and self._batch < self._trained.size

    def _grow_batch(self) -> None:
        """Take larger batches from the next pass on; the plateau test starts afresh."""
        self._batch = min(self._batch * self.options.batch_growth, self._trained.size)
        self.stopping.grew()
        self._velocity[...] = 0
        self._arrange()

    @property
    def batch(self) -> int:
        """Captures per batch now (``batch``, grown by ``batch_growth`` at each plateau)."""
        return self._batch

    # ------------------------------------------------------------ results and checkpoints
    def spectrum(self) -> np.ndarray:
        """Current spectrum estimate (complex64, M x M), on the host."""
        return self._to_host(self._spectrum)

    def calibration(self) -> Calibration:
        """The current positions, pupils and brightness, in the problem's capture order."""
        calibrator = self.calibrator
        if len(self._held):  # the model holds the trained captures' pupils only
            return calibrator.calibration(calibrator.pupils_for(self._all_layout, calibrator.pupil_index))
        inverse = np.empty_like(self._order)
        inverse[self._order] = np.arange(self._order.size)
        return calibrator.calibration(self._engine_pupils()[inverse])   # a new array (fancy indexing copies)

    def _engine_pupils(self) -> np.ndarray:
        """The pupils the passes use now (engine order, on the host), complex64 (K, b, b)."""
        return np.asarray(self._model.pupils)

    def state(self) -> dict:
        """Spectrum, momentum, calibration and stopping state (problem order, on the host)."""
        host = self._to_host
        return {"spectrum": host(self._spectrum), "velocity": host(self._velocity), "anchor": host(self._anchor),
                "previous_misfit": self._previous_misfit, "batch": self._batch, **self.stopping.state(),
                **self.calibrator.state()}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state` (of any momentum engine); layout, visiting order and pupils are rebuilt."""
        for name in ("spectrum", "velocity", "anchor"):
            getattr(self, f"_{name}")[...] = self._to_device(np.asarray(state[name], np.complex64))
        self.stopping.restore(state)
        self._previous_misfit = float(state["previous_misfit"])
        self._batch = int(state.get("batch", self.options.batch))
        self.calibrator.restore(state)
        self._arrange()


class SequentialMomentum(MomentumBase):
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
        named = options.threads or min(fft.default_threads(), self.max_threads)
        threads = max(1, min(named, MAX_THREADS, problem.model.n_images))
        self._lanes = lanes_for(threads)
        self._start(problem, options, spectrum, threads)
        self.passes = SequentialPass(problem.model, threads)
        self._coverages = [np.zeros(problem.model.spectrum_shape, np.float32) for _ in range(threads)]  # work arrays
        self._buffers: dict[str, np.ndarray] = {}   # pupils, pupil boxes and update factors (see _buffer)
        self._map_pupils: kernels.MapPupils | None = None   # a map model's parts, when the lanes form the pupils
        self._arrange()

    # ------------------------------------------------------------ the model of a pass
    def _arrange(self) -> None:
        """Lay out the captures at their current centres and (re)build the visiting order and the model."""
        order = self._lay_out()
        self._origins = np.ascontiguousarray(self._layout.box_origins, dtype=np.int64)
        self._amplitudes = self._in_order(self.problem.amplitudes, order, getattr(self, "_amplitudes", None))
        self._weights = None if self.problem.weights is None else self._in_order(
            self.problem.weights, order, getattr(self, "_weights", None))
        self._set_targets()
        recovery = self.calibrator.recovery
        capacity = max(sl.stop - sl.start for sl in self._schedule.batches)
        self.passes.reserve(capacity, fusable=self.options.cost == "amplitude"
                            and (recovery is None or recovery.model != "zernike"))
        if recovery is not None:
            recovery.set_geometry(self._layout, self.calibrator.pupil_index[order])
            self._set_recovered_model()
        else:
            self._set_model(self.calibrator.pupils_for(self._layout, self.calibrator.pupil_index[order]))

    @staticmethod
    def _in_order(source: np.ndarray, order: np.ndarray, kept: np.ndarray | None) -> np.ndarray:
        """``source[order]`` as a C-contiguous float32 array, written into ``kept`` where it fits.

        The batches grow a few times per run, and each new arrangement would otherwise take fresh
        pages for every capture (first-touch page faults cost more than the copy).
        """
        if (kept is not None and kept.shape == (len(order),) + source.shape[1:] and kept.dtype == np.float32
                and kept.flags.c_contiguous and not np.shares_memory(kept, source)):
            return np.take(np.asarray(source, np.float32), order, axis=0, out=kept, mode="clip")
        return np.ascontiguousarray(source[order], dtype=np.float32)

    def _set_targets(self) -> None:
        """Measured amplitudes less each capture's background, divided by its brightness (engine order)."""
        scale = self.calibrator.target_scale(self._order)
        kept = getattr(self, "_less_background", None)
        amplitudes = less_background(self._amplitudes, self.calibrator.background[self._order],
                                     out=kept if kept is not None and kept.shape == self._amplitudes.shape else None)
        if amplitudes is not self._amplitudes:
            self._less_background = amplitudes   # refilled at the next round
        self._targets = amplitudes if np.all(scale == 1) else amplitudes * scale[:, None, None]
        self._intensities = np.square(self._targets) if self.options.cost == "poisson" else None

    def _set_model(self, pupils: np.ndarray | None, parts: tuple | None = None) -> None:
        """Use ``pupils`` (engine order) and precompute each capture's update factor.

        With ``parts`` (:meth:`~cca_cli.engines.pupil_recovery.PupilRecovery.map_parts`) the pupils
        are built here instead, each thread its share, together with the model's pupil boxes.
        """
        self._map_pupils = None
        layout, opts = self._layout, self.options
        bounds = np.array([[sl.start, sl.stop] for sl in self._schedule.batches], np.int64)
        # Batches are independent: each thread takes a contiguous share of them, with its own work array.
        shares = [np.ascontiguousarray(share) for share in np.array_split(bounds, self.passes.threads)]
        from_maps = parts is not None
        # The previous model is out of use from here on: its arrays are refilled (fresh pages cost more).
        factors = self._buffer("factors")
        if from_maps:
            pupils, boxes = self._buffer("pupils"), self._buffer("boxes")
        else:
            self._model = ForwardModel(layout, pupils)
            pupils = self._model.pupils

        def share_of_factors(t: int) -> None:
            rpie = dict(alpha=opts.alpha, tau=opts.tau, scale=opts.beta / layout.lowres_size,
                        coverage=self._coverages[t])
            if from_maps:
                kernels.map_pupil_factors(*parts, self._origins, shares[t], forward_scale=1.0 / layout.lowres_size,
                                          pupils=pupils, boxes=boxes, factors=factors, **rpie)
            else:
                kernels.rpie_factors(pupils, self._origins, shares[t], out=factors, **rpie)

        self.passes.on_every_thread(share_of_factors)
        if from_maps:
            self._model = ForwardModel(layout, pupils, pupil_boxes=boxes)
        self._factors = factors

    def _buffer(self, name: str) -> np.ndarray:
        """A complex64 (K, b, b) array kept from model to model (made anew when the layout's shape changes)."""
        shape = (self._layout.n_images, self._layout.box_size, self._layout.box_size)
        array = self._buffers.get(name)
        if array is None or array.shape != shape:
            array = self._buffers[name] = np.empty(shape, np.complex64)
        return array

    def _set_recovered_model(self) -> None:
        """Use the pupil recovery's current pupils: for the map models, formed in the fused lanes from the
        maps, or built on every thread."""
        recovery = self.calibrator.recovery
        parts = recovery.map_parts()
        self._map_pupils = None
        if parts is None:
            self._set_model(recovery.pupils())
        elif self.passes.fused:
            opts, layout = self.options, self._layout
            self._map_pupils = kernels.MapPupils(*parts, forward_scale=1.0 / layout.lowres_size, alpha=opts.alpha,
                                                 tau=opts.tau, scale=opts.beta / layout.lowres_size)
            self._model = self._factors = None
        else:   # the schedule's batches hold every capture of the layout once
            self._set_model(None, parts)

    def _engine_pupils(self) -> np.ndarray:
        if self._map_pupils is not None:
            return self._map_pupils.pupils()
        return super()._engine_pupils()

    # ------------------------------------------------------------ the update rule
    def _difference(self, fields: np.ndarray, images: slice, scratch: np.ndarray) -> float:
        """Replace ``fields`` by the data step ``ψ' − ψ``; return the squared amplitude misfit."""
        amplitudes = self._targets[images]
        weights = None if self._weights is None else self._weights[images]
        eps = self.problem.amplitude_floor
        if self.options.cost == "amplitude":
            return kernels.magnitude_step(fields, amplitudes, scratch, weights=weights, eps=eps)
        magnitude = np.abs(fields, out=scratch)
        misfit = magnitude - amplitudes
        if weights is not None:
            misfit *= np.sqrt(weights)
        squared = float(np.vdot(misfit.ravel(), misfit.ravel()))
        # Poisson cost: ψ' − ψ = −μ ψ (1 − I/|ψ|²); the floor on |ψ|² bounds the step where the model
        # is dark.
        np.square(magnitude, out=magnitude)
        np.maximum(magnitude, eps * eps + 1e-3 * self._intensities[images].mean(), out=magnitude)
        factor = np.divide(self._intensities[images], magnitude, out=magnitude)
        factor -= 1.0
        factor *= np.float32(self.options.poisson_step)
        if weights is not None:
            factor *= weights
        fields *= factor
        return squared

    def _accumulate_pupil(self, thread: int, images: slice, spectrum: np.ndarray, fields: np.ndarray) -> None:
        self.calibrator.recovery.accumulate(thread, images, spectrum, self._origins, fields, self._model.pupils)

    def _momentum(self, misfit: float) -> float:
        """The end-of-pass momentum step (after a restart check); returns the pass's relative change."""
        eta = self.options.eta
        if self.options.restart and misfit > self._previous_misfit:
            self._velocity[:] = 0
            eta = 0.0
        # Each thread steps its own band of rows (the step is per pixel); the sums add in thread order.
        bands = np.array_split(np.arange(self._spectrum.shape[0]), self.passes.threads)
        sums = [(0.0, 0.0)] * len(bands)

        def band_step(t: int) -> None:
            if not len(bands[t]):
                return
            rows = slice(int(bands[t][0]), int(bands[t][-1]) + 1)
            sums[t] = kernels.momentum_step(self._spectrum[rows], self._anchor[rows], self._velocity[rows], eta)

        self.passes.on_every_thread(band_step)
        change, norm = (sum(parts) for parts in zip(*sums))
        return float(np.sqrt(change / max(norm, 1e-30)))

    def _calibrate(self) -> None:
        """A position / brightness round when one is due before this pass."""
        if not self.calibrator.due(self.stopping.iteration):
            return
        moved, relit = self.calibrator.round(self._spectrum)
        if moved:
            self._arrange()
        elif relit:
            self._set_targets()

    def update(self) -> tuple[float, float]:
        """One pass over all captures (with a calibration round first when one is due)."""
        self._calibrate()
        recovery = self.calibrator.recovery
        targets = BatchTargets(self._model, self._origins, self._factors, self._targets, self._weights,
                               self.problem.amplitude_floor,
                               pupil_sums=None if recovery is None else recovery.lane_sums,
                               map_pupils=self._map_pupils, coverages=self._coverages)
        after = self._accumulate_pupil if self.calibrator.recovery is not None else None
        misfit = self.passes.run(self._schedule, self._spectrum, targets, self._difference, after)
        return self._end_pass(misfit)

    def close(self) -> None:
        """Stop worker threads."""
        self.passes.close()
