"""Pupil discs: on the pupil boxes of a :class:`~cca_cli.sampling.BandLayout`, or centred on a spectrum grid.

The aberration phase on them is :mod:`cca_cli.optics.zernike`'s.
"""

from __future__ import annotations

import numpy as np

__all__ = ["circular_pupils", "centred_disc"]


#: Bytes of float64 work :func:`circular_pupils` holds at a time.
_WORK_BYTES = 1 << 20


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
    pupils = np.empty((len(centres), box_size, box_size), np.float32)
    # A few captures at a time: the float64 work array stays in cache (a box set can be tens of MB).
    step = max(1, _WORK_BYTES // (8 * box_size * box_size))
    for start in range(0, len(centres), step):
        part = centres[start:start + step]
        dy = grid[None, :, None] - part[:, 0, None, None]
        dx = grid[None, None, :] - part[:, 1, None, None]
        distance = dy * dy + dx * dx   # worked on in place
        np.sqrt(distance, out=distance)
        if edge_px <= 0:
            np.less_equal(distance, radius_px, out=pupils[start:start + step], casting="unsafe")
            continue
        ramp = np.subtract(radius_px + 0.5 * edge_px, distance, out=distance)
        ramp /= edge_px
        np.maximum(ramp, 0.0, out=ramp)
        np.minimum(ramp, 1.0, out=ramp)
        pupils[start:start + step] = ramp
    return pupils


def centred_disc(size: int, radius_px: float) -> np.ndarray:
    """Binary disc ``r ≤ radius_px`` centred on pixel ``size // 2`` of a ``size`` x ``size`` spectrum grid (float32)."""
    return circular_pupils(size, [[size // 2, size // 2]], radius_px, edge_px=0)[0]
