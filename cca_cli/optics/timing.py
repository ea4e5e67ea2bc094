"""A short measurement of this machine's FFT rate, for run-time estimates."""

from __future__ import annotations

import time

import numpy as np

from cca_cli.optics import fft

__all__ = ["fft_seconds"]


def fft_seconds(size: int, *, batch: int = 8, repeats: int = 3) -> float:
    """Seconds per ``size`` x ``size`` complex64 FFT, timed on a batch of ``batch`` transforms.

    Parameters
    ----------
    size : int
        Side of the transform.
    batch, repeats : int
        Transforms per timed call and timed calls (the fastest is kept).

    Returns
    -------
    float
        Best time of one transform (s), through :class:`~cca_cli.optics.fft.InPlaceFFT2`
        as the engines use it.
    """
    buffer = fft.zeros((batch, size, size), np.complex64)
    plan = fft.InPlaceFFT2(buffer)
    buffer[...] = 0  # planning may leave arbitrary values in the buffer
    buffer[:, 0, 0] = 1
    plan.forward()
    best = float("inf")
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        plan.forward()
        plan.inverse()
        best = min(best, time.perf_counter() - start)
    return best / (2 * batch)
