"""Resolution (bar) chart with a known layout.

The chart follows the one used by Holloway et al. (2016), "Toward long
distance, sub-diffraction imaging using coherent camera arrays": for every
bar width ``w`` there is one group of horizontal bars (long along x, stacked
along y, so they measure resolution along y) and one group of vertical bars
(long along y, side by side along x, measuring resolution along x).  Bars are
white (amplitude 1.0) on a black (0.0) background.

Because every bar and every gap between bars is recorded as a pixel box,
contrast metrics (:mod:`cca_cli.metrics`) can be evaluated exactly on any
image of the chart.

Layout rule
-----------
Groups are placed by deterministic shelf (row) packing, largest width first,
horizontal group before vertical group of the same width.  Every group is
surrounded by a quiet black margin:

* between two neighbouring groups (same row, or consecutive rows) the gap is
  at least ``max(w_a, w_b, 4)`` pixels;
* between a group and the image edge the gap is at least ``max(w, 4)``
  pixels, so that groups on opposite edges are also well separated when the
  image is treated as periodic (FFT filtering).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Box",
    "BarGroup",
    "BarChart",
    "DEFAULT_WIDTHS",
    "resolution_chart",
    "chart_groups_for_grid",
]

Box = tuple[int, int, int, int]
"""A half-open pixel box ``(y0, y1, x0, x1)``."""

DEFAULT_WIDTHS: tuple[int, ...] = (20, 18, 16, 14, 12, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1)
"""Bar widths (pixels) of the default chart."""

_MIN_MARGIN = 4
_MIN_LENGTH = 7
_ORIENTATIONS = ("horizontal", "vertical")


@dataclass(frozen=True)
class BarGroup:
    """One group of parallel bars with known pixel boxes.

    Parameters
    ----------
    width_px : int
        Bar width (and gap width) in pixels of the grid the chart was drawn
        on.  It is the group's label: :func:`chart_groups_for_grid` keeps it
        unchanged while rescaling the boxes.
    orientation : str
        ``'horizontal'``: bars long along x, stacked along y (the group
        measures resolution along y).  ``'vertical'``: bars long along y,
        side by side along x (measures resolution along x).
    box : tuple of int
        ``(y0, y1, x0, x1)``, half-open, enclosing the whole group.
    bar_boxes : tuple of tuple of int
        One half-open box per bar.
    gap_boxes : tuple of tuple of int
        One half-open box per gap between consecutive bars (``bars - 1`` of
        them), with the same length as the bars.
    """

    width_px: int
    orientation: str
    box: Box
    bar_boxes: tuple[Box, ...]
    gap_boxes: tuple[Box, ...]

    @property
    def axis(self) -> int:
        """Array axis along which the group measures resolution (0 = y, 1 = x).

        Returns
        -------
        int
            0 for horizontal bars, 1 for vertical bars.
        """
        return 0 if self.orientation == "horizontal" else 1


@dataclass(frozen=True, eq=False)
class BarChart:
    """A bar chart image together with its layout.

    Parameters
    ----------
    image : numpy.ndarray
        float32 amplitude image of shape ``(size, size)``; bars are 1.0 and
        everything else 0.0.  The array is read-only.
    groups : tuple of BarGroup
        All groups, in layout order (width descending, horizontal first).
    """

    image: np.ndarray
    groups: tuple[BarGroup, ...]

    @property
    def size(self) -> int:
        """Side length of the square chart in pixels.

        Returns
        -------
        int
            ``image.shape[0]``.
        """
        return int(self.image.shape[0])

    @property
    def widths(self) -> tuple[int, ...]:
        """Unique bar widths of the chart, sorted descending.

        Returns
        -------
        tuple of int
            The widths in pixels.
        """
        return tuple(sorted({g.width_px for g in self.groups}, reverse=True))

    def group(self, width_px: int, orientation: str) -> BarGroup:
        """Look up the group with a given width and orientation.

        Parameters
        ----------
        width_px : int
            Bar width in pixels.
        orientation : str
            ``'horizontal'`` or ``'vertical'``.

        Returns
        -------
        BarGroup
            The matching group.

        Raises
        ------
        ValueError
            If the chart has no such group.
        """
        for g in self.groups:
            if g.width_px == width_px and g.orientation == orientation:
                return g
        raise ValueError(
            f"group: expected a (width_px, orientation) present in the chart "
            f"(widths {list(self.widths)}, orientations {list(_ORIENTATIONS)}), "
            f"got ({width_px!r}, {orientation!r})"
        )


def _check_int(name: str, value, *, minimum: int | None) -> int:
    """Return ``value`` as int or raise ValueError naming ``name``."""
    what = "an integer" if minimum is None else f"an integer >= {minimum}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name}: expected {what}, got {value!r}")
    if minimum is not None and value < minimum:
        raise ValueError(f"{name}: expected {what}, got {value!r}")
    return int(value)


def _group_shape(width: int, orientation: str, bars: int, length: int) -> tuple[int, int]:
    """(height, width) in pixels of a group."""
    extent = (2 * bars - 1) * width
    return (extent, length) if orientation == "horizontal" else (length, extent)


def _make_group(
    width: int, orientation: str, bars: int, length: int, y0: int, x0: int
) -> BarGroup:
    """Build the boxes of one group whose top-left corner is at (y0, x0)."""
    h, wd = _group_shape(width, orientation, bars, length)
    bar_boxes = []
    gap_boxes = []
    for k in range(2 * bars - 1):
        a = k * width
        if orientation == "horizontal":
            b = (y0 + a, y0 + a + width, x0, x0 + length)
        else:
            b = (y0, y0 + length, x0 + a, x0 + a + width)
        (bar_boxes if k % 2 == 0 else gap_boxes).append(b)
    return BarGroup(
        width_px=width,
        orientation=orientation,
        box=(y0, y0 + h, x0, x0 + wd),
        bar_boxes=tuple(bar_boxes),
        gap_boxes=tuple(gap_boxes),
    )


def _shelf_pack(
    shapes: Sequence[tuple[int, int, int]], size: int
) -> list[tuple[int, int]] | None:
    """Place rectangles row by row in a square of side ``size``.

    Parameters
    ----------
    shapes : sequence of (height, width, margin)
        Items in placement order, ``margin`` non-increasing.
    size : int
        Side of the square.

    Returns
    -------
    list of (y0, x0) or None
        Top-left corners, or None when the items do not fit.

    Notes
    -----
    Gap between two items of one row: ``max(m_left, m_right)``.  Gap between
    rows: ``max`` over the margins of both rows (the first item of a row has
    the largest margin because margins are non-increasing).  Gap to the
    image edges: the item's own margin.
    """
    positions: list[tuple[int, int]] = []
    row_y = None  # top of the current row
    row_bottom = 0  # max y1 in the current row
    row_margin = 0  # max margin in the current row
    x_next = 0  # x1 of the last item of the current row
    prev_margin = 0
    for h, w, m in shapes:
        placed = False
        if row_y is not None:
            x0 = x_next + max(prev_margin, m)
            if x0 + w + m <= size and row_y + h + m <= size:
                positions.append((row_y, x0))
                x_next = x0 + w
                row_bottom = max(row_bottom, row_y + h)
                row_margin = max(row_margin, m)
                placed = True
        if not placed:
            y0 = m if row_y is None else row_bottom + max(row_margin, m)
            x0 = m
            if x0 + w + m > size or y0 + h + m > size:
                return None
            positions.append((y0, x0))
            row_y, row_bottom, row_margin, x_next = y0, y0 + h, m, x0 + w
        prev_margin = m
    return positions


def _layout_groups(
    specs: Sequence[tuple[int, str, int]], size: int, bars: int
) -> list[BarGroup] | None:
    """Pack groups given as (width, orientation, length); None if they do not fit.

    Groups are placed by width descending; equal widths keep their order in
    ``specs``.  The result is in the order of ``specs``.
    """
    order = sorted(
        range(len(specs)),
        key=lambda i: (-specs[i][0], i),
    )
    shapes = []
    for i in order:
        w, o, length = specs[i]
        h, wd = _group_shape(w, o, bars, length)
        shapes.append((h, wd, max(w, _MIN_MARGIN)))
    pos = _shelf_pack(shapes, size)
    if pos is None:
        return None
    groups: list[BarGroup | None] = [None] * len(specs)
    for i, (y0, x0) in zip(order, pos):
        w, o, length = specs[i]
        groups[i] = _make_group(w, o, bars, length, y0, x0)
    return groups  # type: ignore[return-value]


def _render(size: int, groups: Sequence[BarGroup]) -> np.ndarray:
    """Draw the bars of ``groups`` as 1.0 on a float32 zero image (read-only)."""
    image = np.zeros((size, size), dtype=np.float32)
    for g in groups:
        for y0, y1, x0, x1 in g.bar_boxes:
            image[y0:y1, x0:x1] = 1.0
    image.setflags(write=False)
    return image


def resolution_chart(
    size: int = 512, *, widths: Sequence[int] = DEFAULT_WIDTHS, bars: int = 3
) -> BarChart:
    """Draw a bar resolution chart with a known layout.

    Parameters
    ----------
    size : int, default 512
        Side of the square image in pixels.
    widths : sequence of int, keyword-only
        Bar widths in pixels (each >= 1, unique).  For every width there is
        one horizontal and one vertical group.
    bars : int, keyword-only, default 3
        Number of bars per group (>= 2).

    Returns
    -------
    BarChart
        float32 amplitude image (bars 1.0, background 0.0) and the groups.

    Raises
    ------
    ValueError
        If an argument is invalid, or if the groups do not fit in
        ``size x size`` with the required margins.

    Notes
    -----
    A group of width ``w`` has ``bars`` bars of width ``w`` separated by gaps
    of width ``w``: its extent across the bars is ``(2*bars - 1) * w`` and the
    bar length is ``L = max(5*w, 7)`` pixels (USAF proportion, with a floor so
    that the finest groups still have area).  Groups are shelf-packed largest
    first with a black margin of at least ``max(w_a, w_b, 4)`` pixels between
    neighbouring groups and ``max(w, 4)`` pixels to the image edge.
    """
    size = _check_int("size", size, minimum=1)
    bars = _check_int("bars", bars, minimum=2)
    if isinstance(widths, (str, bytes)) or not isinstance(widths, Sequence):
        raise ValueError(f"widths: expected a sequence of integers >= 1, got {widths!r}")
    if len(widths) == 0:
        raise ValueError("widths: expected at least one bar width, got an empty sequence")
    ws = [_check_int("widths", w, minimum=1) for w in widths]
    if len(set(ws)) != len(ws):
        raise ValueError(f"widths: expected unique bar widths, got {list(widths)!r}")
    specs = [(w, o, max(5 * w, _MIN_LENGTH)) for w in ws for o in _ORIENTATIONS]
    groups = _layout_groups(specs, size, bars)
    if groups is None:
        raise ValueError(
            f"size: a chart with widths {ws} and {bars} bars per group does not fit "
            f"in {size}x{size} pixels with the required margins; "
            "use a larger size or fewer/smaller widths"
        )
    return BarChart(image=_render(size, groups), groups=tuple(groups))


def _scale_box(box: Box, factor: float, *, outward: bool) -> Box:
    y0, y1, x0, x1 = box
    if outward:
        ny0, nx0 = math.floor(y0 * factor), math.floor(x0 * factor)
        ny1, nx1 = math.ceil(y1 * factor), math.ceil(x1 * factor)
    else:
        ny0, ny1, nx0, nx1 = (math.floor(v * factor + 0.5) for v in (y0, y1, x0, x1))
    return (ny0, max(ny1, ny0 + 1), nx0, max(nx1, nx0 + 1))


def chart_groups_for_grid(chart: BarChart, grid_size: int) -> tuple[BarGroup, ...]:
    """Rescale the chart's group boxes to another square sampling grid.

    Parameters
    ----------
    chart : BarChart
        The chart as drawn (``chart.size`` pixels square).
    grid_size : int
        Side of the grid the image to be measured is sampled on (for
        example 1024 for a recovered image of a 512 chart).

    Returns
    -------
    tuple of BarGroup
        Groups with boxes in ``grid_size`` pixel coordinates.  ``width_px``
        is unchanged: it stays the bar width in *chart* pixels, so limits
        measured on differently sampled images are in the same unit.

    Notes
    -----
    With ``s = grid_size / chart.size`` every coordinate ``c`` maps to
    ``c * s``.  Group boxes are rounded outward (``floor`` of starts,
    ``ceil`` of ends).  Bar and gap boxes are rounded to the nearest integer
    so that adjacent bars and gaps still tile the group without overlapping
    (for integer ``s`` both rules are exact); a box that would become empty
    keeps one pixel.
    """
    if not isinstance(chart, BarChart):
        raise ValueError(f"chart: expected a BarChart, got {type(chart).__name__}")
    grid_size = _check_int("grid_size", grid_size, minimum=1)
    factor = grid_size / chart.size
    out = []
    for g in chart.groups:
        out.append(
            BarGroup(
                width_px=g.width_px,
                orientation=g.orientation,
                box=_scale_box(g.box, factor, outward=True),
                bar_boxes=tuple(_scale_box(b, factor, outward=False) for b in g.bar_boxes),
                gap_boxes=tuple(_scale_box(b, factor, outward=False) for b in g.gap_boxes),
            )
        )
    return tuple(out)
