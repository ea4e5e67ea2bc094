"""Build the simulated object (complex field) and its known layout from the scene section."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cca_cli.config.model import SceneSection
from cca_cli.errors import ConfigError
from cca_cli.optics import fft
from cca_cli.targets import BarGroup, chart_groups_for_grid, resolution_chart

__all__ = ["Scene", "build_scene", "check_scene", "bars_to_table", "table_to_bars", "usaf_to_table", "table_to_usaf",
           "surface_phase"]


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
    usaf: tuple = ()  # UsafElement layout on the scene's own grid (kind=usaf)
    usaf_size: int = 0  # side of that grid (scene.size_px)


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

    With ``scene.surface_phase: random`` the field is multiplied by
    ``exp(i φ)`` of a random surface phase (:func:`surface_phase`), which
    makes the object diffuse: its images show speckle.

    Raises
    ------
    ConfigError
        If the chart does not fit in ``scene.size_px`` or an image file cannot be read.
    """
    scene = _base_scene(section, grid_size)
    if section.surface_phase == "random":
        phase = surface_phase(grid_size, roughness_rad=section.surface_roughness_rad,
                              correlation_px=section.surface_correlation_px, seed=section.surface_seed)
        scene = replace(scene, field=(scene.field * np.exp(1j * phase)).astype(np.complex64))
    return scene


def surface_phase(size: int, *, roughness_rad: float, correlation_px: float = 0.0, seed: int = 0) -> np.ndarray:
    """Random phase of a rough surface: Gaussian, RMS ``roughness_rad``, Gaussian-correlated over ``correlation_px``.

    An RMS well above π (or any RMS with no correlation and ≥ 2.5 rad)
    gives fully developed speckle; a correlation length of a few pixels
    confines the scattered light to a band that a large synthetic aperture
    captures, so speckle falls as the aperture grows.

    Returns
    -------
    ndarray, float32, (size, size)
    """
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((size, size))
    if correlation_px > 0:
        from scipy import ndimage

        noise = ndimage.gaussian_filter(noise, correlation_px, mode="wrap")
    std = float(noise.std())
    return (noise / std * roughness_rad if std > 0 else noise).astype(np.float32)


def check_scene(section: SceneSection) -> None:
    """Raise the :class:`~cca_cli.errors.ConfigError` :func:`build_scene` would for a chart that does not fit.

    Cheap (the chart is laid out at ``scene.size_px``, nothing is resampled), so a sweep checks every
    point before any runs. Other kinds of scene are checked when they are built.
    """
    if section.kind == "resolution_chart":
        widths = tuple(section.widths_px) if section.widths_px else None
        _fits(("resolution_chart", section.size_px, widths), lambda: resolution_chart(section.size_px, widths=widths)
              if widths else resolution_chart(section.size_px), size="scene.size_px", widths="scene.widths_px")
    elif section.kind == "usaf":
        from cca_cli.targets import usaf1951_chart

        pitch = section.field_width_m / section.size_px
        groups = tuple(section.usaf_groups) if section.usaf_groups else (-2, -1, 0, 1, 2, 3)
        _fits(("usaf", section.size_px, pitch, groups),
              lambda: usaf1951_chart(section.size_px, pixel_pitch_m=pitch, groups=groups), size="scene.size_px",
              groups="scene.usaf_groups", pixel_pitch_m="the pixel (scene.field_width_m / scene.size_px)")


_CHECKED: dict[tuple, str | None] = {}   # what each chart layout checked gave (None: it fits)


def _fits(key: tuple, make, **names: str) -> None:
    if key not in _CHECKED:
        try:
            make()
            _CHECKED[key] = None
        except ValueError as exc:
            _CHECKED[key] = _scene_message(exc, **names)
    if _CHECKED[key] is not None:
        raise ConfigError(_CHECKED[key])


def _base_scene(section: SceneSection, grid_size: int) -> Scene:
    """The object of ``section`` before any surface roughness.

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
            raise ConfigError(_scene_message(exc, size="scene.size_px", widths="scene.widths_px")) from None
        amplitude = _resample_amplitude(np.asarray(chart.image, np.float32), grid_size)
        bars = chart.groups if grid_size == chart.size else chart_groups_for_grid(chart, grid_size)
        return Scene(field=amplitude.astype(np.complex64), bars=tuple(bars))
    if section.kind == "usaf":
        from cca_cli.targets import usaf1951_chart

        pitch = section.field_width_m / section.size_px
        try:
            groups = tuple(section.usaf_groups) if section.usaf_groups else (-2, -1, 0, 1, 2, 3)
            chart = usaf1951_chart(section.size_px, pixel_pitch_m=pitch, groups=groups)
        except ValueError as exc:
            raise ConfigError(_scene_message(exc, size="scene.size_px", groups="scene.usaf_groups",
                                             pixel_pitch_m="the pixel (scene.field_width_m / scene.size_px)")) from None
        amplitude = _resample_amplitude(np.asarray(chart.image, np.float32), grid_size)
        return Scene(field=amplitude.astype(np.complex64), usaf=tuple(chart.elements), usaf_size=chart.size)
    if section.kind in ("fingerprint", "face", "label"):
        return _synthetic_scene(section, grid_size)
    if section.kind == "natural":
        from cca_cli.targets.natural import natural_portrait

        amplitude = _resample_amplitude(natural_portrait(section.size_px), grid_size)
        return Scene(field=np.clip(amplitude, 0, None).astype(np.complex64))
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


def _synthetic_scene(section: SceneSection, grid_size: int) -> Scene:
    """fingerprint / face / label, with an optional bar-chart inset in the lower-right corner."""
    from cca_cli.targets import BarChart
    from cca_cli.targets.biometric import face, fingerprint, label

    n = section.size_px
    if section.kind == "fingerprint":
        image = fingerprint(n, period_px=section.ridge_period_m / (section.field_width_m / n))
    elif section.kind == "face":
        image = face(n)
    else:
        image = label(n)
    image = np.array(image, np.float32)
    bars: tuple[BarGroup, ...] = ()
    if section.chart_inset_px:
        inset = _inset_chart(section.chart_inset_px, section.widths_px)
        k = inset.size
        if k > n:
            raise ConfigError(f"scene.chart_inset_px: {k} px does not fit in scene.size_px {n}")
        image[n - k:, n - k:] = inset.image
        shifted = tuple(
            BarGroup(width_px=g.width_px, orientation=g.orientation, box=_shift(g.box, n - k),
                     bar_boxes=tuple(_shift(b, n - k) for b in g.bar_boxes),
                     gap_boxes=tuple(_shift(b, n - k) for b in g.gap_boxes))
            for g in inset.groups)
        full = BarChart(image=image, groups=shifted)
        bars = shifted if grid_size == n else chart_groups_for_grid(full, grid_size)
    amplitude = np.clip(_resample_amplitude(image, grid_size), 0, None)
    return Scene(field=amplitude.astype(np.complex64), bars=tuple(bars))


def _scene_message(exc: ValueError, **keys: str) -> str:
    """A chart maker's message in the config's words: its argument names (``size``) become the keys
    (``scene.size_px``) that set them."""
    import re

    text = str(exc)
    for name, key in keys.items():
        text = re.sub(rf"\b{name}\b", key, text)
    return text if text.startswith("scene") else f"scene: {text}"


def _shift(box, offset: int):
    y0, y1, x0, x1 = box
    return (y0 + offset, y1 + offset, x0 + offset, x1 + offset)


def _inset_chart(size: int, widths):
    """The bar chart of the inset: the given widths, or the widest-first default widths that fit."""
    from cca_cli.targets import DEFAULT_WIDTHS

    if widths:
        try:
            return resolution_chart(size, widths=tuple(widths))
        except ValueError as exc:
            raise ConfigError(f"scene.widths_px: {exc}") from None
    candidates = list(DEFAULT_WIDTHS)
    while candidates:
        try:
            return resolution_chart(size, widths=tuple(candidates))
        except ValueError:
            candidates.pop(0)
    raise ConfigError(f"scene.chart_inset_px: no bar chart fits in {size} px; make the inset larger")


def usaf_to_table(elements, size: int) -> np.ndarray:
    """USAF layout → float64 rows ``group, element, lp_per_mm, width_px, orientation, role, y0, y1, x0, x1, size``.

    Orientation 0 horizontal, 1 vertical; role 0 bar, 1 gap, 2 the group box;
    boxes on the ``size`` x ``size`` grid the chart was drawn on.
    """
    rows = []
    for el in elements:
        for group in (el.horizontal, el.vertical):
            head = [el.group, el.element, el.lp_per_mm, el.width_px, _ORIENT[group.orientation]]
            rows.append(head + [2, *group.box, size])
            rows += [head + [0, *box, size] for box in group.bar_boxes]
            rows += [head + [1, *box, size] for box in group.gap_boxes]
    return np.asarray(rows, dtype=np.float64).reshape(-1, 11)


def table_to_usaf(table: np.ndarray, *, pixel_pitch_m: float = float("nan")):
    """Inverse of :func:`usaf_to_table`: a :class:`~cca_cli.targets.UsafChart` whose image is blank.

    The chart serves :func:`cca_cli.metrics.usaf_resolution` on images
    resampled to its grid (``chart.size``, the scene's own pixels).
    """
    from cca_cli.targets import UsafChart, UsafElement

    table = np.asarray(table, np.float64)
    names = {v: k for k, v in _ORIENT.items()}
    elements = []
    keys = sorted({(int(r[0]), int(r[1])) for r in table}, key=lambda ge: ge[0] + (ge[1] - 1) / 6)
    for g, e in keys:
        rows = table[(table[:, 0] == g) & (table[:, 1] == e)]
        groups = {}
        for o in (0, 1):
            sub = rows[rows[:, 4] == o]
            box = tuple(int(v) for v in sub[sub[:, 5] == 2][0, 6:10])
            groups[names[o]] = BarGroup(
                width_px=max(1, int(round(sub[0, 3]))), orientation=names[o], box=box,
                bar_boxes=tuple(tuple(int(v) for v in r[6:10]) for r in sub[sub[:, 5] == 0]),
                gap_boxes=tuple(tuple(int(v) for v in r[6:10]) for r in sub[sub[:, 5] == 1]))
        elements.append(UsafElement(group=g, element=e, lp_per_mm=float(rows[0, 2]), width_px=float(rows[0, 3]),
                                    horizontal=groups["horizontal"], vertical=groups["vertical"]))
    grid_size = int(table[0, 10]) if len(table) else 1
    image = np.zeros((grid_size, grid_size), np.float32)
    return UsafChart(image=image, pixel_pitch_m=pixel_pitch_m, elements=tuple(elements))
