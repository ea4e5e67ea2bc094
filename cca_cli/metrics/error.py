"""Image error metrics against a known ground truth.

All sums are accumulated in float64, whatever the input dtype, so float32
images give the same result as their float64 copies to ~1e-7.
"""

from __future__ import annotations

import numpy as np

__all__ = ["rmse", "amplitude_rmse", "relative_error"]


def _pair(name_a: str, a, name_b: str, b, *, allow_complex: bool) -> tuple[np.ndarray, np.ndarray]:
    """Validate two arrays (same shape, numeric, finite) and return float64/complex128 copies."""
    arrs = []
    for name, x in ((name_a, a), (name_b, b)):
        arr = np.asarray(x)
        if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.number):
            raise ValueError(f"{name}: expected a numeric array, got dtype {arr.dtype}")
        if np.iscomplexobj(arr) and not allow_complex:
            raise ValueError(f"{name}: expected a real array, got dtype {arr.dtype}")
        if arr.size == 0:
            raise ValueError(f"{name}: expected a non-empty array, got shape {arr.shape}")
        arrs.append(arr)
    if arrs[0].shape != arrs[1].shape:
        raise ValueError(
            f"{name_a}: expected the shape of {name_b} {arrs[1].shape}, got shape {arrs[0].shape}"
        )
    out = []
    for name, arr in ((name_a, arrs[0]), (name_b, arrs[1])):
        arr = arr.astype(np.complex128 if np.iscomplexobj(arr) else np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}: expected finite values, got NaN or infinity")
        out.append(arr)
    return out[0], out[1]


def _scaled_rmse(rec: np.ndarray, truth: np.ndarray, fit_scale: bool) -> float:
    if not isinstance(fit_scale, (bool, np.bool_)):
        raise ValueError(f"fit_scale: expected a bool, got {fit_scale!r}")
    peak = float(np.max(np.abs(truth)))
    if peak <= 0.0:
        raise ValueError("truth: expected an image with a non-zero maximum, got all zeros")
    if fit_scale:
        rr = float(np.vdot(rec, rec).real)
        if rr > 0.0:
            rec = rec * (float(np.vdot(rec, truth).real) / rr)
    diff = rec - truth
    return float(np.sqrt(np.mean(diff * diff)) / peak)


def rmse(recovered, truth, *, fit_scale: bool = True) -> float:
    """Normalised root-mean-square error between two real images.

    Parameters
    ----------
    recovered : array_like
        Real image (e.g. recovered intensity), any numeric dtype.
    truth : array_like
        Real ground-truth image of the same shape, with a non-zero maximum.
    fit_scale : bool, keyword-only, default True
        Fit a global intensity scale to ``recovered`` first (the scale of a
        phase-retrieval result is arbitrary).

    Returns
    -------
    float
        The normalised RMSE, in units of the truth's full scale.

    Raises
    ------
    ValueError
        On a shape mismatch (both shapes are named), complex or non-numeric
        input, NaN/inf values, or an all-zero truth.

    Notes
    -----
    With ``r`` = recovered and ``t`` = truth (flattened, N pixels)::

        a    = <r, t> / <r, r>          if fit_scale (a = 1 otherwise, or if r = 0)
        RMSE = sqrt( sum((a r - t)**2) / N ) / max|t|

    so for a chart with maximum 1 the RMSE is in units of full-scale
    intensity.  Sums are accumulated in float64.
    """
    rec, tru = _pair("recovered", recovered, "truth", truth, allow_complex=False)
    return _scaled_rmse(rec, tru, fit_scale)


def amplitude_rmse(recovered_field, truth_field, *, fit_scale: bool = True) -> float:
    """Normalised RMSE between the amplitudes of two fields.

    Parameters
    ----------
    recovered_field : array_like
        Complex (or real) recovered field.
    truth_field : array_like
        Complex (or real) ground-truth field of the same shape.
    fit_scale : bool, keyword-only, default True
        Fit a global amplitude scale first, as in :func:`rmse`.

    Returns
    -------
    float
        :func:`rmse` of ``|recovered_field|`` against ``|truth_field|``.

    Raises
    ------
    ValueError
        As :func:`rmse`.

    Notes
    -----
    ``a = <|r|, |t|> / <|r|, |r|>``, ``RMSE = sqrt(mean((a|r| - |t|)**2)) /
    max|t|``; the phase of both fields is ignored.
    """
    rec, tru = _pair(
        "recovered_field", recovered_field, "truth_field", truth_field, allow_complex=True
    )
    return _scaled_rmse(np.abs(rec), np.abs(tru), fit_scale)


def relative_error(a, b) -> float:
    """Relative error of ``a`` with respect to the reference ``b``.

    Parameters
    ----------
    a : array_like
        Estimate (real or complex).
    b : array_like
        Reference of the same shape, not all zero.

    Returns
    -------
    float
        ``||a - b|| / ||b||`` (Frobenius / Euclidean norms over all elements).

    Raises
    ------
    ValueError
        On a shape mismatch, NaN/inf values, or ``||b|| = 0``.

    Notes
    -----
    ``||x|| = sqrt(sum |x_i|**2)``, accumulated in float64 / complex128.
    """
    x, y = _pair("a", a, "b", b, allow_complex=True)
    nb = float(np.linalg.norm(y.ravel()))
    if nb == 0.0:
        raise ValueError("b: expected a reference with non-zero norm, got all zeros")
    return float(np.linalg.norm((x - y).ravel()) / nb)
