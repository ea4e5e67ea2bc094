"""What one iteration of an engine costs on this machine, measured on a sample of the engine's own work.

An iteration of ``altmin`` or ``momentum`` visits every capture once: the
capture's pupil box of the spectrum is placed on the m x m band grid,
transformed (inverse, rows pruned to the box), given the measured magnitude,
transformed back and added into the spectrum. Then the whole M x M spectrum is
swept a few times (altmin: the threads' accumulators and the Tikhonov update;
momentum: the momentum step). So

    seconds per iteration = K · capture_seconds + M² · pixel_seconds.

:func:`measure_iteration_cost` measures both rates on this machine, now: the
engine's whole-spectrum steps on a grid of up to 1024², and the captures'
share either from iterations of the engine itself on the plan's captures
(flat amplitudes; small plans) or from passes of the engines' chunked code
(the pass altmin runs, which does per capture what momentum's lanes do) over
a sample of a couple of chunks on each of the engine's threads. They are
measured rather than modelled: what a capture costs depends on the FFT size
and its factors, on the cache, on the threads' hand-overs and on how much of
the machine the threads get now.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from cca_cli.engines.options import AltMinOptions, MomentumOptions
from cca_cli.engines.passes import ChunkedPass
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.registry import get_engine
from cca_cli.optics import fft, kernels
from cca_cli.optics.forward import ForwardModel
from cca_cli.sampling.grid import band_layout

__all__ = ["TIMED_ENGINES", "IterationCost", "engine_threads", "measure_iteration_cost"]

#: Engines whose iteration :func:`measure_iteration_cost` can time.
TIMED_ENGINES = ("altmin", "momentum")
#: Largest band grid timed as it is (a 7-smooth size); larger ones are timed at this size and scaled as m² log m.
_LARGEST_TIMED_BAND = 256
#: Largest spectrum the whole-grid steps are timed on; larger ones scale as M².
_LARGEST_TIMED_SPECTRUM = 1024
#: Plans of at most this many band-grid pixels over all captures are timed whole, with the engine itself.
_WHOLE_PLAN_PIXELS = 1 << 22
#: Chunks each thread works through in a timed pass: more than one, as in a pass over every capture.
_CHUNKS_PER_THREAD = 2
#: Timed repeats of each measurement: at least the first, at most the second, beyond that only within the budget.
_REPEATS = (3, 1000)


@dataclass(frozen=True)
class IterationCost:
    """The measured rates of one engine's iteration.

    Attributes
    ----------
    engine : str
    threads : int
        Worker threads the engine runs on this machine (and the measurement ran on).
    capture_seconds : float
        Wall time per capture of a pass over all captures.
    pixel_seconds : float
        Wall time per spectrum pixel of the whole-spectrum steps.
    """

    engine: str
    threads: int
    capture_seconds: float
    pixel_seconds: float


def engine_threads(engine: str, n_images: int) -> int:
    """Worker threads ``engine`` runs ``n_images`` captures on, on this machine.

    ``altmin`` runs a thread per chunk of captures, up to the cores;
    ``momentum`` runs two threads whenever there are two cores and two captures.
    """
    cores = fft.default_threads()
    if engine == "momentum":
        return 2 if cores > 1 and n_images > 1 else 1
    return max(1, min(cores, math.ceil(n_images / AltMinOptions().chunk)))


def measure_iteration_cost(engine: str, *, n_images: int, pupil_radius_px: float, step_px: float,
                           lowres_size: int, hires_size: int, budget_seconds: float = 0.25) -> IterationCost:
    """Time ``engine``'s work per capture and per spectrum pixel on this machine, now.

    Parameters
    ----------
    engine : {"altmin", "momentum"}
    n_images : int
        Captures K of the plan (sets the worker threads and the sample size).
    pupil_radius_px : float
        Pupil radius R (spectrum pixels).
    step_px : float
        Distance of neighbouring pupil centres (spectrum pixels).
    lowres_size, hires_size : int
        Band grid m and spectrum grid M.
    budget_seconds : float
        About how long the captures' share is timed, a fifth of it the spectrum's (each at least three
        repeats, however long they take).

    Returns
    -------
    IterationCost

    Raises
    ------
    ValueError
        An engine other than those in :data:`TIMED_ENGINES`.
    """
    if engine not in TIMED_ENGINES:
        raise ValueError(f"cannot time engine {engine!r}; choose one of {', '.join(TIMED_ENGINES)}")
    threads = engine_threads(engine, n_images)
    chunk = MomentumOptions().batch if engine == "momentum" else AltMinOptions().chunk
    size = min(int(lowres_size), _LARGEST_TIMED_BAND)
    scale = size / lowres_size
    sample = max(1, min(int(n_images), _CHUNKS_PER_THREAD * threads * chunk))
    timed = min(int(hires_size), _LARGEST_TIMED_SPECTRUM)
    pixel = _pixel_seconds(engine, threads, timed, budget_seconds / 5)
    if size == lowres_size and n_images * size * size <= _WHOLE_PLAN_PIXELS:
        # Small plans: the engine's own iterations, whose fixed costs (threads handing over, the
        # interpreter between batches) a sample would leave out; what the spectrum steps take is then
        # set apart, as the plan's spectrum may be larger than this one.
        seconds, spectrum_pixels = _iteration_seconds(engine, int(n_images), pupil_radius_px, step_px, size,
                                                      budget_seconds)
        per_capture = max(seconds - spectrum_pixels * pixel, seconds / 2) / n_images
    else:
        per_capture = _pass_seconds(sample, pupil_radius_px * scale, step_px * scale, size, chunk, threads,
                                    budget_seconds) / sample
        per_capture *= _fft_work(lowres_size) / _fft_work(size)
    return IterationCost(engine=engine, threads=threads, capture_seconds=per_capture, pixel_seconds=pixel)


def _fft_work(size: int) -> float:
    """Relative work of one ``size`` x ``size`` FFT."""
    return size * size * math.log2(max(size, 2))


def _lattice(count: int, step_px: float) -> np.ndarray:
    """``count`` pupil centres ``[y, x]`` on a square lattice of ``step_px`` around DC."""
    side = math.ceil(math.sqrt(count))
    offsets = (np.arange(side) - (side - 1) / 2.0) * step_px
    yy, xx = np.meshgrid(offsets, offsets, indexing="ij")
    return np.stack([yy.ravel(), xx.ravel()], axis=1)[:count]


def _median_seconds(run, budget_seconds: float) -> float:
    """Median wall time of ``run()`` over about ``budget_seconds``, after one untimed call (plans, first touches)."""
    run()
    least, most = _REPEATS
    times: list[float] = []
    while len(times) < least or (len(times) < most and sum(times) < budget_seconds):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _iteration_seconds(engine: str, count: int, radius: float, step_px: float, size: int,
                       budget_seconds: float) -> tuple[float, int]:
    """Seconds of an iteration of ``engine`` (default options) on ``count`` flat captures, and its spectrum's pixels."""
    layout = band_layout(_lattice(count, step_px), radius, lowres_size=size)
    model = ForwardModel.unaberrated(layout)
    problem = PhaseRetrievalProblem(model=model, amplitudes=np.ones((count,) + model.field_shape, np.float32))
    entry = get_engine(engine)
    work = entry.engine_class()(problem, entry.options())
    try:
        return _median_seconds(work.update, budget_seconds), work.spectrum().size
    finally:
        work.close()


def _pass_seconds(count: int, radius: float, step_px: float, size: int, chunk: int, threads: int,
                  budget_seconds: float) -> float:
    """Seconds of a pass over ``count`` captures in chunks of ``chunk`` on ``threads`` threads.

    The pass places each capture's pupil box, transforms it, takes the magnitude
    step, transforms back and adds it into the spectrum, as both engines do.
    """
    layout = band_layout(_lattice(count, step_px), radius, lowres_size=size)
    model = ForwardModel.unaberrated(layout)
    rng = np.random.default_rng(0)
    shape = model.spectrum_shape
    spectrum = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    amplitudes = np.ones((count,) + model.field_shape, np.float32)
    out = np.empty_like(spectrum)
    work = ChunkedPass(model, chunk=chunk, threads=threads)

    def magnitude_step(fields, images, scratch):
        return kernels.project_magnitudes(fields, amplitudes[images], scratch, eps=1e-6)

    try:
        return _median_seconds(lambda: work.run(spectrum, magnitude_step, out), budget_seconds)
    finally:
        work.close()


def _pixel_seconds(engine: str, threads: int, size: int, budget_seconds: float) -> float:
    """Seconds per spectrum pixel of the engine's whole-spectrum steps of one iteration, timed on ``size``²."""
    spectrum = np.ones((size, size), np.complex64)
    other = np.ones_like(spectrum)
    if engine == "momentum":
        velocity = np.zeros_like(spectrum)
        step = lambda: kernels.momentum_step(spectrum, other, velocity, 0.5)  # noqa: E731
    else:
        accumulators = [np.zeros_like(spectrum) for _ in range(threads)]
        inverse_normal = np.ones((size, size), np.float32)

        def step():
            # ChunkedPass clears each thread's accumulator and sums them; then the Tikhonov update.
            for accumulator in accumulators:
                accumulator.fill(0)
            np.copyto(other, accumulators[0])
            for accumulator in accumulators[1:]:
                np.add(other, accumulator, out=other)
            kernels.tikhonov_update(other, inverse_normal, spectrum)

    return _median_seconds(step, budget_seconds) / (size * size)
