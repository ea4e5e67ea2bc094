"""Where the optical axis lies among an LED array's illumination angles, read from the bright-field images.

A bright-field image holds the object's unscattered light, which interferes with the light the object
scatters into the pupil. The image's spectrum therefore carries two discs of the pupil's radius, centred on
plus and minus the illumination's spatial frequency, with a sharp edge (Eckert, Phillips & Waller, Appl.
Opt. 57(19), 2018). Where the LED positions given are all off by one shift (a board whose middle LED is not
on the axis, or a table counted from another origin), every disc sits that shift away from where the
positions put it. The recovery cannot see such a shift (it only tilts the object's phase, by tens of
radians over the field, which no run unwinds), and a recovery with it has stripes and a wrong phase.

:func:`axis_offset` finds the one shift that puts the discs' edges of every bright-field image where the
images have them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["AxisOffset", "axis_offset", "misplaced", "lit_level", "OFF_AXIS", "CLEAR_GAIN", "EDGE_WIDTH_PX"]

#: A shift at least this fraction of the pupil radius is reported. The recorded corpus's sets where the
#: discs can be read (benchmarks/corpus) read 0.07-0.08 radii; an LED board half a pitch off its axis, 0.29.
OFF_AXIS = 0.15
#: The edges at the shift found must be this many times as strong as at the positions given.
CLEAR_GAIN = 1.5
#: Width of the bands inside and outside a disc's edge whose mean log spectra are compared (spectrum px).
EDGE_WIDTH_PX = 2.0
#: Bright-field images used at most (those nearest the axis).
MAX_IMAGES = 32
#: Farthest the search looks, as a fraction of the pupil radius.
SEARCH_RADII = 0.75
#: Side of the centred square the spectra are read on (px): wider frames are cut to it (memory stays bounded).
MAX_SIDE = 256


@dataclass(frozen=True)
class AxisOffset:
    """How far the bright-field images put the LED positions from where they were given.

    Attributes
    ----------
    shift_yx_px : ndarray, float64, (2,)
        What to add to every capture's pupil centre [y, x] (spectrum px over the frame's width).
    radii : float
        Its length in pupil radii.
    gain : float
        How much stronger the discs' edges are at the shift than at the positions as given (1: alike).
    images : int
        Bright-field images read.
    misplaced_given, misplaced_shifted : int
        Captures whose light contradicts the bright or dark field the positions as given, and as shifted,
        put them in (:func:`misplaced`).
    """

    shift_yx_px: np.ndarray
    radii: float
    gain: float
    images: int
    misplaced_given: int = 0
    misplaced_shifted: int = 0

    @property
    def confirmed(self) -> bool:
        """Whether the shift puts fewer captures on the wrong side of the pupil's edge than the positions as
        given (:func:`misplaced`): the captures' brightness, not the circles alone, says the axis moved."""
        return self.misplaced_shifted < self.misplaced_given

    @property
    def off_axis(self) -> bool:
        """Whether the shift is large and clear enough to report (:data:`OFF_AXIS`, :data:`CLEAR_GAIN`) and the
        captures' light confirms it (:attr:`confirmed`)."""
        return self.radii >= OFF_AXIS and self.gain >= CLEAR_GAIN and self.confirmed


def misplaced(light: np.ndarray, centres_px: np.ndarray, radius_px: float, lit: float) -> int:
    """Captures whose light contradicts the field the centres put them in.

    A capture whose pupil holds the unscattered light (centre more than a pixel inside the pupil's edge)
    records at least ``lit``; one more than a pixel outside it records less. Captures on the edge itself
    count for neither.

    Parameters
    ----------
    light : ndarray, (K,)
        Each capture's mean intensity (per unit exposure).
    centres_px : ndarray, (K, 2)
    radius_px : float
    lit : float
        The least light of a bright-field capture (:func:`lit_level`).
    """
    light = np.asarray(light, np.float64)
    distance = np.hypot(*np.asarray(centres_px, np.float64).T)
    bright, dark = distance < radius_px - 1, distance > radius_px + 1
    return int(np.sum(bright & (light < lit)) + np.sum(dark & (light >= lit)))


def lit_level(light: np.ndarray, *arrangements: np.ndarray, radius_px: float) -> float:
    """Half the median light of the bright-field captures, under whichever ``arrangements`` of the centres gives
    the brighter median: every bright-field capture holds the unscattered light, and a dark-field one only what
    the object scatters (far less for all but the densest samples, even beside the pupil's edge)."""
    light = np.asarray(light, np.float64)
    inside = [np.hypot(*np.asarray(c, np.float64).T) < radius_px - 1 for c in arrangements]
    return 0.5 * max((np.median(light[bright]) for bright in inside if bright.any()), default=0.0)


def axis_offset(images: np.ndarray, centres_px: np.ndarray, radius_px: float,
                light: np.ndarray | None = None) -> AxisOffset | None:
    """The shift of every pupil centre that the bright-field images' spectra show.

    Parameters
    ----------
    images : ndarray, (K, H, W)
        One image per capture (any linear scale; an exposure each is fine).
    centres_px : ndarray, (K, 2)
        The captures' pupil centres [y, x] as given (spectrum px over the frame's width ``W``).
    radius_px : float
        Pupil radius (spectrum px over ``W``).
    light : ndarray, (K,), optional
        Each capture's mean intensity per unit exposure (default: the images' means), which confirms a shift
        (:attr:`AxisOffset.confirmed`).

    Returns
    -------
    AxisOffset or None
        None where the discs cannot be read: fewer than three bright-field captures, or a pupil so wide that
        their edges leave the images' band (a radius over a quarter of the frame).
    """
    images = np.asarray(images)
    if images.ndim != 3 or len(images) != len(centres_px):
        raise ValueError(f"images must be (K, H, W) with one per centre, got {images.shape} for {len(centres_px)}")
    h, w = images.shape[-2:]
    n = min(h, w, MAX_SIDE)
    to_crop = n / w                      # spectrum px over the square crop's width
    centres = np.asarray(centres_px, np.float64) * to_crop
    radius = float(radius_px) * to_crop
    distance = np.hypot(centres[:, 0], centres[:, 1])
    bright = np.flatnonzero(distance < 0.8 * radius)
    if bright.size < 3 or radius > n / 4:
        return None
    bright = bright[np.argsort(distance[bright], kind="stable")[:MAX_IMAGES]]
    top, left = (h - n) // 2, (w - n) // 2
    crop = np.asarray(images[bright, top:top + n, left:left + n], np.float64)
    edges = _edge_maps(crop, radius)
    reach = SEARCH_RADII * radius
    step = max(0.5, radius / 48)          # at most about 72² shifts on the coarse grid
    steps = np.arange(-reach, reach + 1e-9, step)
    grid = np.stack(np.meshgrid(steps, steps, indexing="ij"), -1).reshape(-1, 2)
    best = grid[int(np.argmax(_scores(edges, centres[bright], grid)))]
    fine = np.arange(-step, step + 1e-9, step / 5)
    trial = best + np.stack(np.meshgrid(fine, fine, indexing="ij"), -1).reshape(-1, 2)
    scores = _scores(edges, centres[bright], trial)
    shift = trial[int(np.argmax(scores))]
    at_given = float(_scores(edges, centres[bright], np.zeros((1, 2)))[0])
    found = float(scores.max())
    # edges that read nowhere (found ≤ 0) claim nothing; none where the positions put them, ten times
    gain = 1.0 if found <= 0 else found / max(at_given, 0.1 * found)
    light = images.mean(axis=(-2, -1), dtype=np.float64) if light is None else np.asarray(light, np.float64)
    given = np.asarray(centres_px, np.float64)
    shifted = given + shift / to_crop
    lit = lit_level(light, given, shifted, radius_px=radius_px)
    return AxisOffset(shift / to_crop, float(np.hypot(*shift) / radius), float(gain), int(bright.size),
                      misplaced(light, given, radius_px, lit), misplaced(light, shifted, radius_px, lit))


def _edge_maps(images: np.ndarray, radius: float) -> np.ndarray:
    """For each image, how sharply its log spectrum falls across a disc edge of ``radius`` centred at each
    spectrum pixel (the mean over a band inside the edge minus that over a band outside), (k, n, n)."""
    k, n, _ = images.shape
    window = np.outer(np.hanning(n), np.hanning(n))
    spectra = np.abs(np.fft.fft2((images - images.mean(axis=(1, 2), keepdims=True)) * window))
    logs = np.log(spectra + 1e-6 * spectra.max(axis=(1, 2), keepdims=True) + 1e-300)
    freq = np.fft.fftfreq(n) * n
    r = np.hypot(freq[:, None], freq[None, :])
    inside = (r < radius) & (r >= radius - EDGE_WIDTH_PX)
    outside = (r >= radius) & (r < radius + EDGE_WIDTH_PX)
    kernel = inside / inside.sum() - outside / outside.sum()
    # correlation: the map at u averages the spectrum over the kernel centred at u
    return np.real(np.fft.ifft2(np.fft.fft2(logs) * np.conj(np.fft.fft2(kernel))))


def _scores(edges: np.ndarray, centres: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Mean edge strength over the images with every centre moved by each of ``shifts`` (bilinear), (S,)."""
    n = edges.shape[-1]
    points = centres[None, :, :] + shifts[:, None, :]                 # (S, k, 2), spectrum px (0 = DC)
    low = np.floor(points)
    frac = points - low
    y0, x0 = low[..., 0].astype(np.int64) % n, low[..., 1].astype(np.int64) % n
    y1, x1 = (y0 + 1) % n, (x0 + 1) % n
    image = np.arange(edges.shape[0])[None, :]
    fy, fx = frac[..., 0], frac[..., 1]
    value = (edges[image, y0, x0] * (1 - fy) * (1 - fx) + edges[image, y0, x1] * (1 - fy) * fx
             + edges[image, y1, x0] * fy * (1 - fx) + edges[image, y1, x1] * fy * fx)
    return value.mean(axis=1)
