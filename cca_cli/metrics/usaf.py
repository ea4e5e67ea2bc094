"""Resolution reading of a synthetic USAF-1951 chart."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.metrics.contrast import _as_real_image, _box_sum, _check_threshold, _group_contrast
from cca_cli.targets import BarGroup, UsafChart

__all__ = [
    "CRITERIA",
    "UsafElementContrast",
    "UsafReading",
    "three_bar_contrast",
    "usaf_resolution",
    "usaf_gain",
]

CRITERIA = ("three_bar", "area_mean")
"""Resolution criteria of :func:`usaf_resolution`."""

BAR_CENTRE_FRACTION = 0.6
"""Central fraction of each bar's length averaged by the three-bar criterion."""


def _central_box(box, axis: int, trim: int):
    y0, y1, x0, x1 = box
    if axis == 0:  # bars long along x
        return (y0, y1, x0 + trim, x1 - trim)
    return (y0 + trim, y1 - trim, x0, x1)


def _three_bar_contrast(image: np.ndarray, group: BarGroup) -> float:
    bars, gaps = group.bar_boxes, group.gap_boxes
    if len(bars) < 2 or len(gaps) != len(bars) - 1:
        raise ValueError(
            f"group: expected at least two bar boxes and one gap box between each pair, got "
            f"{len(bars)} bar and {len(gaps)} gap boxes"
        )
    y0, y1, x0, x1 = bars[0]
    length = (x1 - x0) if group.axis == 0 else (y1 - y0)
    trim = min(int(np.floor(length * (1.0 - BAR_CENTRE_FRACTION) / 2.0)), (length - 1) // 2)

    def mean(box):
        s, n = _box_sum(image, _central_box(box, group.axis, trim), "intensity")
        return s / n

    bar_means = [mean(b) for b in bars]
    worst = np.inf
    for k, gap in enumerate(gaps):
        peak = min(bar_means[k], bar_means[k + 1])
        dip = mean(gap)
        denom = peak + dip
        c = (peak - dip) / denom if np.isfinite(denom) and denom > 0.0 else 0.0
        worst = min(worst, c)
    return float(worst)


def three_bar_contrast(intensity, group: BarGroup) -> float:
    """Three-bar (every gap dips) contrast of one bar group.

    Parameters
    ----------
    intensity : array_like
        Real 2-D intensity image sampled on the grid of ``group``'s boxes.
    group : BarGroup
        The group whose bars and gaps are compared.

    Returns
    -------
    float
        ``min_k (min(B_k, B_k+1) - G_k) / (min(B_k, B_k+1) + G_k)`` over the
        gaps ``k``; 1 for sharp bars on black, 0 for a uniform image or a gap
        as bright as a neighbouring bar, negative when a gap is brighter.

    Raises
    ------
    ValueError
        If ``intensity`` is not a real 2-D array or a box lies outside it.

    Notes
    -----
    This is how a bar target is read by eye: the intensity is averaged
    along the bars over the central :data:`BAR_CENTRE_FRACTION` (0.6) of
    their length (the ends blur into the background), giving a profile
    across the group; ``B_k`` is its mean over bar ``k`` and ``G_k`` over
    the gap after it.  Every gap must be darker than *both* neighbouring
    bars, so a group whose bars merge into one blob, or of which two bars
    fuse, scores <= 0 even when its bars are brighter than its gaps on
    average (which the area-mean contrast :func:`cca_cli.metrics.bar_contrast`
    still counts as resolved).  Per-gap terms with ``B + G <= 0`` count as 0.
    """
    if not isinstance(group, BarGroup):
        raise ValueError(f"group: expected a BarGroup, got {type(group).__name__}")
    return _three_bar_contrast(_as_real_image("intensity", intensity), group)


@dataclass(frozen=True)
class UsafElementContrast:
    """Measured contrast of one USAF element.

    Parameters
    ----------
    group : int
        USAF group.
    element : int
        USAF element (1-6).
    lp_per_mm : float
        Line pairs per millimetre of the element.
    width_px : float
        Exact bar width in pixels.
    horizontal : float
        Contrast of the horizontal bars (resolution along y), under the
        reading's criterion.
    vertical : float
        Contrast of the vertical bars (resolution along x).
    """

    group: int
    element: int
    lp_per_mm: float
    width_px: float
    horizontal: float
    vertical: float

    def to_dict(self) -> dict:
        """JSON-friendly representation.

        Returns
        -------
        dict
            All fields as plain Python numbers.
        """
        return {
            "group": int(self.group),
            "element": int(self.element),
            "lp_per_mm": float(self.lp_per_mm),
            "width_px": float(self.width_px),
            "horizontal": float(self.horizontal),
            "vertical": float(self.vertical),
        }


@dataclass(frozen=True)
class UsafReading:
    """Finest resolved element of a USAF chart.

    Parameters
    ----------
    group : int or None
        Group of the finest resolved element, None if none is resolved.
    element : int or None
        Element of the finest resolved element.
    lp_per_mm : float or None
        Its spatial frequency in line pairs per millimetre.
    width_px : float or None
        Its exact bar width in pixels.
    threshold : float
        Contrast threshold used.
    contrasts : tuple of UsafElementContrast
        Per-element contrasts, coarsest first.
    criterion : str, default "three_bar"
        Contrast criterion used (one of :data:`CRITERIA`).
    """

    group: int | None
    element: int | None
    lp_per_mm: float | None
    width_px: float | None
    threshold: float
    contrasts: tuple[UsafElementContrast, ...]
    criterion: str = "three_bar"

    @property
    def resolved(self) -> bool:
        """Whether any element is resolved.

        Returns
        -------
        bool
            ``lp_per_mm is not None``.
        """
        return self.lp_per_mm is not None

    def to_dict(self) -> dict:
        """JSON-friendly representation.

        Returns
        -------
        dict
            ``group``, ``element``, ``lp_per_mm``, ``width_px`` (None when
            unresolved), ``threshold``, ``criterion`` and ``contrasts``
            (list of dicts).
        """
        return {
            "group": None if self.group is None else int(self.group),
            "element": None if self.element is None else int(self.element),
            "lp_per_mm": None if self.lp_per_mm is None else float(self.lp_per_mm),
            "width_px": None if self.width_px is None else float(self.width_px),
            "threshold": float(self.threshold),
            "criterion": str(self.criterion),
            "contrasts": [c.to_dict() for c in self.contrasts],
        }


def usaf_resolution(
    intensity, chart: UsafChart, *, threshold: float = 0.2, criterion: str = "three_bar"
) -> UsafReading:
    """Read the finest resolved element of a USAF chart image.

    Parameters
    ----------
    intensity : array_like
        Real 2-D intensity image with the chart's shape.
    chart : UsafChart
        The chart that was imaged.
    threshold : float, keyword-only, default 0.2
        Minimum contrast for an element to count as resolved.
    criterion : {"three_bar", "area_mean"}, keyword-only, default "three_bar"
        ``"three_bar"``: :func:`three_bar_contrast`, every gap darker than
        both neighbouring bars (the usual visual reading of a USAF target).
        ``"area_mean"``: :func:`cca_cli.metrics.bar_contrast`, mean over all
        bars vs. mean over all gaps (the bar-chart MTF20 contrast).

    Returns
    -------
    UsafReading
        Finest resolved element and every element's contrasts.

    Raises
    ------
    ValueError
        If ``intensity`` is not real 2-D with the chart's shape,
        ``threshold`` is not a finite number or ``criterion`` is unknown.

    Notes
    -----
    With the default criterion an element is resolved when, in both
    orientations, each of its two gaps is darker than both adjacent bars by
    a Michelson contrast of at least ``threshold``:
    ``(min(B_k, B_k+1) - G_k) / (min(B_k, B_k+1) + G_k) >= 0.2`` means
    the gap is at most 2/3 of the dimmer neighbouring bar (bars and gaps
    averaged along the central 60 % of the bar length).  The default 0.2
    is the same 20 % contrast as the MTF20 limit of the bar chart.
    Elements are walked from coarse to fine (ascending lp/mm); the reading
    is the last element before the first one that fails (every coarser
    element must be resolved too).  The image should sample the finest
    bars with several pixels (read a recovered field on the chart's grid).
    """
    if not isinstance(chart, UsafChart):
        raise ValueError(f"chart: expected a UsafChart, got {type(chart).__name__}")
    thr = _check_threshold(threshold)
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: expected one of {CRITERIA}, got {criterion!r}")
    measure = _three_bar_contrast if criterion == "three_bar" else _group_contrast
    image = _as_real_image("intensity", intensity)
    if image.shape != chart.image.shape:
        raise ValueError(
            f"intensity: expected the chart's shape {chart.image.shape}, got shape {image.shape}"
        )
    contrasts = []
    for el in sorted(chart.elements, key=lambda e: e.lp_per_mm):
        contrasts.append(
            UsafElementContrast(
                group=el.group,
                element=el.element,
                lp_per_mm=el.lp_per_mm,
                width_px=el.width_px,
                horizontal=measure(image, el.horizontal),
                vertical=measure(image, el.vertical),
            )
        )
    best = None
    for c in contrasts:
        if not (c.horizontal >= thr and c.vertical >= thr):  # NaN fails
            break
        best = c
    return UsafReading(
        group=None if best is None else best.group,
        element=None if best is None else best.element,
        lp_per_mm=None if best is None else best.lp_per_mm,
        width_px=None if best is None else best.width_px,
        threshold=thr,
        contrasts=tuple(contrasts),
        criterion=criterion,
    )


def usaf_gain(observed: UsafReading, recovered: UsafReading) -> float | None:
    """Resolution gain between two USAF readings.

    Parameters
    ----------
    observed : UsafReading
        Reading of the observed (e.g. single-camera) image.
    recovered : UsafReading
        Reading of the recovered (synthetic-aperture) image.

    Returns
    -------
    float or None
        ``recovered.lp_per_mm / observed.lp_per_mm``; None if either
        reading resolved nothing.
    """
    for name, r in (("observed", observed), ("recovered", recovered)):
        if not isinstance(r, UsafReading):
            raise ValueError(f"{name}: expected a UsafReading, got {type(r).__name__}")
    if observed.lp_per_mm is None or recovered.lp_per_mm is None:
        return None
    return float(np.float64(recovered.lp_per_mm) / np.float64(observed.lp_per_mm))
