"""Build the simulated object (complex field) and its known layout from the scene section."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.config.model import SceneSection
from cca_cli.errors import ConfigError
from cca_cli.optics import fft
from cca_cli.targets import BarGroup, chart_groups_for_grid, resolution_chart

__all__ = ["Scene", "build_scene", "bars_to_table", "table_to_bars"]


@dataclass(frozen=True)
class Scene:
    """A simulated object on the simulation grid.

    Attributes
    ----------
    field : ndarray, complex64, (M, M)
        Object field (amplitude × exp(i·phase)), amplitude in √irradiance.
    bars : tuple of BarGroup
        Bar-group layout on the M grid (empty for non-chart scenes); ``width_px``
        stays in scene pixels.
    """

    field: np.ndarray
    bars: tuple[BarGroup, ...] = ()


def _resample_amplitude(image: np.ndarray, size: int) -> np.ndarray:
    n = image.shape[0]
    if size == n:
        return image.astype(np.float32)
    if size % n == 0:
        k = size // n
        return np.kron(image, np.ones((k, k), np.float32)).astype(np.float32)
    return np.clip(fft.fourier_resample(image[None], size)[0], 0, None)


def build_scene(section: SceneSection, grid_size: int) -> Scene:
    """The object of ``section`` sampled on a ``grid_size`` x ``grid_size`` grid.

    Raises
    ------
    ConfigError
        If the chart does not fit in ``scene.size_px`` or an image file cannot be read.
    """
    if section.kind == "resolution_chart":
        widths = tuple(section.widths_px) if section.widths_px else None
        try:
            chart = resolution_chart(section.size_px, widths=widths) if widths else resolution_chart(section.size_px)
        except ValueError as exc:
            raise ConfigError(f"scene: {exc}") from None
        amplitude = _resample_amplitude(np.asarray(chart.image, np.float32), grid_size)
        bars = chart.groups if grid_size == chart.size else chart_groups_for_grid(chart, grid_size)
        return Scene(field=amplitude.astype(np.complex64), bars=tuple(bars))
    if section.kind == "usaf":
        from cca_cli.targets import usaf1951_chart

        pitch = section.field_width_m / section.size_px
        try:
            chart = usaf1951_chart(section.size_px, pixel_pitch_m=pitch)
        except ValueError as exc:
            raise ConfigError(f"scene: {exc}") from None
        amplitude = _resample_amplitude(np.asarray(chart.image, np.float32), grid_size)
        return Scene(field=amplitude.astype(np.complex64))
    from cca_cli.io.images import read_image

    amplitude = _square_unit(read_image(section.image_path).pixels, section.size_px)
    phase = np.zeros_like(amplitude)
    if section.phase_path is not None:
        phase = _square_unit(read_image(section.phase_path).pixels, section.size_px) * section.phase_max_rad
    field = _resample_amplitude(amplitude, grid_size) * np.exp(1j * _resample_amplitude(phase, grid_size))
    return Scene(field=field.astype(np.complex64))


def _square_unit(pixels: np.ndarray, size: int) -> np.ndarray:
    """Centre-crop to a square, scale to [0, 1], resample to ``size``."""
    pixels = np.asarray(pixels, np.float32)
    h, w = pixels.shape
    n = min(h, w)
    pixels = pixels[(h - n) // 2:(h - n) // 2 + n, (w - n) // 2:(w - n) // 2 + n]
    peak = float(pixels.max())
    pixels = pixels / peak if peak > 0 else pixels
    from scipy import ndimage

    if n != size:
        pixels = ndimage.zoom(pixels, size / n, order=1, grid_mode=True, mode="nearest")[:size, :size]
    return np.clip(pixels, 0, 1).astype(np.float32)


_ORIENT = {"horizontal": 0, "vertical": 1}


def bars_to_table(bars: tuple[BarGroup, ...]) -> np.ndarray:
    """Bar layout → int32 rows ``group, width_px, orientation, role, y0, y1, x0, x1``.

    Roles: 0 bar, 1 gap, 2 the whole group box.
    """
    rows = []
    for g, group in enumerate(bars):
        head = [g, group.width_px, _ORIENT[group.orientation]]
        rows.append(head + [2, *group.box])
        rows += [head + [0, *box] for box in group.bar_boxes]
        rows += [head + [1, *box] for box in group.gap_boxes]
    return np.asarray(rows, dtype=np.int32).reshape(-1, 8)


def table_to_bars(table: np.ndarray) -> tuple[BarGroup, ...]:
    """Inverse of :func:`bars_to_table`."""
    table = np.asarray(table)
    names = {v: k for k, v in _ORIENT.items()}
    groups = []
    for g in np.unique(table[:, 0]) if table.size else []:
        rows = table[table[:, 0] == g]
        box = tuple(int(v) for v in rows[rows[:, 3] == 2][0, 4:])
        groups.append(BarGroup(
            width_px=int(rows[0, 1]),
            orientation=names[int(rows[0, 2])],
            box=box,
            bar_boxes=tuple(tuple(int(v) for v in r[4:]) for r in rows[rows[:, 3] == 0]),
            gap_boxes=tuple(tuple(int(v) for v in r[4:]) for r in rows[rows[:, 3] == 1]),
        ))
    return tuple(groups)
