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


def _harmonics_in_band(reciprocal: np.ndarray, reach: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
    """Every harmonic ``n1·r1 + n2·r2`` (but zero) with both coordinates within ``bound`` bins, ``|n| ≤ reach``,
    ordered by n1 then n2; built a row of n1 at a time (a coarse lattice has a great many candidates)."""
    orders = np.arange(-reach, reach + 1)
    found_y, found_x = [], []
    for n1 in orders:
        hy = n1 * reciprocal[0, 0] + orders * reciprocal[1, 0]
        hx = n1 * reciprocal[0, 1] + orders * reciprocal[1, 1]
        keep = ((n1 != 0) | (orders != 0)) & (np.abs(hy) <= bound) & (np.abs(hx) <= bound)
        found_y.append(hy[keep])
        found_x.append(hx[keep])
    return np.concatenate(found_y), np.concatenate(found_x)


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
    hy, hx = _harmonics_in_band(reciprocal, reach, limit + 3 * width)
    # Each notch is worked out on the bins within 6 widths of its harmonic (beyond, it is 1 to 1e-7).
    half = int(np.ceil(6 * width))
    near = np.arange(-half, half + 1) if 2 * half + 1 < box_size else None

    def notches(hy: np.ndarray, hx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat indices into the factor and the notch values there, harmonic by harmonic."""
        if near is None:
            rows = cols = np.broadcast_to(np.arange(box_size), (hy.size, box_size))
        else:
            rows = (np.round(hy).astype(np.int64)[:, None] + near) % box_size
            cols = (np.round(hx).astype(np.int64)[:, None] + near) % box_size
        dy = (bins[rows] - hy[:, None] + limit) % box_size - limit   # distance on the periodic frequency grid
        dx = (bins[cols] - hx[:, None] + limit) % box_size - limit
        values = 1.0 - np.exp(-(dy[:, :, None] ** 2 + dx[:, None, :] ** 2) / (2.0 * width * width))
        return (rows[:, :, None] * box_size + cols[:, None, :]).ravel(), values.ravel()

    # Overlapping notches multiply; ``multiply.at`` applies them one after another in the order of the
    # harmonics, so the product rounds the same on every run. Zero frequency first: harmonics that crowd it
    # (pupils that barely overlap, whose lattice may have a great many harmonics) end it there.
    if near is None:
        at_zero = np.ones(hy.size, bool)
    else:
        at_zero = (np.abs(np.round(hy)) <= half) & (np.abs(np.round(hx)) <= half)
    where, values = notches(hy[at_zero], hx[at_zero])
    zero = np.ones(1)
    np.multiply.at(zero, np.zeros(np.count_nonzero(where == 0), np.int64), values[where == 0])
    if not zero[0] >= 0.99:
        return None
    factor = np.ones((box_size, box_size))
    chunk = max(1, 2 ** 20 // (box_size if near is None else near.size) ** 2)   # bounded work arrays
    for start in range(0, hy.size, chunk):
        where, values = notches(hy[start:start + chunk], hx[start:start + chunk])
        np.multiply.at(factor.reshape(-1), where, values)
    return factor if factor[0, 0] >= 0.99 else None
