"""Sensor calibration from dark and flat frames: per-pixel black level, gain map, noise.

Dark frames (shutter closed) give the black level of every pixel at their
exposure time; several dark frames at one exposure also give the read
noise (their frame-to-frame scatter). Flat frames (a uniform light source)
give the relative gain of every pixel (photo-response non-uniformity);
two or more flats at one exposure also give the conversion gain in
electrons per count (photon transfer: the variance of their difference is
``2 (σ_r² + μ / g)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["DarkModel", "dark_model", "gain_map", "read_noise_from_darks", "electrons_per_count_from_flats"]


@dataclass(frozen=True)
class DarkModel:
    """Per-pixel black level as a function of exposure time.

    Attributes
    ----------
    exposure_s : ndarray, float64, (D,)
        Exposure times of the dark frames, ascending and distinct.
    black : ndarray, float32, (D, H, W)
        Mean dark frame at each exposure (counts).
    """

    exposure_s: np.ndarray
    black: np.ndarray

    def at(self, exposure_s: float) -> tuple[np.ndarray, str | None]:
        """Black level at ``exposure_s`` and a note when it is not measured there.

        An exposure with dark frames uses their mean; otherwise, with dark
        frames at two or more exposures, each pixel's black level is the
        least-squares line ``a + b t`` through them (dark current grows
        linearly with time); with one exposure its mean is used as is.
        """
        t = np.asarray(self.exposure_s)
        match = np.nonzero(np.isclose(t, exposure_s, rtol=1e-6, atol=0.0))[0]
        if match.size:
            return self.black[int(match[0])], None
        if t.size == 1:
            level = self.black[0]
        else:
            design = np.stack([np.ones_like(t), t], axis=1)
            coeffs, *_ = np.linalg.lstsq(design, self.black.reshape(t.size, -1).astype(np.float64), rcond=None)
            level = (coeffs[0] + coeffs[1] * exposure_s).reshape(self.black.shape[1:]).astype(np.float32)
        return level, self.unmeasured_note([exposure_s])

    def unmeasured_note(self, exposures_s) -> str:
        """One note for exposures (ascending) without dark frames of their own: how their black level is found."""
        t = np.asarray(self.exposure_s)
        times = [float(v) for v in exposures_s]
        if len(times) <= 3:
            where = f"no dark frames at {', '.join(f'{v * 1e3:g}' for v in times)} ms"
        else:
            where = f"no dark frames at {len(times)} of the exposures ({times[0] * 1e3:g} … {times[-1] * 1e3:g} ms)"
        their = "its" if len(times) == 1 else "their"
        if t.size == 1:
            return f"{where}; the {t[0] * 1e3:g} ms dark frames are used as {their} black level"
        return (f"{where}; {their} black level is the per-pixel line through the dark frames at "
                f"{', '.join(f'{v * 1e3:g}' for v in t)} ms")


def dark_model(frames: list[np.ndarray], exposure_s: list[float]) -> DarkModel:
    """Average dark frames per exposure time.

    Parameters
    ----------
    frames : list of ndarray, (H, W)
        Dark frames (counts, black level *not* subtracted).
    exposure_s : list of float
        Exposure of each frame.
    """
    times = np.asarray(exposure_s, np.float64)
    unique = np.unique(times)
    black = np.stack([np.mean([f for f, t in zip(frames, times) if t == u], axis=0, dtype=np.float64)
                      for u in unique]).astype(np.float32)
    return DarkModel(exposure_s=unique, black=black)


def read_noise_from_darks(frames: list[np.ndarray], exposure_s: list[float]) -> float | None:
    """Read noise (counts RMS): the pooled frame-to-frame scatter of dark frames at equal exposures.

    None when no exposure has two or more dark frames.
    """
    times = np.asarray(exposure_s, np.float64)
    total, dof = 0.0, 0
    for u in np.unique(times):
        group = np.stack([f for f, t in zip(frames, times) if t == u]).astype(np.float64)
        if group.shape[0] < 2:
            continue
        total += float(np.var(group, axis=0, ddof=1).sum()) * (group.shape[0] - 1)
        dof += (group.shape[0] - 1) * group[0].size
    return float(np.sqrt(total / dof)) if dof else None


def gain_map(flats: list[np.ndarray], black: list[np.ndarray]) -> np.ndarray:
    """Relative pixel gain (mean 1) from flat frames and their black levels.

    Raises
    ------
    ValueError
        A pixel of the mean flat is at or below its black level (flats too dark).
    """
    signal = np.mean([f.astype(np.float64) - b for f, b in zip(flats, black)], axis=0)
    mean = float(signal.mean())
    if not mean > 0 or (signal <= 0).any():
        raise ValueError(f"{int((signal <= 0).sum())} pixel(s) of the flat frames are at or below the black level; "
                         "expose the flats brighter")
    return (signal / mean).astype(np.float32)


def electrons_per_count_from_flats(flats: list[np.ndarray], black: list[np.ndarray], exposure_s: list[float],
                                   read_noise: float) -> float | None:
    """Conversion gain (electrons per count) from pairs of flats at the same exposure (photon transfer).

    The difference of two flats removes the fixed pattern; its variance is
    ``2 (σ_r² + μ / g)`` for a mean signal μ. None without a pair, or when the
    scatter is not above the read noise.
    """
    times = np.asarray(exposure_s, np.float64)
    estimates = []
    for u in np.unique(times):
        idx = np.nonzero(times == u)[0]
        for a, b in zip(idx[0::2], idx[1::2]):
            fa = flats[a].astype(np.float64) - black[a]
            fb = flats[b].astype(np.float64) - black[b]
            shot = float(np.var(fa - fb)) / 2.0 - read_noise**2
            mean = float(0.5 * (fa.mean() + fb.mean()))
            if shot > 0 and mean > 0:
                estimates.append(mean / shot)
    return float(np.median(estimates)) if estimates else None
