"""Three-bar Michelson contrast read from a profile inside a box (real captures).

On a recorded USAF-1951 target the bar positions are not known to the pixel,
so the synthetic-chart reading (:mod:`cca_cli.metrics.usaf`, which averages
known bar and gap boxes) does not apply. This reading needs only a box around
one element's three bars, the bars' nominal period and the direction across
them:

1. average the image along the bar length inside the box, giving a profile
   across the bars;
2. find three local minima whose two spacings each lie within ±25 % of the
   nominal period (the dark bars);
3. take the maximum of the profile between each pair of neighbouring minima;
4. ``C = (mean of the 2 maxima − mean of the 3 minima) / (their sum)``.

An element without such a triple of minima reads as NaN (not resolved).
Boxes, the element table and its text format are described in
:func:`parse_element_table`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

__all__ = ["BarElement", "three_bar_profile_contrast", "parse_element_table", "usaf_period_m",
           "read_bar_elements", "PERIOD_TOLERANCE"]

PERIOD_TOLERANCE = 0.25
"""Largest relative deviation of a minima spacing from the nominal period."""


def usaf_period_m(group: int, element: int) -> float:
    """Bar period (one bar plus one gap) of a USAF-1951 element, in metres.

    The element's frequency is ``2^(group + (element − 1)/6)`` line pairs per mm.
    """
    return 1e-3 / 2.0 ** (group + (element - 1) / 6.0)


def _box_indices(lo: float, hi: float, size: int, name: str) -> slice:
    start, stop = int(math.ceil(lo)), int(math.floor(hi)) + 1
    if not (0 <= start < stop <= size):
        raise ValueError(f"box: {name} range {lo:g}–{hi:g} px is empty or outside the image (0–{size - 1})")
    return slice(start, stop)


def three_bar_profile_contrast(image, box, period_px: float, axis: int,
                               tolerance: float = PERIOD_TOLERANCE) -> float:
    """Michelson contrast of three dark bars read from a profile across them.

    Parameters
    ----------
    image : array_like, (H, W)
        Real image (usually an amplitude ``|object|``), bars darker than gaps.
    box : tuple of 4 float
        ``(y0, y1, x0, x1)`` in pixels of ``image`` (pixel ``i`` sits at
        coordinate ``i``); the rows ``ceil(y0) … floor(y1)`` and columns
        ``ceil(x0) … floor(x1)`` are read.
    period_px : float
        Nominal bar period (bar + gap) in pixels of ``image``.
    axis : {0, 1}
        Image axis the profile runs along: 0 reads bars that lie along the
        columns (profile over rows, averaged along each row), 1 reads bars
        that lie along the rows (profile over columns).
    tolerance : float, optional
        Largest relative deviation of each minima spacing from ``period_px``.

    Returns
    -------
    float
        ``C = (mean(max₁, max₂) − mean(min₁, min₂, min₃)) / (sum)`` in
        [−1, 1]; NaN when the profile has no three local minima spaced within
        tolerance of the period. When several triples qualify, the one whose
        spacings are closest to the period is read.

    Raises
    ------
    ValueError
        ``image`` is not a real 2-D array, the box lies outside it, ``axis``
        is not 0 or 1, or ``period_px`` is not positive.
    """
    img = np.asarray(image)
    if img.ndim != 2 or np.iscomplexobj(img) or not np.issubdtype(img.dtype, np.number):
        raise ValueError(f"image: expected a real 2-D array, got dtype {img.dtype} and shape {img.shape}")
    if axis not in (0, 1):
        raise ValueError(f"axis: expected 0 (profile over rows) or 1 (profile over columns), got {axis!r}")
    if not period_px > 0:
        raise ValueError(f"period_px: expected a positive period, got {period_px!r}")
    y0, y1, x0, x1 = (float(v) for v in box)
    rows = _box_indices(y0, y1, img.shape[0], "row")
    cols = _box_indices(x0, x1, img.shape[1], "column")
    profile = np.asarray(img[rows, cols], np.float64).mean(axis=1 - axis)
    inner = np.arange(1, profile.size - 1)
    minima = inner[(profile[inner] < profile[inner - 1]) & (profile[inner] <= profile[inner + 1])]
    lo, hi = (1.0 - tolerance) * period_px, (1.0 + tolerance) * period_px
    best = None
    for a in range(len(minima)):
        for b in range(a + 1, len(minima)):
            d1 = minima[b] - minima[a]
            if d1 > hi:
                break
            if d1 < lo:
                continue
            for c in range(b + 1, len(minima)):
                d2 = minima[c] - minima[b]
                if d2 > hi:
                    break
                if d2 < lo:
                    continue
                miss = abs(d1 - period_px) + abs(d2 - period_px)
                if best is None or miss < best[0]:
                    best = (miss, minima[a], minima[b], minima[c])
    if best is None:
        return float("nan")
    _, m1, m2, m3 = best
    dips = profile[[m1, m2, m3]].mean()
    peaks = 0.5 * (profile[m1:m2 + 1].max() + profile[m2:m3 + 1].max())
    total = peaks + dips
    return float((peaks - dips) / total) if total > 0 else float("nan")


@dataclass(frozen=True)
class BarElement:
    """One USAF element's reading box.

    Attributes
    ----------
    group, element : int
        USAF group and element.
    axis : int
        Profile axis (0: over rows, 1: over columns), as in :func:`three_bar_profile_contrast`.
    box : tuple of 4 float
        ``(y0, y1, x0, x1)`` in the pixels of the image the table refers to.
    """

    group: int
    element: int
    axis: int
    box: tuple[float, float, float, float]

    @property
    def name(self) -> str:
        """``G<group>E<element>``."""
        return f"G{self.group}E{self.element}"

    @property
    def orientation(self) -> str:
        """``row`` (profile over rows) or ``col`` (profile over columns)."""
        return "row" if self.axis == 0 else "col"


_NUMBER = r"-?\d+(?:\.\d+)?"
_RANGE = re.compile(rf"({_NUMBER})\s*[–-]\s*({_NUMBER})")
_NAME = re.compile(r"^G(\d+)E(\d+)$")


def parse_element_table(text: str) -> list[BarElement]:
    """Element boxes from a Markdown table.

    Reads every table row whose first cell names an element (``G8E2``); its
    third cell lists the profile directions (``row`` or ``col``, several
    separated by ``/``) and its fourth the matching boxes, each ``y0–y1,
    x0–x1`` (en dash or hyphen), separated by ``/``. Further cells are
    ignored. This is the layout of the dataset READMEs' known-answer tables:

    ``| G8E2 | 287 | col / row | 6.9–10.6, 17.9–23.1 / 11.6–16.4, 18.8–22.5 | … |``

    Parameters
    ----------
    text : str
        Markdown text (other lines are skipped).

    Returns
    -------
    list of BarElement
        One entry per element and direction, in table order.

    Raises
    ------
    ValueError
        An element row whose directions and boxes do not match, naming the row.
    """
    out = []
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 4 or not _NAME.match(cells[0]):
            continue
        group, element = (int(v) for v in _NAME.match(cells[0]).groups())
        directions = [d.strip() for d in cells[2].split("/")]
        boxes = [b.strip() for b in cells[3].split("/")]
        if len(directions) != len(boxes) or any(d not in ("row", "col") for d in directions):
            raise ValueError(f"element table: row {cells[0]}: expected matching 'row'/'col' directions and boxes, "
                             f"got {cells[2]!r} and {cells[3]!r}")
        for direction, box in zip(directions, boxes):
            ranges = _RANGE.findall(box)
            if len(ranges) != 2:
                raise ValueError(f"element table: row {cells[0]}: box {box!r} is not 'y0–y1, x0–x1'")
            (a, b), (c, d) = ranges
            out.append(BarElement(group, element, 0 if direction == "row" else 1,
                                  (float(a), float(b), float(c), float(d))))
    return out


def read_bar_elements(image, elements, table_pixel_m: float, upsampling: float = 1.0) -> dict[str, float]:
    """Three-bar contrast of every element of a table on one image.

    Parameters
    ----------
    image : array_like, (H, W)
        Real image (amplitude), sampled ``upsampling`` times finer than the
        pixels the table's boxes are given in.
    elements : iterable of BarElement
    table_pixel_m : float
        Object-plane size of one table pixel (m), which sets each element's
        period in pixels: ``usaf_period_m / table_pixel_m · upsampling``.
    upsampling : float, optional
        Image pixels per table pixel; boxes are scaled by it.

    Returns
    -------
    dict
        ``"G9E1 col" → C`` (NaN where no three minima are found).
    """
    out = {}
    for el in elements:
        box = tuple(v * upsampling for v in el.box)
        period = usaf_period_m(el.group, el.element) / table_pixel_m * upsampling
        out[f"{el.name} {el.orientation}"] = three_bar_profile_contrast(image, box, period, el.axis)
    return out
