"""Magnitude projections: replace field magnitudes with measured ones (pure, in place)."""

from __future__ import annotations

import numpy as np

from cca_cli.optics import kernels

__all__ = ["project_magnitudes", "project_grouped_magnitudes"]


def project_magnitudes(fields: np.ndarray, amplitudes: np.ndarray, scratch: np.ndarray, *,
                       weights: np.ndarray | None = None, eps: float = 1e-12) -> float:
    """Replace ``|ψ|`` by the measured amplitude, keeping the phase; return the squared misfit.

    ``ψ ← w · A ψ/max(|ψ|, ε) + (1 − w) · ψ`` with ``w = 1`` when no weights are given,
    in one fused pass (:func:`cca_cli.optics.kernels.project_magnitudes`).

    Parameters
    ----------
    fields : ndarray, complex64, (k, m, m)
        Fields ψ, modified in place.
    amplitudes : ndarray, float32, (k, m, m)
        Measured amplitudes A.
    scratch : ndarray, float32, (2, k, m, m)
        Work arrays (overwritten).
    weights : ndarray, float32, (k, m, m), optional
        Per-pixel confidence in [0, 1].
    eps : float
        Floor on ``|ψ|`` to avoid division by zero.

    Returns
    -------
    float
        ``Σ w (|ψ| − A)²`` over the chunk, before the projection.
    """
    return kernels.project_magnitudes(fields, amplitudes, scratch, weights=weights, eps=eps)


def project_grouped_magnitudes(fields: np.ndarray, amplitudes: np.ndarray, scratch: np.ndarray,
                               offsets: np.ndarray, *, weights: np.ndarray | None = None,
                               eps: float = 1e-12) -> float:
    """Joint magnitude projection of fields whose intensities add up to one measurement.

    For each group ``g`` (fields ``offsets[g]:offsets[g+1]``) with measured
    amplitude ``A_g = √I_g``: ``ψ_i ← w · A_g / √(Σ_j |ψ_j|²) · ψ_i + (1 − w) · ψ_i``
    for every ``i`` in the group. With one field per group this is
    :func:`project_magnitudes`.

    Parameters
    ----------
    fields : ndarray, complex64, (k, m, m)
        Fields ψ of consecutive virtual captures, modified in place.
    amplitudes : ndarray, float32, (g, m, m)
        Measured amplitudes of the g groups.
    scratch : ndarray, float32, (k, m, m) or (2, k, m, m)
        Work array(s) (overwritten; only the first is used).
    offsets : ndarray, int, (g + 1,)
        Group boundaries within ``fields`` (``offsets[0] == 0``, ``offsets[-1] == k``).
    weights : ndarray, float32, (g, m, m), optional
        Per-pixel confidence of each measurement in [0, 1].
    eps : float
        Floor on the modelled amplitude ``√(Σ |ψ|²)``.

    Returns
    -------
    float
        ``Σ w (√(Σ_j |ψ_j|²) − A_g)²`` over the groups, before the projection.
    """
    power = np.abs(fields, out=scratch[0] if scratch.ndim == 4 else scratch)
    np.square(power, out=power)
    squared = 0.0
    for g in range(len(offsets) - 1):
        lo, hi = int(offsets[g]), int(offsets[g + 1])
        magnitude = np.sqrt(power[lo:hi].sum(axis=0) if hi - lo > 1 else power[lo])
        misfit = magnitude - amplitudes[g]
        if weights is not None:
            misfit *= np.sqrt(weights[g])
        flat = misfit.reshape(-1)
        squared += float(np.dot(flat, flat))
        np.maximum(magnitude, np.float32(eps), out=magnitude)
        ratio = np.divide(amplitudes[g], magnitude, out=magnitude)
        if weights is not None:
            ratio *= weights[g]
            ratio += 1.0 - weights[g]
        fields[lo:hi] *= ratio
    return squared
