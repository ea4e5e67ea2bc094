"""Work split into shares that run side by side on a few threads for one call.

For steps outside the passes (which keep their own worker threads, :mod:`cca_cli.engines.passes`) whose
shares release the GIL (numpy, scipy.ndimage, FFTW): each share writes its own part of the result, so any
thread count gives the same values.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

__all__ = ["run_side_by_side"]


def run_side_by_side(work: Callable[[int], None], count: int) -> None:
    """Run ``work(t)`` for ``t = 0 … count - 1`` side by side (``t = 0`` on the calling thread).

    An exception in any share is raised here, after every share has finished.
    """
    if count <= 1:
        work(0)
        return
    with ThreadPoolExecutor(count - 1) as pool:
        futures = [pool.submit(work, t) for t in range(1, count)]
        work(0)
        for future in futures:
            future.result()
