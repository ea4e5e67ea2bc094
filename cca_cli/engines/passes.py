"""Passes over all captures, and the threads that run them.

:class:`ChunkedPass` (simultaneous engines): forward, an in-place operation and
adjoint of every capture. Captures are processed in chunks small enough to stay
in cache between the inverse FFT, the magnitude projection and the forward FFT;
chunks run on a few worker threads (FFTW and numpy release the GIL), each with
its own buffer, FFT plan and spectrum accumulator.

:class:`SequentialPass` (sequential engines): batches of captures update the
spectrum one after the other, in the phases and lanes of a
:class:`~cca_cli.engines.schedule.Schedule`. Lanes of a phase touch disjoint
parts of the spectrum, so threads run them side by side with the result of
running them in turn; with numba and FFTW a thread's whole lane is one
compiled, GIL-free call (:func:`~cca_cli.optics.kernels.sequential_lane`).
The captures of one batch all read the spectrum before any of them updates it,
so a batch may also be split among threads and its parts added in order: a
phase of one lane is split among all threads, and a phase with fewer lanes
than threads gives each lane a group of threads (:func:`thread_groups`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import accumulate
from typing import Callable

import numpy as np

from cca_cli.engines.schedule import Schedule
from cca_cli.optics import fft, kernels
from cca_cli.optics.forward import ForwardModel, chunk_slices

__all__ = ["ChunkedPass", "BatchTargets", "SequentialPass", "PART_CAPTURES", "part_threads", "thread_groups"]

#: operation(fields, images, scratch (2, k, m, m) float32) -> float statistic summed over chunks
ChunkOperation = Callable[[np.ndarray, slice, np.ndarray], float]


class ChunkedPass:
    """Back-projection of processed fields, ``Σ_i A_iᴴ op(A_i S)``, over all captures.

    Parameters
    ----------
    model : ForwardModel
    chunk : int
        Captures per chunk (cache-sized; 8-32 is typical).
    threads : int, optional
        Worker threads (default: all cores).
    slices : list of slice, optional
        Capture ranges processed together (e.g. whole multiplexed measurements);
        default: contiguous chunks of ``chunk`` captures.
    """

    def __init__(self, model: ForwardModel, *, chunk: int = 16, threads: int | None = None,
                 slices: list[slice] | None = None):
        self.model = model
        self.slices = slices if slices is not None else chunk_slices(model.n_images, chunk)
        capacity = max(s.stop - s.start for s in self.slices)
        cores = threads or fft.default_threads()
        self.threads = max(1, min(cores, len(self.slices)))
        fft_threads = max(1, cores // self.threads)
        self.workspaces = [model.workspace(capacity, threads=fft_threads) for _ in range(self.threads)]
        self.scratch = [np.empty((2, capacity) + model.field_shape, np.float32) for _ in range(self.threads)]
        self.accumulators = [np.zeros(model.spectrum_shape, np.complex64) for _ in range(self.threads)]
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def run(self, spectrum: np.ndarray, operation: ChunkOperation, out: np.ndarray) -> float:
        """Compute ``Σ_i A_iᴴ op(A_i S)`` into ``out`` and return the summed statistic."""
        if self._pool is None:
            total = self._worker(0, spectrum, operation)
        else:
            futures = [self._pool.submit(self._worker, t, spectrum, operation) for t in range(self.threads)]
            total = sum(f.result() for f in futures)
        np.copyto(out, self.accumulators[0])
        for acc in self.accumulators[1:]:
            out += acc
        return total

    def _worker(self, t: int, spectrum: np.ndarray, operation: ChunkOperation) -> float:
        ws, scratch, acc = self.workspaces[t], self.scratch[t], self.accumulators[t]
        acc.fill(0)
        total = 0.0
        for sl in self.slices[t::self.threads]:
            fields = self.model.forward_into(spectrum, sl, ws)
            total += operation(fields, sl, scratch[:, : sl.stop - sl.start])
            self.model.adjoint_into(ws, sl, acc)
        return total

    def close(self) -> None:
        """Stop the worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


@dataclass(frozen=True)
class BatchTargets:
    """What a sequential pass updates the spectrum towards, in the schedule's capture order.

    Attributes
    ----------
    model : ForwardModel
        The captures' pupils and boxes.
    origins : ndarray, int64, (K, 2)
        Box origins in the spectrum.
    factors : ndarray, complex64, (K, b, b)
        Each capture's update factor (step size over the batch's pupil power, times the conjugate pupil).
    amplitudes : ndarray, float32, (K, m, m)
        Target amplitudes.
    weights : ndarray, float32, (K, m, m) or None
    eps : float
        Amplitude floor of the magnitude step.
    pupil_sums : callable, optional
        ``pupil_sums(thread)`` gives the arrays a fused lane adds the pupil fit's sums to (see
        :func:`~cca_cli.optics.kernels.sequential_lane`); None: nothing is summed in the lane.
    map_pupils : MapPupils, optional
        Fused lanes only: a map model's parts, from which the lanes form the pupil boxes and factors
        (``model`` and ``factors`` are then None).
    coverages : list of ndarray, optional
        With ``map_pupils``: one zero float32 (M, M) work array per thread.
    """

    model: ForwardModel | None
    origins: np.ndarray
    factors: np.ndarray | None
    amplitudes: np.ndarray
    weights: np.ndarray | None
    eps: float
    pupil_sums: Callable[[int], tuple] | None = None
    map_pupils: kernels.MapPupils | None = None
    coverages: list | None = None


#: data_step(fields, images, scratch) replaces ``fields`` by the data step ψ' − ψ and returns the squared misfit.
DataStep = Callable[[np.ndarray, slice, np.ndarray], float]
#: after_step(thread, images, spectrum, fields) sees each batch's data step in the spectrum domain (pupil sums).
AfterStep = Callable[[int, slice, np.ndarray, np.ndarray], None]


class SequentialPass:
    """Runs the batches of a schedule over a spectrum, on one or more threads.

    Parameters
    ----------
    model : ForwardModel
        Any model of the captures' grids (makes the workspaces).
    threads : int
        Threads: a phase's lanes run side by side (the lanes, largest first, dealt to the threads in
        turn); a batch of a phase with one lane is split among the threads (:func:`part_threads`), its
        parts computed side by side and scattered in order; a phase with fewer lanes than threads (more than two threads only) gives
        each lane a group of threads (:func:`thread_groups`) that split each of its batches likewise.
        Which thread computes which captures depends only on the schedule and ``threads``, so a
        thread count gives the same result every time.
    """

    def __init__(self, model: ForwardModel, threads: int):
        self.threads = threads
        self._model = model
        self._pool = ThreadPoolExecutor(threads - 1) if threads > 1 else None
        self._capacity = 0
        self._workspaces: list = []
        self._scratch: list[np.ndarray] = []
        self._boxes: list = []
        self._fused: list = []

    def reserve(self, capacity: int, *, fusable: bool) -> None:
        """Make room for batches of ``capacity`` captures; ``fusable``: lanes may run as one compiled call.

        The fused lane does the magnitude step (and the map models' pupil sums) only, so engines with
        another data step pass ``fusable=False``. A fused lane transforms a few captures at a time
        (:func:`~cca_cli.optics.kernels.lane_chunk`), so its workspace holds that many fields and only
        the update boxes grow with the batches. Nothing changes while the capacity suffices.
        """
        if capacity <= self._capacity:
            return
        self._capacity = capacity
        model = self._model
        box = model.layout.box_size
        if fusable:
            if not self.fused:
                chunk = kernels.lane_chunk(model.field_shape[0])
                workspaces = [model.workspace(chunk, threads=1) for _ in range(self.threads)]
                raw = [None if ws.box_fft is None else ws.box_fft.raw_plans() for ws in workspaces]
                if all(kernels.can_fuse_lanes(plans) for plans in raw):
                    self._workspaces, self._fused, self._scratch = workspaces, raw, [None] * self.threads
            if self.fused:
                self._boxes = [np.empty((capacity, box, box), np.complex64) for _ in range(self.threads)]
                return
        self._workspaces = [model.workspace(capacity, threads=1) for _ in range(self.threads)]
        self._scratch = [np.empty((capacity,) + model.field_shape, np.float32) for _ in range(self.threads)]
        self._fused = [None] * self.threads
        self._boxes = [None] * self.threads

    @property
    def fused(self) -> bool:
        """Whether each lane runs as one compiled call (numba and FFTW's own plans, magnitude steps only)."""
        return bool(self._fused) and self._fused[0] is not None

    def run(self, schedule: Schedule, spectrum: np.ndarray, targets: BatchTargets, data_step: DataStep,
            after_step: AfterStep | None = None) -> float:
        """One pass over every batch of ``schedule``, updating ``spectrum`` in place; returns the summed misfit."""
        runner = _PassRun(self, spectrum, targets, data_step, after_step)
        misfit = 0.0
        for phase in schedule.phases:
            if self._pool is None:
                misfit += sum(runner.lane(0, lane) for lane in phase.lanes)
            elif len(phase.lanes) == 1:
                for sl in phase.lanes[0]:
                    misfit += runner.shared_batch(sl)
            elif len(phase.lanes) < self.threads:
                misfit += runner.grouped_lanes(phase.lanes)
            else:
                # Lanes touch disjoint parts of the spectrum: running them together equals running them in turn.
                # The calling thread takes the longest lanes: it waits least for the interpreter between kernels.
                lanes = sorted(phase.lanes, key=_lane_size, reverse=True)
                shares = [lanes[t::self.threads] for t in range(min(self.threads, len(lanes)))]
                futures = [self._pool.submit(runner.lanes, t, share) for t, share in enumerate(shares) if t > 0]
                misfit += runner.lanes(0, shares[0]) + sum(f.result() for f in futures)
        return misfit

    def on_every_thread(self, work: Callable[[int], None]) -> None:
        """Run ``work(t)`` for every thread ``t`` side by side (``t = 0`` on the calling thread)."""
        futures = [self._pool.submit(work, t) for t in range(1, self.threads)] if self._pool is not None else []
        work(0)
        for future in futures:
            future.result()

    def close(self) -> None:
        """Stop the worker thread."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


def _lane_size(batches: tuple[slice, ...]) -> int:
    return sum(sl.stop - sl.start for sl in batches)


#: With more than two threads, the fewest captures a thread takes of a split batch: a part of one capture
#: costs about as much in hand-overs between threads as it saves. On a 16-core machine the blood smear took
#: 6.39 / 5.53 / 5.09 s at 8 threads and 7.60 / 6.04 / 6.35 s at 16 with at least 1 / 2 / 4 captures a thread.
PART_CAPTURES = 2


def thread_groups(sizes: list[int], threads: int, least: int = PART_CAPTURES) -> list[list[int]]:
    """Threads for each lane of a phase: every lane one, the rest by lane size, at least ``least`` captures each.

    Parameters
    ----------
    sizes : list of int
        Captures in each lane (at most ``threads`` lanes).
    threads : int
    least : int
        A lane gets another thread only while each of its threads keeps this many of its captures.

    Returns
    -------
    list of list of int
        Consecutive thread numbers for each lane, in the order of ``sizes``; the first group starts at 0.
        The same sizes and thread count always give the same groups (threads may be left over).
    """
    if not 0 < len(sizes) <= threads:
        raise ValueError(f"thread_groups: need 1 to {threads} lanes, got {len(sizes)}")
    counts = [1] * len(sizes)
    for _ in range(threads - len(sizes)):
        # the lane with the most captures per thread gets the next one (the first such lane on a tie)
        open_lanes = [i for i in range(len(sizes)) if sizes[i] >= (counts[i] + 1) * max(1, least)]
        if not open_lanes:
            break
        counts[max(open_lanes, key=lambda i: (sizes[i] / counts[i], -i))] += 1
    starts = list(accumulate(counts, initial=0))
    return [list(range(starts[i], starts[i + 1])) for i in range(len(sizes))]


def part_threads(captures: int, threads: int) -> int:
    """How many of ``threads`` split a batch of ``captures``: one or two as given, more only while each
    keeps :data:`PART_CAPTURES` captures (never fewer than two)."""
    if threads <= 2:
        return threads
    return max(2, min(threads, captures // PART_CAPTURES))


class _PassRun:
    """The batches of one pass: fields, data step and scatter, per thread."""

    def __init__(self, owner: SequentialPass, spectrum: np.ndarray, targets: BatchTargets, data_step: DataStep,
                 after_step: AfterStep | None):
        self.owner, self.spectrum, self.targets = owner, spectrum, targets
        self.data_step, self.after_step = data_step, after_step

    def half_batch(self, t: int, images: slice) -> float:
        """Fields → data step → spectrum-domain update boxes, in workspace ``t``."""
        if images.stop <= images.start:
            return 0.0
        ws = self.owner._workspaces[t]
        k = images.stop - images.start
        fields = self.targets.model.forward_into(self.spectrum, images, ws)
        misfit = self.data_step(fields, images, self.owner._scratch[t][:k])
        ws.forward(k)
        if self.after_step is not None:
            self.after_step(t, images, self.spectrum, ws.fields[:k])
        return misfit

    def scatter(self, t: int, images: slice, batch: slice, work: int = 0) -> None:
        """Add the weighted update boxes (thread ``t``'s) of ``images``, part of ``batch``, to the spectrum.

        ``work``: the thread whose work array the map model's scatter may use (the one scattering).
        """
        k = images.stop - images.start
        if k > 0:
            held = self.owner._boxes[t] if self.owner._fused[t] is not None else self.owner._workspaces[t].fields
            tg = self.targets
            if tg.map_pupils is not None:
                kernels.scatter_map_boxes(held[:k], tg.origins, tg.map_pupils, tg.coverages[work], self.spectrum,
                                          (batch.start, batch.stop), images.start)
            else:
                kernels.scatter_boxes(held[:k], tg.origins, tg.factors, self.spectrum, images.start)

    def lanes(self, t: int, lanes: list[tuple[slice, ...]]) -> float:
        """Run ``lanes`` one after the other on thread ``t``; returns their summed misfit."""
        return sum(self.lane(t, lane) for lane in lanes)

    def lane(self, t: int, batches: tuple[slice, ...], *, scatter: bool = True) -> float:
        """Run ``batches`` one after the other on thread ``t``; returns their summed misfit.

        ``scatter=False`` (one batch): leave its update in thread ``t``'s boxes for :meth:`scatter`.
        """
        raw = self.owner._fused[t]
        if raw is not None:  # one compiled call for the whole lane: the threads never wait for the interpreter
            bounds = np.array([[sl.start, sl.stop] for sl in batches], dtype=np.int64).reshape(-1, 2)
            tg = self.targets
            sums = None if tg.pupil_sums is None else tg.pupil_sums(t)
            mapped = tg.map_pupils is not None
            return kernels.sequential_lane(raw, bounds, self.spectrum, tg.origins,
                                           None if mapped else tg.model.pupil_boxes, tg.factors,
                                           self.owner._workspaces[t].fields, tg.amplitudes, tg.weights, tg.eps,
                                           pupil_sums=sums, boxes=self.owner._boxes[t], scatter=scatter,
                                           map_pupils=tg.map_pupils, coverage=tg.coverages[t] if mapped else None)
        if not scatter:
            return self.half_batch(t, batches[0])
        misfit = 0.0
        for sl in batches:
            misfit += self.half_batch(t, sl)
            self.scatter(t, sl, sl)
        return misfit

    def shared_batch(self, sl: slice) -> float:
        """One batch computed by every thread (a part each), then scattered in order."""
        return self.split_batch(sl, list(range(self.owner.threads)))

    def split_batch(self, sl: slice, group: list[int]) -> float:
        """One batch computed by the threads of ``group`` (a part each), then scattered in order by the first.

        More than two threads take at least :data:`PART_CAPTURES` captures each (the first threads of the
        group; one or two threads always split the batch as before).
        """
        size = sl.stop - sl.start
        group = group[:part_threads(size, len(group))]
        threads = len(group)
        cuts = [sl.start + (size * i + threads - 1) // threads for i in range(threads)] + [sl.stop]
        if threads == 2:   # halves as before: the first the larger
            cuts = [sl.start, sl.start + (size + 1) // 2, sl.stop]
        parts = list(zip(group, (slice(a, b) for a, b in zip(cuts[:-1], cuts[1:]))))
        futures = [self.owner._pool.submit(self.part_of_batch, t, part) for t, part in parts[1:]]
        misfit = self.part_of_batch(*parts[0]) + sum(f.result() for f in futures)
        for t, part in parts:  # every part has read the spectrum: now the updates go in, in order
            self.scatter(t, part, sl, work=group[0])
        return misfit

    def grouped_lanes(self, lanes: tuple[tuple[slice, ...], ...]) -> float:
        """A phase with fewer lanes than threads: each lane's batches split among its group of threads.

        The groups run side by side (the first on the calling thread); a group leader waits only for
        its own group's parts, so at most ``threads - 1`` tasks are ever queued on the pool's
        ``threads - 1`` workers.
        """
        ordered = sorted(lanes, key=_lane_size, reverse=True)
        groups = thread_groups([_lane_size(lane) for lane in ordered], self.owner.threads)
        futures = [self.owner._pool.submit(self.lane_in_group, group, lane)
                   for group, lane in zip(groups[1:], ordered[1:])]
        return self.lane_in_group(groups[0], ordered[0]) + sum(f.result() for f in futures)

    def lane_in_group(self, group: list[int], batches: tuple[slice, ...]) -> float:
        """Run one lane's batches in turn, each split among the threads of ``group``."""
        if len(group) == 1:
            return self.lane(group[0], batches)
        return sum(self.split_batch(sl, group) for sl in batches)

    def part_of_batch(self, t: int, images: slice) -> float:
        """Thread ``t``'s part of a shared batch, up to its update (not yet scattered)."""
        if images.stop <= images.start:
            return 0.0
        return self.lane(t, (images,), scatter=False)
