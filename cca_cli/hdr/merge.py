"""Merge an exposure bracket into one linear radiance map.

The prototype records several exposures at every camera position. Each
exposure is linear in scene radiance up to the sensor's saturation level,
so ``x_e / t_e`` (counts per second) estimates the same radiance from every
exposure that is neither clipped nor lost in the noise floor. This module
combines those estimates per pixel with weights that favour the exposures
that collected the most signal.

Weighting
---------
For an unsaturated exposure that is above the noise floor the weight is the
exposure time, ``w_e = t_e``; all other exposures get ``w_e = 0``. Under
shot noise the variance of ``x_e / t_e`` is ``L / t_e`` (``L`` the
radiance), so ``w_e = t_e`` is the inverse-variance (maximum-likelihood)
weight, and the merged radiance reduces to ``sum(x_e) / sum(t_e)`` over the
usable exposures: the total counts collected divided by the total time they
took. Unlike a hat function it does not down-weight a long exposure that is
well inside the linear range, and it needs no tuning beyond the two
thresholds.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

__all__ = ["HdrResult", "merge_exposures"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HdrResult:
    """Merged radiance of one exposure bracket (or a batch of brackets).

    Attributes
    ----------
    radiance : numpy.ndarray
        float32 ``(..., H, W)`` linear radiance in counts per second.
    weight : numpy.ndarray
        float32 ``(..., H, W)`` per-pixel confidence in ``[0, 1]``. It is the
        number of counts the usable exposures collected divided by the
        saturation level (relative shot-noise SNR squared of the merged value
        against one full-well exposure), capped at 1 and floored at
        ``min_weight`` for valid pixels. Invalid pixels have weight exactly 0
        and must not constrain a reconstruction.
    valid : numpy.ndarray
        bool ``(..., H, W)``; True where at least one exposure was neither
        saturated nor at or below the noise floor.
    dynamic_range_gain : float
        Measured dynamic range of the merged map (max / min radiance over
        valid pixels) divided by the best dynamic range any single exposure
        index reached on the same pixels (max / min of ``x/t`` over the pixels
        usable in that exposure), floored at 1.0; 1.0 when the scene fits in
        one exposure or no pixel is valid.
    saturated_fraction : float
        Fraction of output pixels saturated in every exposure (no usable
        measurement; radiance is a lower bound).
    underexposed_fraction : float
        Fraction of output pixels at or below the noise floor in every
        usable (unsaturated) exposure.
    exposure_ratio : float
        Longest over shortest exposure time of the bracket (largest over the
        batch); the nominal dynamic range extension.
    """

    radiance: np.ndarray
    weight: np.ndarray
    valid: np.ndarray
    dynamic_range_gain: float
    saturated_fraction: float
    underexposed_fraction: float
    exposure_ratio: float


def _check_exposures(exposure_s: np.ndarray, batch_shape: tuple[int, ...], n_exp: int) -> np.ndarray:
    """Validate exposure times and broadcast them to ``batch_shape + (E,)``."""
    if exposure_s.ndim == 0:
        exposure_s = exposure_s.reshape(1)
    if exposure_s.shape != (n_exp,) and exposure_s.shape != batch_shape + (n_exp,):
        raise ValueError(
            f"exposure_s has shape {exposure_s.shape}; expected ({n_exp},) or "
            f"{batch_shape + (n_exp,)} to match a stack of {n_exp} exposures"
        )
    if not np.all(np.isfinite(exposure_s)):
        raise ValueError("exposure_s contains NaN or infinite exposure times")
    if np.any(exposure_s <= 0):
        bad = float(exposure_s[exposure_s <= 0].ravel()[0])
        raise ValueError(f"exposure time {bad:g} s is not positive; all exposure times must be > 0")
    if n_exp > 1:
        srt = np.sort(exposure_s, axis=-1)
        dup = srt[..., 1:] == srt[..., :-1]
        if np.any(dup):
            value = float(srt[..., 1:][dup].ravel()[0])
            raise ValueError(f"exposure {value:g} s listed twice")
    return np.broadcast_to(exposure_s, batch_shape + (n_exp,))


def merge_exposures(
    stack,
    exposure_s,
    *,
    saturation_level: float,
    noise_floor: float = 0.0,
    min_weight: float = 1e-3,
    saturation_margin: float = 0.01,
) -> HdrResult:
    """Merge linear exposures into a radiance map in counts per second.

    Parameters
    ----------
    stack : array_like
        ``(..., E, H, W)`` linear, black-level-subtracted sensor values in
        counts (e.g. 0..4095 for 12-bit data). Leading axes are batch axes
        (e.g. camera positions), each with its own bracket.
    exposure_s : array_like
        Exposure times in seconds, shape ``(E,)`` (shared by the batch) or
        ``(..., E)`` (one bracket per batch element). All must be > 0 and
        distinct within a bracket.
    saturation_level : float
        Sensor value at which a pixel clips, in the same counts as ``stack``
        (white level minus black level).
    noise_floor : float, optional
        Values at or below this are treated as noise and ignored
        (default 0: only exact zeros are ignored).
    min_weight : float, optional
        Smallest confidence given to a valid pixel, so that ``weight == 0``
        means exactly "invalid". Must be in ``(0, 1]``.
    saturation_margin : float, optional
        Relative margin below ``saturation_level`` from which a value counts
        as saturated (``x >= saturation_level * (1 - margin)``); covers the
        non-linear shoulder of real sensors. Default 0.01.

    Returns
    -------
    HdrResult
        Radiance, confidence weight, validity mask and summary numbers.

    Raises
    ------
    ValueError
        Wrong shapes, fewer than one exposure, NaN/inf values, non-positive
        or duplicate exposure times, or inconsistent thresholds.

    Notes
    -----
    The merge weight is ``w_e = t_e`` for usable exposures (see the module
    docstring), so the radiance is ``sum(x_e) / sum(t_e)`` over exposures
    with ``noise_floor < x_e < saturation_level * (1 - saturation_margin)``.
    Pixels without a usable exposure are marked invalid and get a
    best-effort radiance: if the shortest exposure is saturated, its
    ``x / t`` (a lower bound); otherwise ``x / t`` of the longest
    unsaturated exposure (when everything is under the noise floor that is
    the longest exposure).
    """
    stack = np.asarray(stack)
    if stack.ndim < 3:
        raise ValueError(f"stack has shape {stack.shape}; expected (..., E, H, W) with E >= 1")
    if not np.issubdtype(stack.dtype, np.number) or np.iscomplexobj(stack):
        raise ValueError(f"stack has dtype {stack.dtype}; expected real numbers")
    stack = stack.astype(np.float32, copy=False)
    n_exp = stack.shape[-3]
    if n_exp < 1:
        raise ValueError("stack holds no exposures (E = 0); need at least one")
    batch_shape = stack.shape[:-3]
    if not np.isfinite(stack).all():
        raise ValueError("stack contains NaN or infinite values; fix the input images")
    if not np.isfinite(saturation_level) or saturation_level <= 0:
        raise ValueError(f"saturation_level {saturation_level!r} must be a positive number")
    if not np.isfinite(noise_floor) or noise_floor < 0 or noise_floor >= saturation_level:
        raise ValueError(f"noise_floor {noise_floor!r} must be >= 0 and below saturation_level {saturation_level:g}")
    if not 0 < min_weight <= 1:
        raise ValueError(f"min_weight {min_weight!r} must be in (0, 1]")
    if not 0 <= saturation_margin < 1:
        raise ValueError(f"saturation_margin {saturation_margin!r} must be in [0, 1)")

    t = _check_exposures(np.asarray(exposure_s, dtype=np.float64), batch_shape, n_exp)
    t32 = t.astype(np.float32)[..., None, None]  # (..., E, 1, 1)

    sat_threshold = np.float32(saturation_level * (1.0 - saturation_margin))
    saturated = stack >= sat_threshold
    dark = stack <= np.float32(noise_floor)
    usable = ~(saturated | dark)  # (..., E, H, W)

    w = np.where(usable, t32, np.float32(0.0))
    w_sum = w.sum(axis=-3)
    x_sum = np.where(usable, stack, np.float32(0.0)).sum(axis=-3)
    valid = w_sum > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        merged = x_sum / w_sum

    # Fallback for pixels without a usable exposure.
    order = np.argsort(t, axis=-1)  # (..., E)
    shortest = order[..., 0]
    idx_short = np.broadcast_to(shortest[..., None, None, None], batch_shape + (1,) + stack.shape[-2:])
    x_short = np.take_along_axis(stack, idx_short, axis=-3)[..., 0, :, :]
    t_short = np.take_along_axis(t, shortest[..., None], axis=-1)[..., None].astype(np.float32)
    short_saturated = np.take_along_axis(saturated, idx_short, axis=-3)[..., 0, :, :]
    # Longest unsaturated exposure: maximise t over unsaturated exposures.
    t_unsat = np.where(~saturated, t32, np.float32(-1.0))
    idx_long_unsat = np.argmax(t_unsat, axis=-3)[..., None, :, :]
    x_long = np.take_along_axis(stack, idx_long_unsat, axis=-3)[..., 0, :, :]
    t_long = np.take_along_axis(np.broadcast_to(t32, t_unsat.shape), idx_long_unsat, axis=-3)[..., 0, :, :]
    fallback = np.where(short_saturated, x_short / t_short, x_long / t_long)
    radiance = np.where(valid, merged, fallback).astype(np.float32)

    counts = x_sum
    conf = np.clip(counts / np.float32(saturation_level), np.float32(min_weight), np.float32(1.0))
    weight = np.where(valid, conf, np.float32(0.0)).astype(np.float32)

    all_saturated = saturated.all(axis=-3)
    underexposed = ~valid & ~all_saturated
    n_pix = valid.size
    saturated_fraction = float(all_saturated.sum()) / n_pix
    underexposed_fraction = float(underexposed.sum()) / n_pix
    exposure_ratio = float(np.max(t.max(axis=-1) / t.min(axis=-1)))

    gain = _dynamic_range_gain(radiance, valid, stack, t32, usable)
    if saturated_fraction > 0.01:
        _log.warning(
            "%.1f%% of pixels are saturated in every exposure; add a shorter exposure",
            100 * saturated_fraction,
        )

    return HdrResult(
        radiance=radiance,
        weight=weight,
        valid=valid,
        dynamic_range_gain=gain,
        saturated_fraction=saturated_fraction,
        underexposed_fraction=underexposed_fraction,
        exposure_ratio=exposure_ratio,
    )


def _dynamic_range_gain(radiance, valid, stack, t32, usable) -> float:
    """Measured dynamic range of the merge over the best single exposure's."""
    if not valid.any():
        return 1.0
    merged_vals = radiance[valid]
    merged_dr = float(merged_vals.max()) / float(merged_vals.min())
    best_single = 1.0
    for e in range(stack.shape[-3]):
        use = usable[..., e, :, :]
        if not use.any():
            continue
        t_e = np.broadcast_to(t32[..., e, :, :], use.shape)[use]
        vals = stack[..., e, :, :][use] / t_e
        best_single = max(best_single, float(vals.max()) / float(vals.min()))
    return float(max(merged_dr / best_single, 1.0)) if merged_dr > 0 else 1.0
