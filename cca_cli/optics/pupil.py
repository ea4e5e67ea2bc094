"""Pupil functions evaluated on the pupil boxes of a :class:`~cca_cli.sampling.BandLayout`."""

from __future__ import annotations

import numpy as np

__all__ = ["circular_pupils", "zernike_phase"]


def circular_pupils(box_size: int, box_centres, radius_px: float, *, edge_px: float = 1.0) -> np.ndarray:
    """Circular pupils, one per capture, sampled on their boxes with an anti-aliased edge.

    A pixel's value falls linearly from 1 to 0 as its centre's distance ``r``
    from the pupil centre goes from ``R − edge/2`` to ``R + edge/2``: about the
    share of the pixel the disc covers. A sampled disc then moves smoothly with
    a sub-pixel change of its centre (a binary one only jumps when an edge pixel
    flips), which sub-pixel positions and their calibration need, and it
    matches recorded images better.

    Parameters
    ----------
    box_size : int
        Side of each pupil box (pixels).
    box_centres : array_like, (K, 2)
        Pupil centre ``[y, x]`` inside each box (fractional pixels).
    radius_px : float
        Pupil radius (spectrum pixels).
    edge_px : float
        Width of the edge ramp (pixels); 0 gives a binary disc ``r ≤ R``.

    Returns
    -------
    ndarray, float32, (K, box_size, box_size)
        Values in [0, 1].
    """
    centres = np.asarray(box_centres, dtype=np.float64).reshape(-1, 2)
    grid = np.arange(box_size, dtype=np.float64)
    dy = grid[None, :, None] - centres[:, 0, None, None]
    dx = grid[None, None, :] - centres[:, 1, None, None]
    distance = np.sqrt(dy * dy + dx * dx)
    if edge_px <= 0:
        return (distance <= radius_px).astype(np.float32)
    return np.clip((radius_px + 0.5 * edge_px - distance) / edge_px, 0.0, 1.0).astype(np.float32)


def zernike_phase(box_size: int, box_centres, radius_px: float, *, defocus_waves: float = 0.0,
                  astigmatism_waves: float = 0.0, oblique_astigmatism_waves: float = 0.0) -> np.ndarray:
    """Low-order aberration phase (radians) over each pupil box.

    Uses the Zernike polynomials ``Z(2,0) = √3 (2ρ² − 1)``, ``Z(2,2) = √6 ρ² cos 2θ``
    and ``Z(2,−2) = √6 ρ² sin 2θ`` with coefficients in waves (RMS-normalised).

    Returns
    -------
    ndarray, float32, (K, box_size, box_size)
    """
    centres = np.asarray(box_centres, dtype=np.float64).reshape(-1, 2)
    grid = np.arange(box_size, dtype=np.float64)
    y = (grid[None, :, None] - centres[:, 0, None, None]) / radius_px
    x = (grid[None, None, :] - centres[:, 1, None, None]) / radius_px
    rho2 = x * x + y * y
    waves = (defocus_waves * np.sqrt(3.0) * (2.0 * rho2 - 1.0)
             + astigmatism_waves * np.sqrt(6.0) * (x * x - y * y)
             + oblique_astigmatism_waves * np.sqrt(6.0) * 2.0 * x * y)
    return (2.0 * np.pi * waves).astype(np.float32)
