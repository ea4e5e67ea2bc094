"""The lattice of pupil centres, and the pupil patterns it leaves undetermined.

When the captures' pupil centres ``c_i`` lie on a lattice (an LED grid, a camera
array), a pupil pattern ``g`` periodic on that lattice, and its inverse in the
spectrum, predict every capture alike: capture ``i`` sees ``S(u + c_i) P(u)``,
and ``S(k) g(k) · P(u) / g(u + c_i)`` is the same product when ``g(u + c_i) =
g(u)`` for every ``i``. The data do not tell such a pattern from the object
(ptychography's raster-grid ambiguity), so a pupil map recovered freely lets one
grow slowly: a checkerboard with the lattice's period in the map, and its
opposite in the object as a grid-like texture. :func:`periodic_filter` makes the
filter that removes the lattice's harmonics from a map.
"""

from __future__ import annotations

import numpy as np

__all__ = ["capture_lattice", "periodic_filter"]


def capture_lattice(centres_px: np.ndarray, tolerance: float = 0.1) -> np.ndarray | None:
    """The two primitive vectors of the lattice the pupil centres lie on, or None if they lie on none.

    Parameters
    ----------
    centres_px : ndarray, (K, 2)
        Pupil centres ``[y, x]`` (spectrum pixels).
    tolerance : float
        Largest root-mean-square distance of the inner quarter of the centres (at least eight) from
        their lattice points, as a fraction of the shorter lattice vector. Tilted LED boards, and the
        sine of the illumination angle, bend a grid a little: the recorded grids of the benchmark
        corpus miss by 0.00–0.04, a 15 × 15 grid reaching 39° by 0.04. LEDs on concentric rings miss
        by 0.2 (the corpus's ring board) to 0.4, centres at random by about 0.4.

    Returns
    -------
    ndarray, float64, (2, 2) or None
        Rows: the shortest vector between neighbouring centres, and the shortest one not parallel to it.
    """
    centres = np.asarray(centres_px, np.float64).reshape(-1, 2)
    if centres.shape[0] < 4:
        return None
    origin = centres[np.argmin(np.hypot(centres[:, 0], centres[:, 1]))]
    offsets = centres - origin
    lengths = np.hypot(offsets[:, 0], offsets[:, 1])
    order = np.argsort(lengths, kind="stable")
    order = order[lengths[order] > 1e-9]
    if order.size < 2:
        return None
    first = offsets[order[0]]
    second = None
    for i in order[1:]:
        cross = first[0] * offsets[i, 1] - first[1] * offsets[i, 0]
        if abs(cross) > 0.5 * lengths[order[0]] * lengths[i]:   # more than 30° from the first
            second = offsets[i]
            break
    if second is None:
        return None
    vectors = np.stack([first, second])
    # Fitted to the inner quarter of the centres: at large angles the sine of the illumination angle bends
    # an LED grid's outer rows (half the centres of a wide grid miss their points as far as rings do).
    inner = order[:max(8, order.size // 4)]
    indices = np.round(offsets[inner] @ np.linalg.inv(vectors))          # each centre's lattice point
    vectors, *_ = np.linalg.lstsq(indices, offsets[inner], rcond=None)   # refitted to them
    if abs(np.linalg.det(vectors)) < 1e-9:
        return None
    misfit = np.sqrt(np.mean(np.sum((indices @ vectors - offsets[inner]) ** 2, axis=1)))
    shortest = min(np.hypot(*vectors[0]), np.hypot(*vectors[1]))
    return vectors if misfit <= tolerance * shortest else None


def periodic_filter(box_size: int, vectors: np.ndarray, width: float = 0.75) -> np.ndarray | None:
    """A factor on the ``fft2`` of a (box_size, box_size) map that removes patterns periodic on a lattice.

    Each harmonic of the lattice (every frequency ``h`` with ``h · v`` a whole number for both lattice
    vectors ``v``, but zero) up to the box's Nyquist frequency is notched out by a Gaussian of
    ``width`` frequency bins; everything far from the harmonics passes unchanged. None where the
    harmonics lie so close to zero frequency that the notches would take more than 1% of it (pupils
    that barely overlap): the map's smooth aberration would be damped with the pattern.

    Parameters
    ----------
    box_size : int
    vectors : ndarray, (2, 2)
        The lattice's vectors (rows, pixels), as :func:`capture_lattice` gives them.
    width : float
        Standard deviation of each notch, in bins of the box's transform.

    Returns
    -------
    ndarray, float64, (box_size, box_size), or None
        In ``numpy.fft.fftfreq`` order; 1 (to rounding) far from the harmonics, at least 0.99 at zero
        frequency.
    """
    reciprocal = np.linalg.inv(np.asarray(vectors, np.float64)).T * box_size   # harmonic steps, in bins
    limit = box_size / 2.0
    steps = np.hypot(reciprocal[:, 0], reciprocal[:, 1])
    reach = int(np.ceil(np.sqrt(2) * limit / max(min(steps), 1e-9))) + 1
    bins = np.fft.fftfreq(box_size, 1.0 / box_size)
    # Every harmonic n1·r1 + n2·r2 (but zero) within the box's band, n1 then n2 ascending.
    orders = np.arange(-reach, reach + 1)
    n1, n2 = (a.ravel() for a in np.meshgrid(orders, orders, indexing="ij"))
    hy = n1 * reciprocal[0, 0] + n2 * reciprocal[1, 0]
    hx = n1 * reciprocal[0, 1] + n2 * reciprocal[1, 1]
    keep = ((n1 != 0) | (n2 != 0)) & (np.abs(hy) <= limit + 3 * width) & (np.abs(hx) <= limit + 3 * width)
    hy, hx = hy[keep], hx[keep]
    # Each notch is worked out on the bins within 6 widths of its harmonic (beyond, it is 1 to 1e-7).
    half = int(np.ceil(6 * width))
    if 2 * half + 1 < box_size:
        near = np.arange(-half, half + 1)
        rows = (np.round(hy).astype(np.int64)[:, None] + near) % box_size
        cols = (np.round(hx).astype(np.int64)[:, None] + near) % box_size
    else:
        rows = cols = np.broadcast_to(np.arange(box_size), (hy.size, box_size))
    # distance to each harmonic on the periodic frequency grid
    dy = (bins[rows] - hy[:, None] + limit) % box_size - limit
    dx = (bins[cols] - hx[:, None] + limit) % box_size - limit
    notches = 1.0 - np.exp(-(dy[:, :, None] ** 2 + dx[:, None, :] ** 2) / (2.0 * width * width))
    # Overlapping notches multiply; ``multiply.at`` applies them one after another in the order above,
    # so the product rounds the same on every run.
    factor = np.ones((box_size, box_size))
    where = rows[:, :, None] * box_size + cols[:, None, :]
    np.multiply.at(factor.reshape(-1), where.ravel(), notches.ravel())
    return factor if factor[0, 0] >= 0.99 else None
