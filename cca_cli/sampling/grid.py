"""Camera-centre lattices and the sampling grids the numeric core runs on.

Conventions: every (K, 2) position array is ordered ``[y, x]`` (row, column);
spectrum arrays are *centred* (the zero frequency at index ``size // 2``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["ScanGrid", "square_scan", "BandLayout", "BandSizes", "band_sizes", "band_layout", "smallest_fft_size"]


def smallest_fft_size(n: int) -> int:
    """Smallest even integer ≥ ``n`` whose only prime factors are 2, 3, 5 and 7.

    Even sizes keep the zero frequency of a centred spectrum at ``size // 2``
    with a real ±1 modulation in the other domain, which the forward model
    relies on; 7-smooth sizes are fast for FFTW and pocketfft alike. Sizes
    beyond 2**62 (far beyond any memory) are only rounded up to even.
    """
    n = max(2, int(n))
    n += n % 2
    if n > 1 << 62:
        return n
    best = None
    p7 = 1
    while p7 < 2 * n:
        p5 = p7
        while p5 < 2 * n:
            p3 = p5
            while p3 < 2 * n:
                two = 2
                while p3 * two < n:
                    two *= 2
                if best is None or p3 * two < best:
                    best = p3 * two
                p3 *= 3
            p5 *= 5
        p7 *= 7
    return best


@dataclass(frozen=True)
class ScanGrid:
    """Aperture positions of a camera array or a scanned camera.

    Attributes
    ----------
    centres_yx_m : ndarray, float64, (K, 2)
        Aperture centres ``[y, x]`` in the aperture plane (m), relative to the optical axis.
    indices : ndarray, int, (K, 2)
        Grid indices ``[row, column]`` of each position.
    shape : tuple of int
        Grid shape ``(rows, columns)``.
    """

    centres_yx_m: np.ndarray
    indices: np.ndarray
    shape: tuple[int, int]

    @property
    def n_images(self) -> int:
        """Number of aperture positions K."""
        return int(self.centres_yx_m.shape[0])

    @property
    def centre_index(self) -> int:
        """Index of the position nearest the optical axis (the 'observed' image)."""
        return int(np.argmin(np.hypot(self.centres_yx_m[:, 0], self.centres_yx_m[:, 1])))


def square_scan(grid: int, step_m: float) -> ScanGrid:
    """An ``grid x grid`` lattice of aperture centres with spacing ``step_m``, centred on the axis.

    Positions are in row-major order (row index first).
    """
    if grid < 1:
        raise ValueError(f"grid must be >= 1, got {grid}")
    offsets = (np.arange(grid) - (grid - 1) / 2.0) * step_m
    rows, cols = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    indices = np.stack([rows.ravel(), cols.ravel()], axis=1)
    centres = np.stack([offsets[indices[:, 0]], offsets[indices[:, 1]]], axis=1)
    return ScanGrid(centres_yx_m=centres, indices=indices, shape=(grid, grid))


@dataclass(frozen=True)
class BandLayout:
    """Where each capture's pupil sits in the high-resolution spectrum.

    Attributes
    ----------
    hires_size : int
        M, side of the high-resolution spectrum / object grid.
    lowres_size : int
        m, side of the per-capture FFT grid (holds the intensity band, ≥ 4 R).
    pupil_radius_px : float
        R, pupil radius in spectrum pixels.
    centres_px : ndarray, float64, (K, 2)
        Pupil centres ``[y, x]`` relative to the zero frequency (spectrum pixels).
    box_size : int
        b, side of the square box that holds one pupil (even, ≤ m).
    box_origins : ndarray, int64, (K, 2)
        Top-left corner of each pupil box in the centred M x M spectrum.
    box_centres : ndarray, float64, (K, 2)
        Pupil centre inside its box (box pixel coordinates, fractional).
    """

    hires_size: int
    lowres_size: int
    pupil_radius_px: float
    centres_px: np.ndarray
    box_size: int
    box_origins: np.ndarray
    box_centres: np.ndarray

    @property
    def n_images(self) -> int:
        """Number of captures K."""
        return int(self.centres_px.shape[0])

    @property
    def lowres_box_start(self) -> int:
        """Index in the m x m grid where each pupil box starts (the box is centred on m // 2)."""
        return self.lowres_size // 2 - self.box_size // 2

    @property
    def band_radius_px(self) -> float:
        """Largest distance from DC reached by any pupil (spectrum pixels, per axis)."""
        return float(np.max(np.abs(self.centres_px)) + self.pupil_radius_px)


@dataclass(frozen=True)
class BandSizes:
    """The grid sizes of a band layout, without the per-capture positions.

    Attributes
    ----------
    hires_size, lowres_size, box_size : int
        M, m and b of :class:`BandLayout`.
    """

    hires_size: int
    lowres_size: int
    box_size: int


def band_sizes(reach_px: float, pupil_radius_px: float, *, sensor_size: int | None = None,
               hires_size: int | None = None, lowres_size: int | None = None) -> BandSizes:
    """The grids :func:`band_layout` chooses, from the largest pupil offset alone (no arrays).

    Parameters
    ----------
    reach_px : float
        Largest ``|y|`` or ``|x|`` of any pupil centre (spectrum pixels; rounded to the nearest pixel).
    pupil_radius_px : float
        Pupil radius R in spectrum pixels.
    sensor_size, hires_size, lowres_size : int, optional
        As in :func:`band_layout`.

    Raises
    ------
    ValueError
        A non-positive radius, an odd or too small per-capture grid, or a forced M too small for the band.
    """
    radius = float(pupil_radius_px)
    if not radius > 0 or not math.isfinite(radius):
        raise ValueError(f"pupil radius must be a positive number, got {radius}")
    box = 2 * math.ceil(radius) + 4

    # The anti-aliased pupil edge reaches R + 1/2 (optics.pupil.circular_pupils), its intensity band 2R + 1.
    needed_lowres = smallest_fft_size(2 * math.floor(2 * radius + 1) + 1)
    if lowres_size is None:
        lowres_size = needed_lowres
        if sensor_size is not None and sensor_size < lowres_size:
            lowres_size = int(sensor_size)
    if lowres_size % 2:
        raise ValueError(f"the per-capture grid must be even, got {lowres_size}")
    if lowres_size < box:
        raise ValueError(
            f"a {lowres_size}-pixel capture grid cannot hold a pupil of radius {radius:.1f} px "
            f"(needs ≥ {box}); the sensor samples the field too coarsely for this aperture"
        )
    reach = int(np.rint(reach_px)) + box // 2 + 1
    needed_hires = smallest_fft_size(2 * reach)
    if hires_size is None:
        hires_size = max(needed_hires, smallest_fft_size(sensor_size or 0), lowres_size)
    elif hires_size < needed_hires:
        raise ValueError(
            f"high-resolution grid {hires_size} is too small for the synthetic band (needs ≥ {needed_hires})"
        )
    return BandSizes(hires_size=int(hires_size), lowres_size=int(lowres_size), box_size=box)


def band_layout(
    centres_px,
    pupil_radius_px: float,
    *,
    sensor_size: int | None = None,
    hires_size: int | None = None,
    lowres_size: int | None = None,
) -> BandLayout:
    """Choose the smallest grids that hold the band and place every pupil box.

    Parameters
    ----------
    centres_px : array_like, (K, 2)
        Pupil centres ``[y, x]`` in spectrum pixels relative to DC.
    pupil_radius_px : float
        Pupil radius R in spectrum pixels.
    sensor_size : int, optional
        Pixels across a sensor image. The per-capture grid never exceeds it
        (a coarser sensor aliases, and the model then samples as the sensor
        does) and the high-resolution grid is at least this large.
    hires_size, lowres_size : int, optional
        Force M or m; a value too small for the band raises ``ValueError``.

    Returns
    -------
    BandLayout

    Notes
    -----
    The intensity of a field whose spectrum is a disc of radius R has its
    spectrum in a disc of radius 2R; with the pupil's anti-aliased edge
    (reaching R + 1/2) an m x m grid with ``m > 4 R + 2`` holds it without
    aliasing; the smallest even 7-smooth size is used.
    """
    centres = np.asarray(centres_px, dtype=np.float64).reshape(-1, 2)
    rounded = np.rint(centres).astype(np.int64)
    sizes = band_sizes(float(np.max(np.abs(rounded))), pupil_radius_px, sensor_size=sensor_size,
                       hires_size=hires_size, lowres_size=lowres_size)
    radius, box, hires_size, lowres_size = float(pupil_radius_px), sizes.box_size, sizes.hires_size, sizes.lowres_size
    origins = rounded + hires_size // 2 - box // 2
    box_centres = centres - origins + hires_size // 2
    return BandLayout(
        hires_size=int(hires_size),
        lowres_size=int(lowres_size),
        pupil_radius_px=radius,
        centres_px=centres,
        box_size=box,
        box_origins=origins,
        box_centres=box_centres,
    )
