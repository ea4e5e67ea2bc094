"""Overlap, step and synthetic aperture ratio (SAR) of a square camera grid.

The paper defines overlap as the fraction of the aperture diameter shared by
two neighbouring apertures, so the step between camera centres is
``(1 - overlap) * d`` and an ``n x n`` grid spans a synthetic aperture of
``(n - 1) * step + d``.
"""

from __future__ import annotations

import math

__all__ = ["step_m", "synthetic_aperture_ratio", "grid_for_sar", "overlap_for"]


def _check_overlap(overlap: float) -> None:
    if not 0.0 <= overlap < 1.0:
        raise ValueError(f"overlap must be in [0, 1), got {overlap}")


def step_m(aperture_diameter_m: float, overlap: float) -> float:
    """Distance between neighbouring aperture centres (m): ``(1 - overlap) * d``."""
    _check_overlap(overlap)
    return (1.0 - overlap) * aperture_diameter_m


def synthetic_aperture_ratio(grid: int, overlap: float) -> float:
    """SAR of an ``grid x grid`` array: ``((grid - 1) * step + d) / d``.

    Parameters
    ----------
    grid : int
        Number of aperture positions along one side (≥ 1).
    overlap : float
        Linear overlap of neighbouring apertures, in [0, 1).

    Returns
    -------
    float
        Synthetic aperture diameter over the single aperture diameter.

    Examples
    --------
    >>> round(synthetic_aperture_ratio(21, 0.61), 2)
    8.8
    >>> round(synthetic_aperture_ratio(23, 0.72), 2)
    7.16
    """
    if grid < 1:
        raise ValueError(f"grid must be >= 1, got {grid}")
    _check_overlap(overlap)
    return (grid - 1) * (1.0 - overlap) + 1.0


def grid_for_sar(target_sar: float, overlap: float, *, odd: bool = True) -> int:
    """Smallest grid whose SAR reaches ``target_sar`` (odd by default, so a centre image exists)."""
    _check_overlap(overlap)
    if target_sar < 1.0:
        raise ValueError(f"target SAR must be >= 1, got {target_sar}")
    n = max(1, math.ceil((target_sar - 1.0) / (1.0 - overlap) - 1e-9) + 1)
    if odd and n % 2 == 0:
        n += 1
    return n


def overlap_for(grid: int, sar: float) -> float:
    """Overlap that makes an ``grid x grid`` array reach a given SAR."""
    if grid < 2:
        raise ValueError("a SAR other than 1 needs a grid of at least 2")
    overlap = 1.0 - (sar - 1.0) / (grid - 1)
    _check_overlap(overlap)
    return overlap
