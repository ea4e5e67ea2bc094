"""Shared pieces of the benchmarks: the headline problem and robust timing."""

from __future__ import annotations

import time

import numpy as np

from cca_cli.config.load import load_config
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.optics import fft
from cca_cli.library.recovery import build_model
from cca_cli.stages.simulate import simulate


def headline_problem(*, store: str = "band", seed: int = 0):
    """The paper's Fig. 5 data made by our simulator, prepared for the engines.

    Returns
    -------
    problem : PhaseRetrievalProblem
    simulation : Simulation
    """
    config = load_config()
    config = config.model_copy(update={
        "simulate": config.simulate.model_copy(update={"store": store}),
        "noise": config.noise.model_copy(update={"seed": seed}),
    })
    simulation = simulate(config)
    model = build_model(simulation.geometry, simulation.intensity.shape[-1])
    return PhaseRetrievalProblem.from_sensor_images(model, simulation.intensity), simulation


def median_seconds(func, *, repeats: int = 7, warmup: int = 1) -> float:
    """Median wall time of ``func()`` over ``repeats`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        func()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        func()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def fft_floor_seconds(n_images: int, size: int, *, repeats: int = 7) -> tuple[float, str]:
    """Fastest time of the FFTs one iteration must do: one inverse and one forward per capture.

    Every combination of FFTW planning effort (measure, patient) and layout (one
    batched plan over all captures on all threads, or chunks of 12 or 16 captures
    on worker threads) is timed; the fastest is the floor.
    """
    import os
    from concurrent.futures import ThreadPoolExecutor

    threads = fft.cpu_count()
    candidates = []
    previous = os.environ.get("CCA_FFTW_PLANNING")
    with ThreadPoolExecutor(threads) as pool:
        try:
            for effort in ("measure", "patient"):
                os.environ["CCA_FFTW_PLANNING"] = effort
                buffer = fft.zeros((n_images, size, size))
                plan = fft.InPlaceFFT2(buffer)
                candidates.append((median_seconds(lambda: (plan.inverse(), plan.forward()), repeats=repeats),
                                   f"one batched plan, {effort}"))
                for chunk in (12, 16):
                    plans = [fft.InPlaceFFT2(fft.zeros((chunk, size, size)), threads=1) for _ in range(threads)]
                    n_chunks = -(-n_images // chunk)

                    def work(t, plans=plans, n_chunks=n_chunks):
                        for _ in range(t, n_chunks, threads):
                            plans[t].inverse()
                            plans[t].forward()

                    candidates.append((median_seconds(lambda: list(pool.map(work, range(threads))), repeats=repeats),
                                       f"chunks of {chunk} on {threads} threads, {effort}"))
        finally:
            if previous is None:
                os.environ.pop("CCA_FFTW_PLANNING", None)
            else:
                os.environ["CCA_FFTW_PLANNING"] = previous
    return min(candidates)
