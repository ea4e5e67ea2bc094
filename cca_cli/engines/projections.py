"""Magnitude projections: replace field magnitudes with measured ones (pure, in place)."""

from __future__ import annotations

import numpy as np

__all__ = ["project_magnitudes"]


def project_magnitudes(fields: np.ndarray, amplitudes: np.ndarray, scratch: np.ndarray, *,
                       weights: np.ndarray | None = None, eps: float = 1e-12) -> float:
    """Replace ``|ψ|`` by the measured amplitude, keeping the phase; return the squared misfit.

    ``ψ ← w · A ψ/|ψ| + (1 − w) · ψ`` with ``w = 1`` when no weights are given.

    Parameters
    ----------
    fields : ndarray, complex64, (k, m, m)
        Fields ψ, modified in place.
    amplitudes : ndarray, float32, (k, m, m)
        Measured amplitudes A.
    scratch : ndarray, float32, (k, m, m)
        Work array (overwritten).
    weights : ndarray, float32, (k, m, m), optional
        Per-pixel confidence in [0, 1].
    eps : float
        Floor on ``|ψ|`` to avoid division by zero.

    Returns
    -------
    float
        ``Σ w (|ψ| − A)²`` over the chunk, before the projection.
    """
    magnitude = np.abs(fields, out=scratch)
    misfit = magnitude - amplitudes
    if weights is not None:
        misfit *= np.sqrt(weights)
    squared = float(np.vdot(misfit.ravel(), misfit.ravel()))
    np.maximum(magnitude, eps, out=magnitude)
    ratio = np.divide(amplitudes, magnitude, out=magnitude)
    if weights is not None:
        ratio *= weights
        ratio += 1.0 - weights
    fields *= ratio
    return squared
