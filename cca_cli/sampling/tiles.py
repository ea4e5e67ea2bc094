"""Overlapping tiles of a wide frame, and the blend that joins their recoveries without seams.

A frame too large for one recovery, or whose pupil and illumination angles
change across the field, is recovered in square tiles of ``size`` pixels that
overlap their neighbours by at least ``overlap`` pixels. Along each axis the
tiles are spread evenly from edge to edge (all the same size, so they share one
grid), and each tile's weight is 1 in its interior and falls smoothly (sin²)
to 0 across the middle half of every overlap with a neighbour. The weights of
all tiles sum to 1 at every frame pixel, so the blend is a weighted sum and
the outer quarter of each overlap, nearest a tile's edge where its recovery is
least constrained, is not used at all.

An LED array lights each point of the sample from its own angle: seen from a
tile whose centre sits at ``p`` (metres from the frame centre, frame axes), LED
``i`` lies along ``L_i − p``, ``L_i`` the LED's position in its plane, which
:func:`local_illumination` recovers from the sines at the frame centre and the
LED plane's distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MIN_TILE_PX", "Tile", "TilePlan", "plan_tiles", "axis_starts", "local_illumination", "tile_order"]


@dataclass(frozen=True)
class Tile:
    """One tile: its place in the tile grid and its box in frame pixels."""

    index: int
    row: int
    col: int
    y0: int
    x0: int
    size: int

    @property
    def centre_yx(self) -> tuple[float, float]:
        """Centre of the tile in frame pixel coordinates (pixel centres at integers)."""
        half = (self.size - 1) / 2.0
        return self.y0 + half, self.x0 + half

    @property
    def box(self) -> tuple[int, int, int, int]:
        """``(y0, x0, height, width)`` in frame pixels."""
        return self.y0, self.x0, self.size, self.size


def axis_starts(length: int, size: int, overlap: int) -> list[int]:
    """First pixel of each tile along an axis of ``length`` pixels: evenly spread, edge to edge.

    The fewest tiles of ``size`` pixels whose neighbours overlap by at least
    ``overlap`` pixels; a single tile when ``size >= length``.
    """
    if size >= length:
        return [0]
    count = math.ceil((length - overlap) / (size - overlap))
    count = max(count, 2)
    return [int(round(v)) for v in np.linspace(0, length - size, count)]


def _ramp_weight(coords: np.ndarray, starts: list[int], size: int, which: int) -> np.ndarray:
    """Weight of tile ``which`` along one axis at frame coordinates ``coords``.

    1 inside, sin² ramps over the middle half of each overlap with the previous
    and the next tile, 0 beyond; the weights of all tiles sum to 1.
    """
    weight = np.ones(coords.shape, np.float64)
    start, end = starts[which], starts[which] + size  # pixels start … end − 1
    if which > 0:  # overlap with the previous tile: [start, previous end)
        lo, hi = start, starts[which - 1] + size
        quarter = (hi - lo) / 4.0
        a, b = lo - 0.5 + quarter, hi - 0.5 - quarter
        weight *= _rise(coords, a, b)
    if which < len(starts) - 1:  # overlap with the next tile: [next start, end)
        lo, hi = starts[which + 1], end
        quarter = (hi - lo) / 4.0
        a, b = lo - 0.5 + quarter, hi - 0.5 - quarter
        weight *= 1.0 - _rise(coords, a, b)
    return weight


def _rise(coords: np.ndarray, a: float, b: float) -> np.ndarray:
    """0 before ``a``, 1 after ``b``, sin² in between (a step when ``a == b``)."""
    if b <= a:
        return (coords >= a).astype(np.float64)
    t = np.clip((coords - a) / (b - a), 0.0, 1.0)
    return np.sin(0.5 * np.pi * t) ** 2


@dataclass(frozen=True)
class TilePlan:
    """The tiles of a frame and their blend weights.

    Attributes
    ----------
    frame_shape : tuple of int
        ``(H, W)`` of the frame (sensor px).
    size, overlap : int
        Tile side and the least overlap between neighbours (px).
    row_starts, col_starts : tuple of int
        First row / column of each tile row / column.
    """

    frame_shape: tuple[int, int]
    size: int
    overlap: int
    row_starts: tuple[int, ...]
    col_starts: tuple[int, ...]

    @property
    def grid_shape(self) -> tuple[int, int]:
        """Tile rows and columns."""
        return len(self.row_starts), len(self.col_starts)

    @property
    def tiles(self) -> tuple[Tile, ...]:
        """Every tile, row by row."""
        cols = len(self.col_starts)
        return tuple(Tile(r * cols + c, r, c, y0, x0, self.size)
                     for r, y0 in enumerate(self.row_starts) for c, x0 in enumerate(self.col_starts))

    def __len__(self) -> int:
        return len(self.row_starts) * len(self.col_starts)

    def weight(self, tile: Tile, upsampling: int = 1) -> np.ndarray:
        """Blend weight of ``tile`` on its box, float32 ``(size·q, size·q)`` for upsampling ``q``.

        Sample ``j`` of the ``q``-times finer grid sits at frame coordinate ``(j + 0.5)/q − 0.5``.
        """
        q = int(upsampling)
        local = (np.arange(self.size * q) + 0.5) / q - 0.5
        wy = _ramp_weight(tile.y0 + local, list(self.row_starts), self.size, tile.row)
        wx = _ramp_weight(tile.x0 + local, list(self.col_starts), self.size, tile.col)
        return np.outer(wy, wx).astype(np.float32)

    def tile_at(self, row: int, col: int) -> Tile:
        """The tile in tile-grid row ``row``, column ``col``."""
        return self.tiles[row * len(self.col_starts) + col]


#: The smallest tile: its guard band and pupil fit need room (configs and the API refuse smaller ones alike).
MIN_TILE_PX = 32


def plan_tiles(frame_shape, size_px: int, overlap_px: int) -> TilePlan:
    """Tiles of ``size_px`` overlapping by at least ``overlap_px`` that cover an ``(H, W)`` frame.

    Raises
    ------
    ValueError
        When the overlap is not below half the tile (then non-neighbours would
        overlap and the blend would lose its meaning) or a tile is larger than
        the frame.
    """
    h, w = (int(v) for v in frame_shape)
    size, overlap = int(size_px), int(overlap_px)
    if size < MIN_TILE_PX or overlap < 0:
        raise ValueError(f"tiles must be at least {MIN_TILE_PX} px (a guard band and a pupil fit in them) with an "
                         f"overlap ≥ 0; got {size} and {overlap}")
    if 2 * overlap >= size:
        raise ValueError(f"an overlap of {overlap} px is half the {size}-px tile or more; give an overlap below "
                         f"{size // 2} px")
    if size > min(h, w):
        raise ValueError(f"{size}-px tiles do not fit the {w} x {h} px frame; give a size of at most {min(h, w)} px")
    return TilePlan((h, w), size, overlap, tuple(axis_starts(h, size, overlap)), tuple(axis_starts(w, size, overlap)))


def tile_order(plan: TilePlan) -> list[tuple[Tile, Tile | None]]:
    """Tiles from the frame centre outwards, each with the neighbour it starts from (None for the first).

    A breadth-first walk of the tile grid from the tile nearest the centre:
    each tile's parent is an already-visited 4-neighbour, so a tile's pupil can
    start from a neighbour's estimate and a tile never waits on one farther out.
    """
    rows, cols = plan.grid_shape
    start = ((rows - 1) // 2, (cols - 1) // 2)
    order: list[tuple[Tile, Tile | None]] = [(plan.tile_at(*start), None)]
    seen = {start}
    head = 0
    while head < len(order):
        tile = order[head][0]
        head += 1
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            r, c = tile.row + dr, tile.col + dc
            if 0 <= r < rows and 0 <= c < cols and (r, c) not in seen:
                seen.add((r, c))
                order.append((plan.tile_at(r, c), tile))
    return order


def local_illumination(sines_yx: np.ndarray, offset_yx_m, distance_m: float) -> np.ndarray:
    """Illumination sines of each LED at a point ``offset_yx_m`` from the frame centre.

    Parameters
    ----------
    sines_yx : ndarray, (K, 2)
        ``[sin θ_y, sin θ_x]`` of the direction from the frame centre towards each
        LED, as the geometry counts them (capture ``k``'s pupil sits at
        ``sines_yx[k] · W / λ`` spectrum pixels).
    offset_yx_m : sequence of float
        The point, metres from the frame centre at the sample, frame axes.
    distance_m : float
        Distance of the LED plane from the sample (m).

    Returns
    -------
    ndarray, float64, (K, 2)
        The sines of the direction from the point towards each LED.
    """
    s = np.asarray(sines_yx, np.float64)
    if not (np.isfinite(distance_m) and distance_m > 0):
        raise ValueError(f"the LED distance must be a positive number of metres, got {distance_m!r}")
    axial = np.sqrt(np.clip(1.0 - np.sum(s * s, axis=1, keepdims=True), 1e-12, None))
    leds = distance_m * s / axial          # LED positions in the LED plane, relative to the frame centre
    towards = leds - np.asarray(offset_yx_m, np.float64)[None, :]
    return towards / np.sqrt(np.sum(towards * towards, axis=1, keepdims=True) + distance_m ** 2)
