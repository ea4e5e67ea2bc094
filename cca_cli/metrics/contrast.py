"""Bar contrast, contrast tables and the MTF20 resolution limit.

The contrast of a bar group is the Michelson-like contrast between the mean
intensity over its bars and the mean intensity over the gaps between them.
The resolution limit follows the usual "MTF20" rule: the finest bar width
for which this and every coarser group, in both orientations, keeps a
contrast of at least 20 %.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cca_cli.targets import BarChart, BarGroup

__all__ = [
    "ContrastTable",
    "bar_contrast",
    "contrast_table",
    "mtf_limit",
    "resolution_gain",
]


def _as_real_image(name: str, image) -> np.ndarray:
    """Return ``image`` as a 2-D real ndarray or raise ValueError naming it."""
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected a 2-D array, got shape {arr.shape}")
    if np.iscomplexobj(arr):
        raise ValueError(f"{name}: expected a real array (intensity), got dtype {arr.dtype}")
    if not (
        np.issubdtype(arr.dtype, np.floating)
        or np.issubdtype(arr.dtype, np.integer)
        or arr.dtype == np.bool_
    ):
        raise ValueError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    return arr


def _box_sum(image: np.ndarray, box, shape_name: str) -> tuple[float, int]:
    y0, y1, x0, x1 = box
    h, w = image.shape
    if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
        raise ValueError(
            f"{shape_name}: expected an image large enough for box (y0, y1, x0, x1)="
            f"{tuple(box)} (chart shape or larger), got shape {image.shape}"
        )
    region = image[y0:y1, x0:x1]
    return float(np.sum(region, dtype=np.float64)), int(region.size)


def _group_contrast(image: np.ndarray, group: BarGroup) -> float:
    bar_sum = bar_n = gap_sum = gap_n = 0
    for b in group.bar_boxes:
        s, n = _box_sum(image, b, "intensity")
        bar_sum += s
        bar_n += n
    for b in group.gap_boxes:
        s, n = _box_sum(image, b, "intensity")
        gap_sum += s
        gap_n += n
    if bar_n == 0 or gap_n == 0:
        raise ValueError(
            f"group: expected at least one bar box and one gap box, got "
            f"{len(group.bar_boxes)} bar and {len(group.gap_boxes)} gap boxes"
        )
    w_mean = bar_sum / bar_n
    b_mean = gap_sum / gap_n
    denom = w_mean + b_mean
    if not np.isfinite(denom) or denom <= 0.0:
        return 0.0
    return float((w_mean - b_mean) / denom)


def bar_contrast(intensity, group: BarGroup) -> float:
    """Contrast of one bar group in an intensity image.

    Parameters
    ----------
    intensity : array_like
        Real 2-D intensity image sampled on the grid of ``group``'s boxes.
    group : BarGroup
        The group whose bars and gaps are compared.

    Returns
    -------
    float
        The contrast ``C``; 1 for perfect bars on black, 0 for a uniform
        image, negative for contrast reversal.  0.0 when ``w + b <= 0``.

    Raises
    ------
    ValueError
        If ``intensity`` is not a real 2-D array or a box of the group lies
        outside it.

    Notes
    -----
    ``C = (w - b) / (w + b)`` where ``w`` is the mean intensity over all
    pixels of all bar boxes and ``b`` the mean over all pixels of all gap
    boxes (accumulated in float64).
    """
    if not isinstance(group, BarGroup):
        raise ValueError(f"group: expected a BarGroup, got {type(group).__name__}")
    return _group_contrast(_as_real_image("intensity", intensity), group)


@dataclass(frozen=True, eq=False)
class ContrastTable:
    """Contrast of every bar width in both orientations.

    Parameters
    ----------
    widths_px : numpy.ndarray
        int64 bar widths, sorted descending.
    horizontal : numpy.ndarray
        float64 contrast of the horizontal-bar groups (resolution along y).
    vertical : numpy.ndarray
        float64 contrast of the vertical-bar groups (resolution along x).
    """

    widths_px: np.ndarray
    horizontal: np.ndarray
    vertical: np.ndarray

    def __post_init__(self) -> None:
        w = np.array(self.widths_px, dtype=np.int64).reshape(-1)
        h = np.array(self.horizontal, dtype=np.float64).reshape(-1)
        v = np.array(self.vertical, dtype=np.float64).reshape(-1)
        if not (w.size == h.size == v.size):
            raise ValueError(
                "ContrastTable: expected widths_px, horizontal and vertical of equal "
                f"length, got {w.size}, {h.size}, {v.size}"
            )
        if w.size and np.any(np.diff(w) >= 0):
            raise ValueError(
                "widths_px: expected strictly descending unique widths, "
                f"got {w.tolist()}"
            )
        for name, arr in (("widths_px", w), ("horizontal", h), ("vertical", v)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def minimum(self) -> np.ndarray:
        """Elementwise minimum of the two orientations.

        Returns
        -------
        numpy.ndarray
            ``min(horizontal, vertical)`` per width (float64).
        """
        return np.minimum(self.horizontal, self.vertical)

    def to_dict(self) -> dict:
        """JSON-friendly representation.

        Returns
        -------
        dict
            ``{"widths_px": [int, ...], "horizontal": [float, ...],
            "vertical": [float, ...]}`` with plain Python numbers.
        """
        return {
            "widths_px": [int(x) for x in self.widths_px],
            "horizontal": [float(x) for x in self.horizontal],
            "vertical": [float(x) for x in self.vertical],
        }


def contrast_table(intensity, groups: BarChart | Sequence[BarGroup]) -> ContrastTable:
    """Contrast of every bar width, both orientations.

    Parameters
    ----------
    intensity : array_like
        Real 2-D intensity image on the grid of the groups' boxes.
    groups : BarChart or sequence of BarGroup
        The chart (its groups are used) or groups, e.g. from
        :func:`cca_cli.targets.chart_groups_for_grid`.  Each width must have
        exactly one horizontal and one vertical group.

    Returns
    -------
    ContrastTable
        Contrasts sorted by width descending.

    Raises
    ------
    ValueError
        If the image is not a real 2-D array, a box lies outside it, or a
        width lacks (or repeats) an orientation.

    Notes
    -----
    Each entry is :func:`bar_contrast`, ``C = (w - b) / (w + b)``.
    """
    image = _as_real_image("intensity", intensity)
    if isinstance(groups, BarChart):
        if image.shape != groups.image.shape:
            raise ValueError(
                f"intensity: expected the chart's shape {groups.image.shape}, got shape "
                f"{image.shape} (use chart_groups_for_grid for other grids)"
            )
        groups = groups.groups
    if isinstance(groups, (str, bytes)) or not isinstance(groups, Sequence) or len(groups) == 0:
        raise ValueError(
            f"groups: expected a BarChart or a non-empty sequence of BarGroup, got {groups!r}"
        )
    by_key: dict[tuple[int, str], BarGroup] = {}
    for g in groups:
        if not isinstance(g, BarGroup):
            raise ValueError(f"groups: expected BarGroup items, got {type(g).__name__}")
        key = (g.width_px, g.orientation)
        if key in by_key:
            raise ValueError(
                f"groups: expected one group per (width, orientation), got two for {key}"
            )
        by_key[key] = g
    need = (max(g.box[1] for g in groups), max(g.box[3] for g in groups))
    if image.shape[0] < need[0] or image.shape[1] < need[1]:
        raise ValueError(
            f"intensity: expected a shape of at least {need} to hold every group box, "
            f"got shape {image.shape}"
        )
    widths = sorted({k[0] for k in by_key}, reverse=True)
    h = []
    v = []
    for w in widths:
        for orient, out in (("horizontal", h), ("vertical", v)):
            if (w, orient) not in by_key:
                raise ValueError(
                    f"groups: expected a {orient} group for width {w} px, got none"
                )
            out.append(_group_contrast(image, by_key[(w, orient)]))
    return ContrastTable(widths_px=np.array(widths), horizontal=np.array(h), vertical=np.array(v))


def _check_threshold(threshold) -> float:
    if isinstance(threshold, (bool, np.bool_)) or not isinstance(
        threshold, (int, float, np.integer, np.floating)
    ) or not np.isfinite(threshold):
        raise ValueError(f"threshold: expected a finite number, got {threshold!r}")
    return float(threshold)


def mtf_limit(table: ContrastTable, *, threshold: float = 0.2) -> int | None:
    """MTF20 resolution limit of a contrast table.

    Parameters
    ----------
    table : ContrastTable
        Contrasts per bar width.
    threshold : float, keyword-only, default 0.2
        Minimum contrast for a width to count as resolved.

    Returns
    -------
    int or None
        The smallest bar width ``w`` (pixels) such that for every width
        ``>= w`` both the horizontal and the vertical contrast are
        ``>= threshold``; None if the widest width already fails.

    Notes
    -----
    Walking from the widest width down, the limit is the last width before
    the first failure: a finer width that happens to pass after a failure
    (spurious resolution, contrast reversal artefacts) does not count.  NaN
    contrasts count as failures.
    """
    if not isinstance(table, ContrastTable):
        raise ValueError(f"table: expected a ContrastTable, got {type(table).__name__}")
    thr = _check_threshold(threshold)
    passing = table.minimum() >= thr  # NaN -> False
    limit = None
    for w, ok in zip(table.widths_px, passing):
        if not ok:
            break
        limit = int(w)
    return limit


def resolution_gain(observed_limit: float | None, recovered_limit: float | None) -> float | None:
    """Resolution gain of a recovery over the observed image.

    Parameters
    ----------
    observed_limit : int or float or None
        Resolution limit (bar width, pixels) of the observed image.
    recovered_limit : int or float or None
        Resolution limit of the recovered image, in the same unit.

    Returns
    -------
    float or None
        ``observed_limit / recovered_limit``; None if either is None.

    Raises
    ------
    ValueError
        If a limit is not a positive number.
    """
    if observed_limit is None or recovered_limit is None:
        return None
    for name, val in (("observed_limit", observed_limit), ("recovered_limit", recovered_limit)):
        if isinstance(val, (bool, np.bool_)) or not isinstance(
            val, (int, float, np.integer, np.floating)
        ) or not np.isfinite(val) or val <= 0:
            raise ValueError(f"{name}: expected a positive number or None, got {val!r}")
    return float(observed_limit) / float(recovered_limit)
