"""A full pass over all captures: forward, an in-place operation, adjoint.

Captures are processed in chunks small enough to stay in cache between the
inverse FFT, the magnitude projection and the forward FFT; chunks run on a
few worker threads (FFTW and numpy release the GIL), each with its own
buffer, FFT plan and spectrum accumulator.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel, chunk_slices

__all__ = ["ChunkedPass"]

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
