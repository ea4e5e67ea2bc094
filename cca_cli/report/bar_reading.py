"""Three-bar readings of a recorded USAF-1951 target at boxes the user gives.

A recorded target's bars are not where a synthetic chart puts them, so the
user names the elements and boxes them in the captured frames (``report.bar_elements``,
in the frames' own pixel coordinates, rows then columns). Each box is read on
the recovered amplitude and on the observed centre capture's amplitude (both
Fourier-interpolated onto a grid fine enough for the finest element) with
:func:`cca_cli.metrics.bars.three_bar_profile_contrast`.
"""

from __future__ import annotations

import math

import numpy as np

from cca_cli.metrics.bars import three_bar_profile_contrast, usaf_period_m
from cca_cli.optics import fft

__all__ = ["FrameToRecovery", "read_elements", "finest_resolved", "offset_to_observed"]


class FrameToRecovery:
    """Where a captured frame's pixel lands on the recovered image.

    Both grids are centred on the optical axis: frame pixel ``i`` of a frame of
    ``frame_size`` pixels, placed at ``offset`` on a square sensor grid of
    ``sensor_size`` pixels (padding; 0 without), sits at recovery position
    ``M/2 + (offset + i − S/2)·M/S − origin`` of a recovered image cut at
    ``origin`` from the ``M``-pixel recovery grid.
    """

    def __init__(self, sensor_size: int, hires_size: int, offset_yx=(0, 0), origin_yx=(0, 0)):
        self.scale = hires_size / sensor_size
        self.sensor_size, self.hires_size = int(sensor_size), int(hires_size)
        self.offset_yx, self.origin_yx = tuple(offset_yx), tuple(origin_yx)

    def __call__(self, value: float, axis: int) -> float:
        return (self.hires_size // 2 + (self.offset_yx[axis] + value - self.sensor_size // 2) * self.scale
                - self.origin_yx[axis])

    def box(self, box) -> tuple[float, float, float, float]:
        """``(y0, y1, x0, x1)`` of a frame box on the recovered image."""
        y0, y1, x0, x1 = box
        return self(y0, 0), self(y1, 0), self(x0, 1), self(x1, 1)


def read_elements(recovered_object: np.ndarray, observed: np.ndarray, elements, frame_pixel_m: float,
                  to_recovery: FrameToRecovery, *, samples_per_period: float = 8.0,
                  offset_yx: tuple[float, float] = (0.0, 0.0)) -> dict:
    """Michelson contrast of each element on the recovered and the observed amplitude.

    Both amplitudes are Fourier-interpolated so that the finest element's period spans at
    least ``samples_per_period`` pixels (at most 8× finer): a profile sampled near two
    pixels per period cannot show three minima reliably.

    Parameters
    ----------
    recovered_object : ndarray, complex, (H, W)
        Recovered object (complex field).
    observed : ndarray, float, (h, w)
        Centre capture's intensity (the frames' grid).
    elements : sequence of mapping
        ``{"element": "G9E1", "profile": "row" | "col", "box_px": [y0, y1, x0, x1]}``
        with boxes in frame pixels.
    frame_pixel_m : float
        Size of one frame pixel at the object (m).
    to_recovery : FrameToRecovery
        Frame pixel → recovered pixel.
    samples_per_period : float
        Pixels per bar period the reading aims for.
    offset_yx : tuple of float
        Shift of the recovered image against the frames (recovered pixels,
        :func:`offset_to_observed`); the boxes on the recovery are moved by it.

    Returns
    -------
    dict
        ``"G9E1 col"`` → ``{"lp_per_mm", "period_px", "observed", "recovered"}``; a contrast is
        None where no three bars at the element's period are found (not resolved). ``period_px``
        is in recovered pixels.
    """
    elements = list(elements)
    if not elements:
        return {}
    names = [_parse_name(spec["element"]) for spec in elements]
    periods = [usaf_period_m(g, e) / frame_pixel_m * to_recovery.scale for g, e in names]
    factor = int(min(8, max(1, math.ceil(samples_per_period / min(periods)))))
    shape = tuple(n * factor for n in recovered_object.shape[-2:])
    recovered_amplitude = np.abs(fft.fourier_interpolate(recovered_object, shape))
    observed_amplitude = np.sqrt(np.clip(fft.fourier_interpolate(observed, shape).real, 0, None))
    small = recovered_object.shape[-2:]
    out = {}
    for spec, (group, element), period in zip(elements, names, periods):
        axis = 0 if spec["profile"] == "row" else 1
        y0, y1, x0, x1 = to_recovery.box(spec["box_px"])
        reading = {"lp_per_mm": round(2.0 ** (group + (element - 1) / 6.0), 1), "period_px": round(period, 3)}
        for name, image in (("observed", observed_amplitude), ("recovered", recovered_amplitude)):
            dy, dx = offset_yx if name == "recovered" else (0.0, 0.0)
            box = (_finer(y0 + dy, small[0], factor), _finer(y1 + dy, small[0], factor),
                   _finer(x0 + dx, small[1], factor), _finer(x1 + dx, small[1], factor))
            try:
                value = three_bar_profile_contrast(image, box, period * factor, axis)
            except ValueError:  # the box leaves the recovered region
                value = math.nan
            reading[name] = None if not math.isfinite(value) else round(float(value), 4)
        out[f"{spec['element']} {spec['profile']}"] = reading
    return out


def finest_resolved(readings: dict, image: str = "recovered", threshold: float = 0.2) -> str | None:
    """The finest element whose every listed profile reads a contrast ≥ ``threshold`` on ``image``.

    Returns None when no element does.
    """
    elements: dict[str, tuple[float, bool]] = {}
    for key, reading in readings.items():
        name = key.split()[0]
        value = reading[image]
        resolved = value is not None and value >= threshold and elements.get(name, (0.0, True))[1]
        elements[name] = (reading["lp_per_mm"], resolved)
    resolved = [(lp, name) for name, (lp, ok) in elements.items() if ok]
    return max(resolved)[1] if resolved else None


def offset_to_observed(recovered: np.ndarray, observed: np.ndarray, cutoff_px: float) -> tuple[float, float]:
    """Where the observed image's content sits in the recovered image, ``(dy, dx)`` recovered pixels.

    A recovered pupil may carry a linear phase whose counterpart is a shift of the object (the
    two are interchangeable in the data); boxes drawn on the captured frames then miss the bars
    on the recovery by that shift. Both intensities are compared below ``cutoff_px`` (spectrum
    pixels of the recovered grid: what the observed image holds) by phase correlation, refined
    to a fraction of a pixel with a parabola through the peak.

    Parameters
    ----------
    recovered, observed : ndarray, float, (H, W)
        The recovered intensity and the observed one on the same grid.
    cutoff_px : float
        Radius of the comparison band (spectrum pixels).

    Returns
    -------
    tuple of float
        Add to observed (frame-based) positions to land on the recovered image.
    """
    h, w = recovered.shape[-2:]
    fy = np.fft.fftfreq(h)[:, None] * h
    fx = np.fft.fftfreq(w)[None, :] * w
    band = np.hypot(fy, fx) <= cutoff_px
    a = np.fft.fft2(recovered - recovered.mean()) * band
    b = np.fft.fft2(observed - observed.mean()) * band
    cross = a * np.conj(b)
    surface = np.fft.ifft2(cross / np.maximum(np.abs(cross), 1e-30 * np.abs(cross).max())).real
    peak = np.unravel_index(int(np.argmax(surface)), surface.shape)
    offset = []
    for axis, size in ((0, h), (1, w)):
        index = list(peak)
        values = []
        for step in (-1, 0, 1):
            index[axis] = (peak[axis] + step) % size
            values.append(surface[tuple(index)])
        left, centre, right = values
        curvature = left - 2 * centre + right
        fraction = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
        offset.append(float((peak[axis] + size // 2) % size - size // 2 + fraction))
    return offset[0], offset[1]


def _finer(position: float, size: int, factor: int) -> float:
    """A pixel position on a grid ``factor`` times finer (both centred at ``size // 2``)."""
    return (size * factor) // 2 + (position - size // 2) * factor


def _parse_name(name: str) -> tuple[int, int]:
    text = name.strip().upper()
    group, _, element = text[1:].partition("E")
    return int(group), int(element)
