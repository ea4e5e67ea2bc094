"""Resolution reading of a synthetic USAF-1951 chart."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.metrics.contrast import _as_real_image, _check_threshold, _group_contrast
from cca_cli.targets import UsafChart

__all__ = ["UsafElementContrast", "UsafReading", "usaf_resolution", "usaf_gain"]


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
        Contrast of the horizontal bars (resolution along y).
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
    """

    group: int | None
    element: int | None
    lp_per_mm: float | None
    width_px: float | None
    threshold: float
    contrasts: tuple[UsafElementContrast, ...]

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
            unresolved), ``threshold`` and ``contrasts`` (list of dicts).
        """
        return {
            "group": None if self.group is None else int(self.group),
            "element": None if self.element is None else int(self.element),
            "lp_per_mm": None if self.lp_per_mm is None else float(self.lp_per_mm),
            "width_px": None if self.width_px is None else float(self.width_px),
            "threshold": float(self.threshold),
            "contrasts": [c.to_dict() for c in self.contrasts],
        }


def usaf_resolution(intensity, chart: UsafChart, *, threshold: float = 0.2) -> UsafReading:
    """Read the finest resolved element of a USAF chart image.

    Parameters
    ----------
    intensity : array_like
        Real 2-D intensity image with the chart's shape.
    chart : UsafChart
        The chart that was imaged.
    threshold : float, keyword-only, default 0.2
        Minimum contrast for an element to count as resolved.

    Returns
    -------
    UsafReading
        Finest resolved element and every element's contrasts.

    Raises
    ------
    ValueError
        If ``intensity`` is not real 2-D with the chart's shape, or
        ``threshold`` is not a finite number.

    Notes
    -----
    Contrast per orientation is ``C = (w - b) / (w + b)`` (mean intensity
    over the bars vs. over the gaps, :func:`cca_cli.metrics.bar_contrast`).
    Elements are walked from coarse to fine (ascending lp/mm); the reading
    is the last element before the first one whose horizontal or vertical
    contrast is below ``threshold`` (MTF20 rule: every coarser element must
    be resolved too).
    """
    if not isinstance(chart, UsafChart):
        raise ValueError(f"chart: expected a UsafChart, got {type(chart).__name__}")
    thr = _check_threshold(threshold)
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
                horizontal=_group_contrast(image, el.horizontal),
                vertical=_group_contrast(image, el.vertical),
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
