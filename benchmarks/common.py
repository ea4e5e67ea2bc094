"""Shared pieces of the benchmarks: the headline problem and robust timing."""

from __future__ import annotations

import time

import numpy as np

from cca_cli.config.load import load_config
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.optics import fft
from cca_cli.stages.reconstruct import build_model
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

    Both a single batched plan over all captures (all threads) and cache-sized
    chunks on worker threads are timed; the faster is the floor.
    """
    from concurrent.futures import ThreadPoolExecutor

    buffer = fft.zeros((n_images, size, size))
    plan = fft.InPlaceFFT2(buffer)
    whole = median_seconds(lambda: (plan.inverse(), plan.forward()), repeats=repeats)

    threads = fft.cpu_count()
    chunk = 16
    per_thread = [fft.zeros((chunk, size, size)) for _ in range(threads)]
    plans = [fft.InPlaceFFT2(b, threads=1) for b in per_thread]
    n_chunks = -(-n_images // chunk)

    def chunked():
        def work(t):
            for _ in range(t, n_chunks, threads):
                plans[t].inverse()
                plans[t].forward()
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(work, range(threads)))

    pool_time = median_seconds(chunked, repeats=repeats)
    return (whole, "one batched plan") if whole <= pool_time else (pool_time, "chunked threads")
