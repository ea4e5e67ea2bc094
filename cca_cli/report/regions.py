"""Where the report zooms in: the finest features of a chart, or the most detailed part of a real scene.

A :class:`Region` is given as fractions of the field along each axis (``y``
of its height, ``x`` of its width), so the same region can be cut from images
on different grids (truth, observed centre image, recovery), square or not.
The regions chosen here are square in pixels (and so at the object): on an
``H x W`` field a region ``s`` pixels on a side spans ``s/H`` of the height
and ``s/W`` of the width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.optics import fft

__all__ = ["Region", "bar_region", "usaf_region", "detail_region"]

#: A zoom region wider than this share of the field is cut down to the finest group alone.
_MAX_SHARE = 0.3
#: Detail is scored relative to the local brightness, which is floored at this share of the 99th percentile.
_BRIGHTNESS_FLOOR = 0.1


def _shape(size) -> tuple[int, int]:
    """``(h, w)`` of a grid given as its side ``n`` (square) or as ``(h, w)``."""
    if np.ndim(size) == 0:
        return int(size), int(size)
    h, w = (int(v) for v in tuple(size)[-2:])
    return h, w


@dataclass(frozen=True)
class Region:
    """A rectangular part of the field.

    Attributes
    ----------
    fractions : tuple of float
        ``(y0, y1, x0, x1)``: rows as fractions of the field's height, columns
        as fractions of its width (0…1, half-open).
    label : str
        What the region shows (for figure titles).
    """

    fractions: tuple[float, float, float, float]
    label: str

    def pixels(self, size) -> tuple[int, int, int, int]:
        """The region as a half-open pixel box ``(y0, y1, x0, x1)`` on a grid of ``size`` (``n`` or ``(h, w)``).

        Examples
        --------
        >>> Region((0.25, 0.75, 0.5, 0.75), "r").pixels((80, 160))
        (20, 60, 80, 120)
        """
        rows, cols = _shape(size)
        y0, y1, x0, x1 = self.fractions
        height = min(max(1, int(round((y1 - y0) * rows))), rows)
        width = min(max(1, int(round((x1 - x0) * cols))), cols)
        top = min(max(int(round(y0 * rows)), 0), rows - height)
        left = min(max(int(round(x0 * cols)), 0), cols - width)
        return top, top + height, left, left + width

    def crop(self, image: np.ndarray) -> np.ndarray:
        """The region of an image (on any grid, square or not)."""
        y0, y1, x0, x1 = self.pixels(image.shape[-2:])
        return image[..., y0:y1, x0:x1]

    def to_dict(self) -> dict:
        """JSON-ready form: ``fractions`` and ``label``."""
        return {"fractions": [round(float(v), 5) for v in self.fractions], "label": self.label}


def _square(box, size, pad: float, minimum: float) -> tuple[float, float, float, float]:
    """A padded pixel box made square (in pixels) and kept inside a grid of ``size``, as fractions per axis."""
    rows, cols = _shape(size)
    y0, y1, x0, x1 = (float(v) for v in box)
    side = max(y1 - y0, x1 - x0) + 2 * pad
    side = min(max(side, minimum), rows, cols)
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    top = min(max(cy - side / 2, 0.0), rows - side)
    left = min(max(cx - side / 2, 0.0), cols - side)
    return (top / rows, (top + side) / rows, left / cols, (left + side) / cols)


def _union(boxes) -> tuple[int, int, int, int]:
    boxes = np.asarray(boxes)
    return int(boxes[:, 0].min()), int(boxes[:, 1].max()), int(boxes[:, 2].min()), int(boxes[:, 3].max())


def bar_region(bars, finest_resolved_px: int | None, size: int) -> Region | None:
    """The bar groups at the recovery's resolution limit, and the next finer ones when they fit.

    Parameters
    ----------
    bars : sequence of BarGroup
        Chart layout on a ``size`` grid.
    finest_resolved_px : int or None
        MTF20 limit of the recovery (bar width, px); None zooms on the coarsest groups.
    size : int
        Side of the grid ``bars`` are given on.

    Returns
    -------
    Region or None
        None without bars.
    """
    if not bars:
        return None
    widths = sorted({g.width_px for g in bars}, reverse=True)
    width = finest_resolved_px if finest_resolved_px in widths else widths[0]
    finer = [w for w in widths if w < width]
    chosen = [g for g in bars if g.width_px == width]
    label = f"{width} px bars (finest resolved)" if finest_resolved_px in widths else f"{width} px bars"
    if finer:
        with_next = chosen + [g for g in bars if g.width_px == finer[0]]
        y0, y1, x0, x1 = _union([g.box for g in with_next])
        if max(y1 - y0, x1 - x0) <= _MAX_SHARE * size:
            chosen, label = with_next, f"{label} and {finer[0]} px bars"
    box = _union([g.box for g in chosen])
    if max(box[1] - box[0], box[3] - box[2]) > _MAX_SHARE * size:
        box = chosen[0].box
    return Region(_square(box, size, pad=2 * width + 4, minimum=24), label)


def usaf_region(chart, reading: dict | None) -> Region | None:
    """The finest resolved USAF element and the next finer one.

    Parameters
    ----------
    chart : UsafChart
        Layout (boxes on ``chart.size``).
    reading : dict or None
        The recovery's reading (``group``, ``element``); None or unresolved
        zooms on the coarsest element.
    """
    elements = list(chart.elements)
    if not elements:
        return None
    index = 0
    resolved = reading is not None and reading.get("group") is not None
    if resolved:
        index = next((i for i, e in enumerate(elements)
                      if (e.group, e.element) == (reading["group"], reading["element"])), 0)
    chosen = [elements[index]]
    label = f"USAF group {chosen[0].group} element {chosen[0].element}" + (" (finest resolved)" if resolved else "")
    if index + 1 < len(elements):
        nxt = elements[index + 1]
        boxes = [b for e in chosen + [nxt] for b in (e.horizontal.box, e.vertical.box)]
        y0, y1, x0, x1 = _union(boxes)
        if max(y1 - y0, x1 - x0) <= _MAX_SHARE * chart.size:
            chosen.append(nxt)
            label += f" and G{nxt.group} E{nxt.element}"
    box = _union([b for e in chosen for b in (e.horizontal.box, e.vertical.box)])
    width = chosen[0].drawn_width_px
    return Region(_square(box, chart.size, pad=2 * width + 4, minimum=24), label)


def detail_region(intensity: np.ndarray, cutoff_px: float, *, share: float = 0.25) -> Region:
    """The square where the recovery holds the most detail beyond one camera's reach.

    The intensity is high-pass filtered at ``cutoff_px`` (what a single camera
    cannot record), and of the square windows whose side is ``share`` of the
    field's longer side (at most its shorter side: a narrow strip is zoomed
    across its whole height) the one holding the most filtered energy
    relative to its brightness is chosen, kept a sixteenth of the field off
    its border where it can be (recoveries carry edge artefacts there). The
    energy is divided by the window's mean intensity (floored at a tenth of
    the field's 99th percentile): a recovery's amplitude error puts intensity
    noise whose energy grows with the brightness on large bright areas, while
    structure's energy grows with its square, so fine structure wins over
    bright noise.

    Parameters
    ----------
    intensity : ndarray, float, (H, W)
    cutoff_px : float
        Radius of the single camera's intensity band in cycles per field
        width (spectrum pixels along x; along y a spectrum pixel is ``W/H``
        of them).
    share : float
        Window side as a share of the field's longer side.

    Returns
    -------
    Region
        Square in pixels.
    """
    from scipy import ndimage

    image = np.asarray(intensity, np.float32)
    rows, cols = image.shape[-2:]
    spectrum = fft.fft2c(image - image.mean())
    fy = (np.arange(rows)[:, None] - rows // 2) * (cols / rows)   # cycles per field width on both axes
    fx = np.arange(cols)[None, :] - cols // 2
    spectrum[np.hypot(fy, fx) < cutoff_px] = 0
    energy = np.abs(fft.ifft2c(spectrum)) ** 2
    side = min(max(8, int(round(share * max(rows, cols)))), rows, cols)
    mean = ndimage.uniform_filter(image.astype(np.float64), size=side, mode="constant")
    floor = _BRIGHTNESS_FLOOR * abs(float(np.percentile(image, 99))) or 1.0
    score = ndimage.uniform_filter(energy.astype(np.float64), size=side, mode="constant") / (np.abs(mean) + floor)
    inner = np.full_like(score, -np.inf)
    margins = []   # of the window's centre from the border
    for n in (rows, cols):
        margin = side // 2 + n // 16
        margins.append(margin if n - 2 * margin >= 1 else (side // 2 if n - 2 * (side // 2) >= 1 else 0))
    (my, mx) = margins
    inner[my:rows - my, mx:cols - mx] = score[my:rows - my, mx:cols - mx]
    cy, cx = np.unravel_index(int(np.argmax(inner)), inner.shape)
    box = (cy - side // 2, cy - side // 2 + side, cx - side // 2, cx - side // 2 + side)
    return Region(_square(box, (rows, cols), pad=0, minimum=side), "most detail beyond the single-camera band")
