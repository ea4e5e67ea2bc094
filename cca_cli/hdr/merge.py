"""Merge an exposure bracket into one linear radiance map, without bias at the dark end.

Every exposure ``e`` of a pixel with radiance ``L`` (counts per second)
records ``x_e = L t_e + n_e`` counts after the black level is subtracted,
with noise variance ``σ_e² = σ_r² + L t_e / g`` (read noise ``σ_r`` in
counts, shot noise for ``g`` electrons per count). Each unsaturated
exposure is an unbiased estimate ``x_e / t_e`` of ``L`` — including values
at or below zero, which a dim pixel records about half the time: dropping
them (or clipping them at zero) biases dim pixels upwards, by a factor of
tens in dark-field views. The merge is the inverse-variance mean

    L̂ = Σ_e w_e x_e / t_e / Σ_e w_e,   w_e = t_e² / σ_e²,   var(L̂) = 1 / Σ_e w_e,

over every unsaturated exposure. The weights are evaluated at a smoothed
first estimate of ``L`` (not at each pixel's own noisy values, which would
correlate weights and noise and bias the mean again). An exposure is also
left out where that estimate predicts it to be within three noise standard
deviations of saturation, so that keeping only the frames that happened
to stay below the clipping level does not bias bright pixels downwards.

Checks and figures
------------------
* Flux ratios: over the pixels usable in every exposure, ``Σ x_e / t_e``
  divided by ``Σ L̂`` must be 1 for every exposure (exposure times, black
  level and linearity agree); each ratio comes with its standard deviation.
* Dynamic range: the ratio of the brightest to the faintest radiance (99.9th
  and 0.1st percentiles) among pixels measured with SNR ≥ 10, for the merge
  and for each single exposure; the gain is the merge's range over the best
  single exposure's. A scene that fits one exposure has gain 1.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

__all__ = ["HdrResult", "NoiseModel", "merge_exposures", "estimate_noise"]

_log = logging.getLogger(__name__)

#: SNR a pixel needs to count towards the dynamic range.
DYNAMIC_RANGE_SNR = 10.0
#: Noise standard deviations kept between a predicted value and the saturation level.
SATURATION_SIGMAS = 3.0


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise in counts: ``σ² = read_noise² + signal / electrons_per_count``.

    Attributes
    ----------
    read_noise : float
        Read noise (counts RMS), quantisation included.
    electrons_per_count : float
        Conversion gain g.
    source : str
        Where the values came from (manifest, dark frames, brackets …).
    """

    read_noise: float
    electrons_per_count: float
    source: str = "given"

    def variance(self, signal):
        """Noise variance (counts²) of a frame whose expected signal is ``signal`` counts (clipped at 0)."""
        return np.float32(self.read_noise**2) + np.maximum(signal, 0) / np.float32(self.electrons_per_count)


@dataclass(frozen=True)
class HdrResult:
    """Merged radiance of one exposure bracket (or a batch of brackets).

    Attributes
    ----------
    radiance : numpy.ndarray
        float32 ``(..., H, W)`` linear radiance in counts per second (may be
        negative where the scene is dark: noise about zero).
    variance : numpy.ndarray
        float32 ``(..., H, W)`` variance of ``radiance`` from the noise model.
    weight : numpy.ndarray
        float32 ``(..., H, W)`` confidence in ``[0, 1]`` for the recovery: the
        amplitude-domain precision of the pixel relative to a shot-noise
        limited pixel of the longest exposure (floored at ``min_weight``);
        exactly 0 where every exposure is saturated.
    valid : numpy.ndarray
        bool ``(..., H, W)``; True where at least one exposure is unsaturated.
    flux_ratio : numpy.ndarray
        float64 ``(..., E)``, exposures ascending: each exposure's flux over
        the merged flux on the pixels usable in every exposure (1 = linear,
        consistent data; NaN when no pixel is usable in every exposure).
    flux_ratio_sigma : numpy.ndarray
        float64 ``(..., E)``: standard deviation of ``flux_ratio`` from the
        noise model.
    dynamic_range : numpy.ndarray
        float64 ``(...)``: radiance range measured with SNR ≥ 10 by the merge.
    dynamic_range_gain : numpy.ndarray
        float64 ``(...)``: that range over the best single exposure's (≥ 1).
    saturated_fraction : float
        Fraction of pixels saturated in every exposure (radiance is a lower bound).
    underexposed_fraction : float
        Fraction of pixels whose merged SNR is below 1.
    exposure_ratio : float
        Longest over shortest exposure time (largest over the batch).
    noise : NoiseModel
        The noise model used.
    """

    radiance: np.ndarray
    variance: np.ndarray
    weight: np.ndarray
    valid: np.ndarray
    flux_ratio: np.ndarray
    flux_ratio_sigma: np.ndarray
    dynamic_range: np.ndarray
    dynamic_range_gain: np.ndarray
    saturated_fraction: float
    underexposed_fraction: float
    exposure_ratio: float
    noise: NoiseModel


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


def _check_stack(stack) -> np.ndarray:
    stack = np.asarray(stack)
    if stack.ndim < 3:
        raise ValueError(f"stack has shape {stack.shape}; expected (..., E, H, W) with E >= 1")
    if not np.issubdtype(stack.dtype, np.number) or np.iscomplexobj(stack):
        raise ValueError(f"stack has dtype {stack.dtype}; expected real numbers")
    stack = stack.astype(np.float32, copy=False)
    if stack.shape[-3] < 1:
        raise ValueError("stack holds no exposures (E = 0); need at least one")
    if not np.isfinite(stack).all():
        raise ValueError("stack contains NaN or infinite values; fix the input images")
    return stack


def _saturation(saturation_level, stack: np.ndarray, margin: float) -> np.ndarray:
    level = np.asarray(saturation_level, np.float32)
    if not np.all(np.isfinite(level)) or np.any(level <= 0):
        raise ValueError(f"saturation_level must be positive and finite (got min {float(np.min(level)):g})")
    try:
        np.broadcast_shapes(level.shape, stack.shape)
    except ValueError:
        raise ValueError(f"saturation_level has shape {level.shape}; it must broadcast to the stack "
                         f"{stack.shape}") from None
    return level * np.float32(1.0 - margin)


def _smooth(image: np.ndarray, radius: int) -> np.ndarray:
    """Box mean over ``(2 radius + 1)²`` pixels of the last two axes (edges replicated)."""
    if radius <= 0:
        return image
    from scipy.ndimage import uniform_filter

    size = (1,) * (image.ndim - 2) + (2 * radius + 1, 2 * radius + 1)
    return uniform_filter(image, size=size, mode="nearest")


def _ascending(stack: np.ndarray, t: np.ndarray, thr: np.ndarray):
    """Stack, exposure times and saturation levels with exposures in ascending order (levels full size)."""
    order = np.argsort(t, axis=-1)
    thr = np.broadcast_to(thr, stack.shape)
    if np.all(order == np.arange(t.shape[-1])):
        return stack, t, thr
    idx = np.broadcast_to(order[..., None, None], order.shape + stack.shape[-2:])
    return (np.take_along_axis(stack, idx, axis=-3), np.take_along_axis(t, order, axis=-1),
            np.take_along_axis(thr, idx, axis=-3))


def _first_estimate(stack, t32, saturated):
    """Plain ratio Σ x / Σ t over unsaturated exposures (unbiased, noisy); saturated-everywhere → lower bound."""
    open_ = ~saturated
    t_sum = np.where(open_, t32, np.float32(0)).sum(axis=-3)
    x_sum = np.where(open_, stack, np.float32(0)).sum(axis=-3)
    valid = t_sum > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        first = np.where(valid, x_sum / np.where(valid, t_sum, 1), np.float32(0))
    return first.astype(np.float32), valid


def estimate_noise(stack, exposure_s, *, saturation_level, saturation_margin: float = 0.01,
                   max_pixels: int = 2_000_000, seed: int = 0) -> NoiseModel:
    """Read noise and conversion gain from exposure brackets of a static scene (photon transfer).

    For two unsaturated exposures a < b of a pixel, ``d = x_b − ρ x_a``
    (``ρ = t_b / t_a``) has mean zero whatever the scene, and variance
    ``σ_r² (1 + ρ²) + L t_b (1 + ρ) / g``. Pixels are binned by their
    (smoothed) radiance, the variance of each bin measured robustly (MAD),
    and ``σ_r²`` and ``1/g`` fitted by weighted least squares over the bins
    of every pair of neighbouring exposures.

    Parameters
    ----------
    stack : array_like, (..., E, H, W)
        Black-subtracted frames (counts).
    exposure_s : array_like, (E,) or (..., E)
    saturation_level : float or array_like
        As for :func:`merge_exposures`.

    Returns
    -------
    NoiseModel
        ``source="exposure brackets"``; read noise at least 0.3 counts (the
        quantisation floor) and a gain of 1 electron per count when the
        brackets do not constrain it (a single exposure, or no shot noise visible).
    """
    stack = _check_stack(stack)
    n_exp = stack.shape[-3]
    batch = stack.shape[:-3]
    t = _check_exposures(np.asarray(exposure_s, np.float64), batch, n_exp)
    if n_exp < 2:
        return NoiseModel(1.0, 1.0, "default (single exposure)")
    frames, t_sorted, thr = _ascending(stack, t, _saturation(saturation_level, stack, saturation_margin))
    frames = frames.reshape((-1, n_exp) + stack.shape[-2:])
    thr = thr.reshape(frames.shape)
    t_sorted = t_sorted.reshape(-1, n_exp)
    first, _ = _first_estimate(frames, t_sorted.astype(np.float32)[..., None, None], frames >= thr)
    radiance = _smooth(first, 2)
    # Only pixels whose neighbourhood is flat: near edges the smoothed radiance is not the pixel's.
    fine, coarse = _smooth(first, 1), _smooth(first, 3)
    flat = np.abs(fine - coarse) <= 0.05 * np.abs(coarse) + 1.0 / t_sorted[:, -1, None, None]
    rng = np.random.default_rng(seed)
    rows, design, weights = [], [], []
    for a in range(n_exp - 1):
        b = a + 1
        rho = t_sorted[:, b] / t_sorted[:, a]
        ok = (frames[:, b] < thr[:, b]) & (frames[:, a] < thr[:, a]) & flat
        d = frames[:, b] - rho[:, None, None].astype(np.float32) * frames[:, a]
        u = np.maximum(radiance, 0) * (t_sorted[:, b] * (1 + rho))[:, None, None]
        c = np.broadcast_to((1 + rho**2)[:, None, None], d.shape)
        d, u, c = d[ok], u[ok], c[ok]
        if d.size < 200:
            continue
        if d.size > max_pixels:
            pick = rng.choice(d.size, max_pixels, replace=False)
            d, u, c = d[pick], u[pick], c[pick]
        edges = np.unique(np.quantile(u, np.linspace(0, 1, 25)))
        which = np.clip(np.searchsorted(edges, u, side="right") - 1, 0, len(edges) - 2)
        for bin_ in range(len(edges) - 1):
            sel = which == bin_
            n = int(sel.sum())
            if n < 50:
                continue
            values = d[sel]
            mad = float(np.median(np.abs(values - np.median(values))))
            variance = (1.4826 * mad) ** 2
            rows.append(variance)
            design.append((float(np.mean(c[sel])), float(np.mean(u[sel]))))
            weights.append(n / max(variance, 1e-12) ** 2)
    if len(rows) < 3:
        return NoiseModel(1.0, 1.0, "default (brackets too small to measure noise)")
    a_mat = np.asarray(design) * np.sqrt(np.asarray(weights))[:, None]
    rhs = np.asarray(rows) * np.sqrt(np.asarray(weights))
    (read_var, inv_gain), *_ = np.linalg.lstsq(a_mat, rhs, rcond=None)
    read_noise = float(np.sqrt(max(read_var, 0.09)))
    # The shot-noise slope must stand out of its own scatter (three standard errors). Where it does not (a dim
    # scene, or brackets that are one frame scaled) 1/slope may be absurd (4763 e/count from read noise alone):
    # the gain is then what the data allow at least, 1 / (slope + 3 standard errors).
    residual = rhs - a_mat @ np.array([read_var, inv_gain])
    dof = max(len(rhs) - 2, 1)
    error = float(np.sqrt(max((np.linalg.pinv(a_mat.T @ a_mat) * float(residual @ residual) / dof)[1, 1], 0.0)))
    if not inv_gain > 3 * error:
        bound = max(float(inv_gain), 0.0) + 3 * error
        gain = 1.0 / bound if bound > 0 else 1.0
        return NoiseModel(read_noise, gain, "exposure brackets (shot noise barely visible: the gain is a lower bound)")
    return NoiseModel(read_noise, float(1.0 / inv_gain), "exposure brackets")


def merge_exposures(
    stack,
    exposure_s,
    *,
    saturation_level,
    noise: NoiseModel | None = None,
    min_weight: float = 1e-3,
    saturation_margin: float = 0.01,
    smoothing_px: int = 2,
    warn_saturated: bool = True,
) -> HdrResult:
    """Merge linear exposures into a radiance map in counts per second.

    Parameters
    ----------
    stack : array_like
        ``(..., E, H, W)`` linear, black-level-subtracted sensor values in
        counts, negative values kept. Leading axes are batch axes (e.g.
        camera positions), each with its own bracket.
    exposure_s : array_like
        Exposure times in seconds, shape ``(E,)`` (shared by the batch) or
        ``(..., E)`` (one bracket per batch element). All must be > 0 and
        distinct within a bracket.
    saturation_level : float or array_like
        Value at which a pixel clips, in the counts of ``stack`` (white level
        minus black level); an array broadcasting to ``stack`` gives it per
        pixel and frame (per-pixel black levels, gain maps).
    noise : NoiseModel, optional
        Read noise and conversion gain; estimated from the brackets when None
        (:func:`estimate_noise`).
    min_weight : float, optional
        Smallest confidence given to a valid pixel, so that ``weight == 0``
        means exactly "no usable exposure". Must be in ``(0, 1]``.
    saturation_margin : float, optional
        Relative margin below ``saturation_level`` from which a value counts
        as saturated (covers the non-linear shoulder of real sensors).
    smoothing_px : int, optional
        Radius of the box filter applied to the first estimate before it sets
        the weights (0: none).
    warn_saturated : bool, optional
        Log a warning where over 1% of the pixels are saturated in every exposure (a caller merging many
        brackets says it once for all of them instead).

    Returns
    -------
    HdrResult

    Raises
    ------
    ValueError
        Wrong shapes, NaN/inf values, non-positive or duplicate exposure
        times, or inconsistent parameters.

    Notes
    -----
    See the module docstring for the estimator, the flux-ratio check and the
    dynamic-range figure.
    """
    stack = _check_stack(stack)
    n_exp = stack.shape[-3]
    batch_shape = stack.shape[:-3]
    if not 0 < min_weight <= 1:
        raise ValueError(f"min_weight {min_weight!r} must be in (0, 1]")
    if not 0 <= saturation_margin < 1:
        raise ValueError(f"saturation_margin {saturation_margin!r} must be in [0, 1)")
    t = _check_exposures(np.asarray(exposure_s, dtype=np.float64), batch_shape, n_exp)
    if noise is None:
        noise = estimate_noise(stack, t, saturation_level=saturation_level, saturation_margin=saturation_margin)
    stack, t, thr = _ascending(stack, t, _saturation(saturation_level, stack, saturation_margin))
    t32 = t.astype(np.float32)[..., None, None]  # (..., E, 1, 1)

    saturated = stack >= thr
    first, valid = _first_estimate(stack, t32, saturated)
    level = np.maximum(_smooth(first, int(smoothing_px)), np.float32(0))[..., None, :, :]  # (..., 1, H, W)
    expected = level * t32                                               # (..., E, H, W) counts
    variance = noise.variance(expected)
    # Near-clipping test at the lower of the smoothed and the pixel's own estimate: a dim pixel beside a
    # bright one keeps its long exposures.
    nearest = np.minimum(level, np.maximum(first, 0)[..., None, :, :]) * t32
    near_clip = nearest + np.float32(SATURATION_SIGMAS) * np.sqrt(noise.variance(nearest)) >= thr
    usable = ~saturated & ~near_clip
    # Where the prediction rules out every unsaturated exposure, keep the shortest unsaturated one.
    open_ = ~saturated
    shortest_open = open_ & (np.cumsum(open_, axis=-3) == 1)
    usable |= shortest_open & ~usable.any(axis=-3, keepdims=True)

    w = np.where(usable, t32 * t32 / variance, np.float32(0))            # 1 / var(x_e / t_e)
    w_sum = w.sum(axis=-3)
    with np.errstate(divide="ignore", invalid="ignore"):
        estimate = (w * stack / t32).sum(axis=-3) / np.where(valid, w_sum, 1)
        merged_var = np.where(valid, 1.0 / np.where(valid, w_sum, 1), np.inf).astype(np.float32)
    # Saturated in every exposure: the shortest exposure's clipping level is a lower bound.
    bound = thr[..., 0, :, :] / t32[..., 0, :, :]
    radiance = np.where(valid, estimate, bound).astype(np.float32)

    weight = _engine_weight(level[..., 0, :, :], merged_var, valid, noise, t, min_weight)
    flux_ratio, flux_sigma = _flux_ratios(stack, t32, usable, radiance, variance)
    dr, gain = _dynamic_range(radiance, usable, valid, stack, t32, saturated, noise)

    all_saturated = ~valid
    n_pix = valid.size
    snr = np.where(valid, np.abs(level[..., 0, :, :]) / np.sqrt(merged_var), 0)
    saturated_fraction = float(all_saturated.sum()) / n_pix
    underexposed_fraction = float((valid & (snr < 1)).sum()) / n_pix
    exposure_ratio = float(np.max(t.max(axis=-1) / t.min(axis=-1)))
    if warn_saturated and saturated_fraction > 0.01:
        _log.warning("%.1f%% of pixels are saturated in every exposure; add a shorter exposure",
                     100 * saturated_fraction)
    return HdrResult(radiance=radiance, variance=merged_var, weight=weight, valid=valid, flux_ratio=flux_ratio,
                     flux_ratio_sigma=flux_sigma, dynamic_range=dr, dynamic_range_gain=gain,
                     saturated_fraction=saturated_fraction, underexposed_fraction=underexposed_fraction,
                     exposure_ratio=exposure_ratio, noise=noise)


def _engine_weight(level, merged_var, valid, noise: NoiseModel, t, min_weight: float) -> np.ndarray:
    """Amplitude-domain precision relative to a shot-noise limited pixel of the longest exposure.

    ``var(√L̂) ≈ var(L̂) / (4 L + 2 σ)``, which stays finite at ``L = 0``
    (where ``√|noise|`` has variance of order σ); a shot-limited pixel of
    exposure ``t`` has ``var(√L̂) = 1 / (4 g t)``.
    """
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(merged_var)
        amplitude_var = merged_var / (4.0 * level + 2.0 * sigma)
    reference = 1.0 / (4.0 * noise.electrons_per_count * t.max(axis=-1))
    reference = np.asarray(reference, np.float32).reshape(t.shape[:-1] + (1, 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        conf = np.clip(reference / amplitude_var, min_weight, 1.0)
    return np.where(valid, conf, np.float32(0)).astype(np.float32)


def _flux_ratios(stack, t32, usable, radiance, variance):
    """Each exposure's flux over the merged flux on the pixels usable in every exposure."""
    common = usable.all(axis=-3)                                          # (..., H, W)
    merged = np.where(common, radiance, 0).sum(axis=(-2, -1), dtype=np.float64)[..., None]     # (..., 1)
    flux = (np.where(common[..., None, :, :], stack, 0).sum(axis=(-2, -1), dtype=np.float64)
            / t32[..., 0, 0].astype(np.float64))                          # (..., E)
    spread = np.sqrt(np.where(common[..., None, :, :], variance, 0).sum(axis=(-2, -1), dtype=np.float64))
    spread = spread / t32[..., 0, 0].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(merged != 0, flux / merged, np.nan)
        sigma = np.where(merged != 0, spread / np.abs(merged), np.nan)
    return ratio, sigma


def _range(values: np.ndarray) -> float:
    values = values[values > 0]
    if values.size < 20:
        return 1.0
    lo, hi = np.percentile(values, [0.1, 99.9])
    return float(max(hi / lo, 1.0)) if lo > 0 else 1.0


def _dynamic_range(radiance, usable, valid, stack, t32, saturated, noise: NoiseModel):
    """Radiance range measured with SNR ≥ 10 by the merge, and its gain over the best single exposure.

    The SNR of a pixel is evaluated at its own estimate (not the smoothed
    one that sets the merge weights): this figure describes what was
    measured, pixel by pixel.
    """
    batch = radiance.shape[:-2]
    dr = np.ones(batch)
    gain = np.ones(batch)
    for index in np.ndindex(batch):
        own = np.maximum(radiance[index], 0)
        counts = own[None] * t32[index]
        precision = np.where(usable[index], t32[index] ** 2 / noise.variance(counts), 0).sum(axis=0)
        snr = np.where(valid[index], own * np.sqrt(precision), 0)
        merged_range = _range(radiance[index][snr >= DYNAMIC_RANGE_SNR])
        best = 1.0
        for e in range(stack.shape[-3]):
            x = stack[index][e]
            snr_e = x / np.sqrt(noise.variance(x))
            keep = ~saturated[index][e] & (snr_e >= DYNAMIC_RANGE_SNR)
            best = max(best, _range(x[keep] / float(t32[index][e, 0, 0])))
        dr[index] = merged_range
        gain[index] = max(merged_range / best, 1.0)
    return dr, gain
