"""Synthetic USAF-1951-like resolution target.

Each element (group ``g``, element ``e``) of the USAF 1951 target has
``2 ** (g + (e - 1) / 6)`` line pairs per millimetre, i.e. bars of width
``1 / (2 * lp_per_mm)`` mm, three horizontal and three vertical bars of
length five times the width.  This module draws such elements at a given
object-plane pixel pitch.  The real target's spiral layout is not
reproduced: elements are shelf-packed with the same margins as the bar
chart of :mod:`cca_cli.targets.charts`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cca_cli.targets.charts import BarGroup, _check_int, _layout_groups, _render

__all__ = ["UsafElement", "UsafChart", "usaf_lp_per_mm", "usaf1951_chart"]

_ELEMENTS = (1, 2, 3, 4, 5, 6)
_BARS = 3


def usaf_lp_per_mm(group: int, element: int) -> float:
    """Spatial frequency of a USAF-1951 element.

    Parameters
    ----------
    group : int
        USAF group number (may be negative).
    element : int
        Element number, 1 to 6.

    Returns
    -------
    float
        Line pairs per millimetre.

    Notes
    -----
    ``lp/mm = 2 ** (group + (element - 1) / 6)``; the bar width is
    ``1 / (2 * lp/mm)`` mm.
    """
    group = _check_int("group", group, minimum=None)
    if (
        isinstance(element, (bool, np.bool_))
        or not isinstance(element, (int, np.integer))
        or not 1 <= element <= 6
    ):
        raise ValueError(f"element: expected an integer from 1 to 6, got {element!r}")
    return float(2.0 ** (group + (int(element) - 1) / 6.0))


@dataclass(frozen=True)
class UsafElement:
    """One drawn element of the USAF chart.

    Parameters
    ----------
    group : int
        USAF group number.
    element : int
        Element number (1-6).
    lp_per_mm : float
        Line pairs per millimetre, ``2 ** (group + (element - 1) / 6)``.
    width_px : float
        Exact bar width in pixels, ``1e-3 / (2 * lp_per_mm) / pixel_pitch_m``.
    horizontal : BarGroup
        The three horizontal bars (measure resolution along y); its
        ``width_px`` is the drawn width, ``round(width_px)``.
    vertical : BarGroup
        The three vertical bars (measure resolution along x).
    """

    group: int
    element: int
    lp_per_mm: float
    width_px: float
    horizontal: BarGroup
    vertical: BarGroup

    @property
    def drawn_width_px(self) -> int:
        """Bar width actually drawn, in pixels (rounded from ``width_px``).

        Returns
        -------
        int
            ``max(1, round(width_px))``.
        """
        return self.horizontal.width_px


@dataclass(frozen=True, eq=False)
class UsafChart:
    """A synthetic USAF-1951 target and its layout.

    Parameters
    ----------
    image : numpy.ndarray
        float32 amplitude image (bars 1.0, background 0.0), read-only.
    pixel_pitch_m : float
        Object-plane pixel pitch in metres per pixel.
    elements : tuple of UsafElement
        Drawn elements, coarsest first (ascending lp/mm).
    """

    image: np.ndarray
    pixel_pitch_m: float
    elements: tuple[UsafElement, ...]

    @property
    def size(self) -> int:
        """Side length of the square image in pixels.

        Returns
        -------
        int
            ``image.shape[0]``.
        """
        return int(self.image.shape[0])


def usaf1951_chart(
    size: int,
    *,
    pixel_pitch_m: float,
    groups: Sequence[int] = (-2, -1, 0, 1, 2, 3),
) -> UsafChart:
    """Draw a synthetic USAF-1951-like target.

    Parameters
    ----------
    size : int
        Side of the square image in pixels.
    pixel_pitch_m : float, keyword-only
        Object-plane pixel pitch in metres per pixel (> 0).
    groups : sequence of int, keyword-only
        USAF groups to draw, each with elements 1 to 6.

    Returns
    -------
    UsafChart
        The float32 amplitude image and the drawn elements.

    Raises
    ------
    ValueError
        If an argument is invalid or no element can be drawn.

    Notes
    -----
    Bar width of element (g, e): ``w = 1e-3 / (2 * 2**(g + (e-1)/6)) /
    pixel_pitch_m`` pixels.  Elements with ``w < 1`` are skipped.  The
    drawn width is ``max(1, round(w))`` pixels, bar length ``5 *`` drawn
    width, three bars per orientation, gaps equal to the width.

    Selection rule: the finest elements (``w >= 1``) are always preferred;
    the chart keeps the largest set of the ``k`` finest elements that packs
    into the image (shelf packing, largest first, margins
    ``max(w_a, w_b, 4)`` between groups and ``max(w, 4)`` to the edge);
    coarser elements that do not fit are dropped.
    """
    size = _check_int("size", size, minimum=1)
    if isinstance(pixel_pitch_m, (bool, np.bool_)) or not isinstance(
        pixel_pitch_m, (int, float, np.integer, np.floating)
    ):
        raise ValueError(f"pixel_pitch_m: expected a positive number, got {pixel_pitch_m!r}")
    pitch = float(pixel_pitch_m)
    if not np.isfinite(pitch) or pitch <= 0:
        raise ValueError(
            f"pixel_pitch_m: expected a positive finite number, got {pixel_pitch_m!r}"
        )
    if isinstance(groups, (str, bytes)) or not isinstance(groups, Sequence) or len(groups) == 0:
        raise ValueError(f"groups: expected a non-empty sequence of integers, got {groups!r}")
    gs = [_check_int("groups", g, minimum=None) for g in groups]
    if len(set(gs)) != len(gs):
        raise ValueError(f"groups: expected unique group numbers, got {list(groups)!r}")

    candidates = []  # (lp, group, element, exact width, drawn width)
    for g in gs:
        for e in _ELEMENTS:
            lp = usaf_lp_per_mm(g, e)
            w = 1e-3 / (2.0 * lp) / pitch
            if w < 1.0:
                continue
            candidates.append((lp, g, e, w, max(1, int(round(w)))))
    if not candidates:
        raise ValueError(
            f"pixel_pitch_m: every element of groups {gs} has bars narrower than "
            f"1 pixel at {pitch:g} m/px; expected a smaller pitch or coarser groups"
        )
    candidates.sort(key=lambda c: -c[0])  # finest first

    for k in range(len(candidates), 0, -1):
        chosen = sorted(candidates[:k], key=lambda c: c[0])  # coarsest first
        specs = []
        for c in chosen:
            wd = c[4]
            specs.append((wd, "horizontal", 5 * wd))
            specs.append((wd, "vertical", 5 * wd))
        laid = _layout_groups(specs, size, _BARS)
        if laid is None:
            continue
        elements = tuple(
            UsafElement(
                group=c[1],
                element=c[2],
                lp_per_mm=c[0],
                width_px=c[3],
                horizontal=laid[2 * i],
                vertical=laid[2 * i + 1],
            )
            for i, c in enumerate(chosen)
        )
        return UsafChart(image=_render(size, laid), pixel_pitch_m=pitch, elements=elements)

    raise ValueError(
        f"size: no USAF element of groups {gs} fits in {size}x{size} pixels at "
        f"{pitch:g} m/px (finest bar {candidates[0][4]} px needs a group of "
        f"{5 * candidates[0][4]} px plus margins); expected a larger size or finer groups"
    )
