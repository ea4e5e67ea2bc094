"""Data residual of a recovery split into bright-field and dark-field captures.

The residual compares a method's modelled amplitudes ``|ψ_k|`` with the
measured ``√I_k``. Methods normalise their objects differently, so one global
scale ``s`` (least squares over all captures) is fitted first; it is the
same for every subset, so a method cannot lower its dark-field figure by
rescaling dark-field frames alone:

    r_subset = ‖s·|ψ| − √I‖_subset / ‖√I‖_subset,   s = ⟨|ψ|, √I⟩ / ⟨|ψ|, |ψ|⟩ over all captures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SplitResidual", "split_amplitude_residual"]


@dataclass(frozen=True)
class SplitResidual:
    """Amplitude residuals with one global scale.

    Attributes
    ----------
    all, bright_field, dark_field : float
        ``‖s·|ψ| − √I‖ / ‖√I‖`` summed over all, bright-field and dark-field
        captures (NaN for an empty subset).
    scale : float
        The least-squares scale ``s`` fitted over all captures.
    per_capture : ndarray, float64, (K,)
        ``‖s·|ψ_k| − √I_k‖ / ‖√I_k‖`` of each capture (NaN where ``√I_k`` is 0).
    """

    all: float
    bright_field: float
    dark_field: float
    scale: float
    per_capture: np.ndarray


def split_amplitude_residual(modelled, measured, bright_field) -> SplitResidual:
    """Relative amplitude residual over all / bright-field / dark-field captures.

    Parameters
    ----------
    modelled : array_like, (K, ...)
        Modelled amplitudes ``|ψ_k|`` (non-negative; complex fields are
        reduced to their modulus).
    measured : array_like, (K, ...)
        Measured amplitudes ``√I_k``, same shape.
    bright_field : array_like of bool, (K,)
        True for captures whose illumination lies inside the objective's
        pupil (illumination NA < objective NA).

    Returns
    -------
    SplitResidual

    Raises
    ------
    ValueError
        Shapes differ, the mask does not have one entry per capture, or the
        modelled amplitudes are all zero.
    """
    model = np.abs(np.asarray(modelled)).astype(np.float64, copy=False)
    data = np.asarray(measured, dtype=np.float64)
    if model.shape != data.shape or model.ndim < 2:
        raise ValueError(f"modelled: expected the shape of measured {data.shape} (K, ...), got {model.shape}")
    k = data.shape[0]
    mask = np.asarray(bright_field, dtype=bool).reshape(-1)
    if mask.size != k:
        raise ValueError(f"bright_field: expected one entry per capture ({k}), got {mask.size}")
    model = model.reshape(k, -1)
    data = data.reshape(k, -1)
    mm = float(np.einsum("ij,ij->", model, model))
    if not mm > 0:
        raise ValueError("modelled: all amplitudes are zero; nothing to scale")
    scale = float(np.einsum("ij,ij->", model, data)) / mm
    err2 = np.einsum("ij,ij->i", scale * model - data, scale * model - data)
    ref2 = np.einsum("ij,ij->i", data, data)

    def ratio(select) -> float:
        den = float(ref2[select].sum())
        return float(np.sqrt(err2[select].sum() / den)) if den > 0 else float("nan")

    with np.errstate(invalid="ignore", divide="ignore"):
        per = np.where(ref2 > 0, np.sqrt(err2 / np.where(ref2 > 0, ref2, 1.0)), np.nan)
    return SplitResidual(all=ratio(slice(None)), bright_field=ratio(mask), dark_field=ratio(~mask),
                         scale=scale, per_capture=per)
