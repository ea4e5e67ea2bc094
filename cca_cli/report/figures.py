"""PNG figures of a reconstruction. The only module that imports matplotlib.

Images are drawn on a pixel-exact layout: every image axes is an integer
multiple of the image's own pixels wide and high, so the recovery appears at
1:1 (or at an integer magnification, pixels replicated), never resampled into
a small panel, and a non-square recovery keeps its aspect ratio. Panels
compared side by side share the field, the size on screen and the intensity
scale. Axes are at the object: a field ``width`` wide whose image is
``H x W`` pixels is ``width · H/W`` high (square pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["write_comparison_figures", "write_coverage_figure", "write_figures", "magnification", "sqrt_units"]

_DPI = 100
# Layout in screen pixels: left margin (y ticks), gap between panels, panel title, x ticks and label,
# colour bar gap and width, right margin (colour bar label).
_LEFT, _GAP, _TITLE, _BOTTOM, _BAR_GAP, _BAR, _RIGHT = 72, 20, 30, 52, 14, 16, 86
#: Panel titles: font size (pt) and the height each further line adds (screen px).
_TITLE_PT, _TITLE_LINE = 9, 14
#: Screen size the recovery is magnified towards when it is small.
_TARGET_PX = 400
#: Full-field panels wider than this are drawn smaller (the 1:1 view is recovered_magnitude.png).
_MAX_OVERVIEW_PX = 1100
#: Phase is left out where the amplitude is below this share of its 99.5th percentile.
_PHASE_MASK = 0.1


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _integer_ticks(axis) -> None:
    """Ticks at whole numbers only on ``axis`` (a matplotlib x or y axis): pixel counts."""
    from matplotlib.ticker import MaxNLocator

    axis.set_major_locator(MaxNLocator(integer=True))


def _save(plt, fig, path: Path, *, tight: bool = True) -> Path:
    """Write ``fig`` to ``path`` and close it (``tight``: let matplotlib lay it out first)."""
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


def magnification(pixels: int, target: int = _TARGET_PX) -> int:
    """Integer magnification that shows an image of ``pixels`` px at least ``target`` px wide (1 when it already is).

    Examples
    --------
    >>> magnification(512), magnification(250), magnification(96)
    (1, 2, 5)
    """
    return max(1, math.ceil(target / max(int(pixels), 1)))


def sqrt_units(units: str) -> str:
    """Units of an amplitude whose intensity is in ``units``.

    Examples
    --------
    >>> sqrt_units("irradiance"), sqrt_units("counts/s")
    ('√irradiance', '√(counts/s)')
    """
    return f"√{units}" if units.isalnum() else f"√({units})"


@dataclass
class _Panel:
    """One image of a figure: values, title, colour map and what to draw on top."""

    image: np.ndarray
    title: str
    cmap: str = "gray"
    vmin: float | None = None
    vmax: float | None = None
    extent: tuple[float, float, float, float] | None = None   # (x0, x1, y1, y0) in `unit`: y grows downwards
    boxes: list = field(default_factory=list)                 # (x0, y0, width, height) outlines in `unit`
    unit: str = "mm"


@dataclass
class _Row:
    """A row of equally sized panels, each ``width_px`` x ``height_px`` screen pixels, with one colour bar."""

    width_px: int
    height_px: int
    panels: list[_Panel]
    colorbar: str = ""
    ticks: dict | None = None   # colour-bar ticks: value -> label


def _draw(plt, rows: list[_Row], title: str = ""):
    """A figure whose image axes are exactly ``row.width_px`` x ``row.height_px`` screen pixels.

    Each image is drawn with nearest-neighbour rendering when it is no larger
    than its axes, so an axes of ``k·w`` x ``k·h`` pixels shows a ``w`` x ``h``
    image with every pixel replicated ``k`` times. The image fills its axes
    (the layout, not matplotlib, keeps the aspect ratio).
    """
    widths = [len(r.panels) * r.width_px + (len(r.panels) - 1) * _GAP for r in rows]
    titles = [[_fit_title(p.title, r.width_px) for p in r.panels] for r in rows]
    title_px = [_TITLE + _TITLE_LINE * max(t.count("\n") for t in row_titles) for row_titles in titles]
    fig_w = _LEFT + max(widths) + _BAR_GAP + _BAR + _RIGHT
    head = 14 + 18 * (title.count("\n") + 1) if title else 8
    fig_h = head + sum(t + r.height_px + _BOTTOM for t, r in zip(title_px, rows))
    fig = plt.figure(figsize=(fig_w / _DPI, fig_h / _DPI), dpi=_DPI)
    if title:
        fig.suptitle(title, y=1 - 10 / fig_h, va="top", fontsize=11)
    top = head
    for row, width, row_titles, row_title_px in zip(rows, widths, titles, title_px):
        top += row_title_px
        bottom = fig_h - top - row.height_px
        shown = None
        for i, panel in enumerate(row.panels):
            left = _LEFT + i * (row.width_px + _GAP)
            ax = fig.add_axes((left / fig_w, bottom / fig_h, row.width_px / fig_w, row.height_px / fig_h))
            image = np.asanyarray(panel.image)   # keeps a mask
            fits = image.shape[-1] <= row.width_px and image.shape[-2] <= row.height_px
            shown = ax.imshow(image, cmap=panel.cmap, vmin=panel.vmin, vmax=panel.vmax, extent=panel.extent,
                              interpolation="nearest" if fits else "antialiased", aspect="auto")
            ax.set_title(row_titles[i], fontsize=_TITLE_PT)
            for x0, y0, w, h in panel.boxes:
                ax.add_patch(plt.Rectangle((x0, y0), w, h, fill=False, edgecolor="#ffb000", lw=1.2))
            if panel.extent is not None:
                if i > 0:
                    _drop_ticks_at_left_edge(ax, row.width_px)
                ax.set_xlabel(f"x at object ({panel.unit})", fontsize=8)
                if i == 0:
                    ax.set_ylabel(f"y at object ({panel.unit})", fontsize=8)
                else:
                    ax.tick_params(labelleft=False)
                ax.tick_params(labelsize=7)
            else:
                ax.set_axis_off()
        cax = fig.add_axes(((_LEFT + width + _BAR_GAP) / fig_w, bottom / fig_h, _BAR / fig_w, row.height_px / fig_h))
        bar = fig.colorbar(shown, cax=cax)
        label = row.colorbar
        if not row.ticks:
            label = _scaled_bar(bar, label)
        bar.set_label(label, fontsize=8)
        bar.ax.tick_params(labelsize=7)
        if row.ticks:
            bar.set_ticks(list(row.ticks), labels=list(row.ticks.values()))
        top += row.height_px + _BOTTOM
    return fig


def _fit_title(title: str, width_px: int) -> str:
    """``title`` broken onto two lines when it is wider than its panel: after its last top-level comma, else
    before its first top-level parenthesis (``observed (centre camera),`` / ``40 x 96 px (5x)``)."""
    from matplotlib.font_manager import FontProperties
    from matplotlib.textpath import text_to_path

    points, _, _ = text_to_path.get_text_width_height_descent(title, FontProperties(size=_TITLE_PT), ismath=False)
    if "\n" in title or points * _DPI / 72 <= width_px:
        return title
    depth, commas, opens = 0, [], []
    for i, char in enumerate(title):
        if char == "(":
            if depth == 0 and i > 0 and title[i - 1] == " ":
                opens.append(i - 1)
            depth += 1
        elif char == ")":
            depth -= 1
        elif char == "," and depth == 0 and title[i + 1:i + 2] == " ":
            commas.append(i + 1)
    if commas:
        return title[:commas[-1]] + "\n" + title[commas[-1] + 1:]
    if opens:
        return title[:opens[0]] + "\n" + title[opens[0] + 1:]
    return title


_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def _scaled_bar(bar, label: str) -> str:
    """Colour-bar ticks of large or small values as multiples of a power of ten named in the label.

    ``intensity (counts/s)`` with values up to 3·10⁶ becomes ``intensity (10⁶ counts/s)``
    with ticks 0…3, instead of six-digit ticks or a detached ``1e6``.
    """
    from matplotlib.ticker import FuncFormatter

    top = max(abs(float(bar.norm.vmin)), abs(float(bar.norm.vmax)))
    if not np.isfinite(top) or top == 0 or 1e-2 <= top < 1e4:
        return label
    power = math.floor(math.log10(top))
    scale = 10.0 ** power
    bar.formatter = FuncFormatter(lambda value, _: f"{value / scale:.4g}")
    bar.update_ticks()
    prefix = f"10{str(power).translate(_SUPERSCRIPT)}"
    if label.endswith(")") and " (" in label:
        name, units = label[:-1].split(" (", 1)
        return f"{name} ({prefix} {units})"
    return f"{label} (×{prefix})"


def _drop_ticks_at_left_edge(ax, width_px: int, clearance_px: float = 12.0) -> None:
    """Remove x ticks within ``clearance_px`` of a panel's left edge when the panels of its row (which share
    its axis) also have one that near their right edge: the two labels would read as one across the gap."""
    lo, hi = sorted(ax.get_xlim())
    near = clearance_px * (hi - lo) / width_px
    slack = 1e-6 * (hi - lo)    # a tick on the edge, up to rounding, is drawn
    ticks = [t for t in ax.get_xticks() if lo - slack <= t <= hi + slack]
    if any(t >= hi - near for t in ticks):
        ax.set_xticks([t for t in ticks if t > lo + near])


def _display_unit(field_width_m: float) -> tuple[float, str]:
    """Scale and name of the length unit the axes use: mm, or µm for fields under 2 mm."""
    return (1e6, "µm") if field_width_m < 2e-3 else (1e3, "mm")


def _extent(width: float, height: float, region=None) -> tuple[float, float, float, float]:
    """imshow extent (x0, x1, y1, y0) of the field ``width`` x ``height``, or of ``region`` of it (centred on the axis)."""
    y0, y1, x0, x1 = region.fractions if region is not None else (0.0, 1.0, 0.0, 1.0)
    return (x0 * width - width / 2, x1 * width - width / 2, y1 * height - height / 2, y0 * height - height / 2)


def _region_box(width: float, height: float, region) -> tuple[float, float, float, float]:
    """Outline (x0, y0, width, height) of ``region`` on the field ``width`` x ``height``."""
    y0, y1, x0, x1 = region.fractions
    return (x0 * width - width / 2, y0 * height - height / 2, (x1 - x0) * width, (y1 - y0) * height)


def _panel_px(shape, k: int, longest: int | None = None) -> tuple[int, int]:
    """Screen size ``(height, width)`` of an image of ``shape`` magnified ``k`` times, or with its longer side ``longest``."""
    rows, cols = shape[-2:]
    if longest is None:
        return rows * k, cols * k
    scale = longest / max(rows, cols)
    return max(1, round(rows * scale)), max(1, round(cols * scale))


def _size_text(shape) -> str:
    """``n px`` for a square image, ``w x h px`` otherwise."""
    rows, cols = shape[-2:]
    return f"{cols} px" if rows == cols else f"{cols} x {rows} px"


def _limits(*images) -> tuple[float, float]:
    """Common intensity range of images: 0 (or the minimum, if negative) to the 99.9th percentile."""
    values = np.concatenate([np.asarray(i, np.float32).ravel() for i in images])
    low = min(0.0, float(np.percentile(values, 0.1)))
    high = float(np.percentile(values, 99.9))
    return low, high if high > low else low + 1.0


def _single(plt, path: Path, image: np.ndarray, title: str, label: str, *, width: float, height: float, unit: str,
            cmap: str = "gray", region=None, vmin=None, vmax=None, ticks=None) -> Path:
    """One image at an integer magnification of its own pixels, with length axes and a colour bar."""
    k = magnification(max(image.shape[-2:]))
    boxes = [_region_box(width, height, region)] if region is not None else []
    scale = "1:1" if k == 1 else f"{k}x, pixels replicated"
    panel = _Panel(image, f"{image.shape[-1]} x {image.shape[-2]} px ({scale})", cmap=cmap, vmin=vmin, vmax=vmax,
                   extent=_extent(width, height), boxes=boxes, unit=unit)
    rows, cols = _panel_px(image.shape, k)
    fig = _draw(plt, [_Row(cols, rows, [panel], label, ticks)], title)
    return _save(plt, fig, path, tight=False)


def _phase(obj: np.ndarray) -> np.ma.MaskedArray:
    """Phase relative to the object's amplitude-weighted mean phase, masked where the amplitude is low."""
    amplitude = np.abs(obj)
    reference = np.angle(np.sum(obj * amplitude))
    phase = np.angle(obj * np.exp(-1j * reference))
    floor = _PHASE_MASK * float(np.percentile(amplitude, 99.5))
    return np.ma.masked_where(amplitude < floor, phase)


def write_figures(directory: Path, *, observed: np.ndarray, recovered_object: np.ndarray, spectrum: np.ndarray,
                  pupil_centres_px: np.ndarray, pupil_radius_px: float, field_width_m: float,
                  residual: np.ndarray, change: np.ndarray, summary: dict, truth: np.ndarray | None = None,
                  units: str = "irradiance", region=None, grid_indices: np.ndarray | None = None,
                  spectrum_field_width_m: float | None = None, held_back: np.ndarray | None = None) -> list[Path]:
    """Write the report's PNGs into ``directory`` and return their paths.

    Parameters
    ----------
    directory : Path
    observed : ndarray, (N, N) or (h, w)
        Centre capture over the recovered field (intensity, ``units``).
    recovered_object : ndarray, complex, (M, M) or (H, W)
        Recovered field.
    spectrum : ndarray, complex, (S, S)
        Recovered spectrum (centred): of the recovered field, or of the
        larger square grid it was cut from (see ``spectrum_field_width_m``).
    pupil_centres_px : ndarray, (K, 2)
        Aperture footprints' centres [y, x] relative to DC (spectrum px).
    pupil_radius_px : float
    field_width_m : float
        Object-plane width of the recovered field (m); its height is
        ``field_width_m · H/W``.
    residual, change : ndarray
        Convergence history.
    held_back : ndarray, optional
        Misfit of the captures held back from the updates, per iteration.
    summary : dict
        The report (titles, contrast tables, ``tol``, ``stopped_by``).
    truth : ndarray, optional
        Ground-truth intensity.
    units : str
        Intensity units (``irradiance`` for simulations, ``counts/s`` for recorded data).
    region : Region, optional
        Zoom region (:mod:`cca_cli.report.regions`).
    grid_indices : ndarray, (K, 2), optional
        Grid position of each footprint (the border ones are outlined).
    spectrum_field_width_m : float, optional
        Object-plane width of the grid ``spectrum`` is on (m), when the
        recovered field is a region cut from it (a region and its guard
        band); the spectrum figure then says so. Default ``field_width_m``.

    Returns
    -------
    list of Path
        ``observed_centre.png``, ``recovered_magnitude.png``,
        ``recovered_phase.png``, ``observed_vs_recovered.png``,
        ``spectrum.png`` and, when available, ``truth.png``,
        ``contrast.png``, ``convergence.png``.
    """
    plt = _plt()
    directory = Path(directory)
    amplitude = np.abs(recovered_object).astype(np.float32)
    rows, cols = amplitude.shape[-2:]
    field_height_m = field_width_m * rows / cols
    scale, unit = _display_unit(max(field_width_m, field_height_m))
    width, height = field_width_m * scale, field_height_m * scale
    pixel_um = field_width_m / cols * 1e6
    low, high = _limits(observed)
    field = dict(width=width, height=height, unit=unit, region=region)
    paths = [
        _single(plt, directory / "observed_centre.png", observed, "Observed centre image (one camera)",
                f"intensity ({units})", vmin=low, vmax=high, **field),
        _single(plt, directory / "recovered_magnitude.png", amplitude,
                f"Recovered magnitude |O| (SAR {summary['sar']:.2f}, {pixel_um:.3g} µm pixels)",
                f"|O| ({sqrt_units(units)})", vmin=0.0, vmax=float(np.percentile(amplitude, 99.9)) or None, **field),
        _single(plt, directory / "recovered_phase.png", _phase(recovered_object),
                f"Recovered phase, relative to its mean\n(black: |O| below {_PHASE_MASK:.0%} of its 99.5th percentile)",
                "phase (rad)", cmap=_phase_cmap(plt), vmin=-np.pi, vmax=np.pi,
                ticks={-np.pi: "−π", -np.pi / 2: "−π/2", 0.0: "0", np.pi / 2: "π/2", np.pi: "π"}, **field),
    ]
    if truth is not None:
        paths.append(_single(plt, directory / "truth.png", truth, "Ground truth intensity", f"intensity ({units})",
                             vmin=0.0, vmax=_limits(truth)[1], **field))
    images = {"observed (centre camera)": observed, "recovered": amplitude ** 2}
    if truth is not None:
        images = {"truth": truth, **images}
    paths.append(_side_by_side(plt, directory / "observed_vs_recovered.png", images, shape=(rows, cols), units=units,
                               heading="Observed vs recovered intensity, same field and scale", **field))
    title = "Recovered spectrum and aperture footprints"
    spectrum_width_m = field_width_m if spectrum_field_width_m is None else spectrum_field_width_m
    if spectrum_field_width_m is not None and not np.isclose(spectrum_field_width_m, field_width_m, rtol=1e-6):
        title = (f"Recovered spectrum and aperture footprints, of the whole\n{spectrum.shape[-1]} x "
                 f"{spectrum.shape[-2]} px grid the engine ran on ({_length(spectrum_width_m)} wide):\n"
                 f"the recovered {_length(field_width_m)} x {_length(field_height_m)} field and its guard band")
    paths.append(_spectrum(plt, directory / "spectrum.png", spectrum, pupil_centres_px, pupil_radius_px,
                           spectrum_width_m, grid_indices, title=title))
    if "contrast_observed" in summary:
        paths.append(_contrast(plt, directory / "contrast.png", summary))
    if len(residual):
        paths.append(_convergence(plt, directory / "convergence.png", residual, change, summary, held_back))
    return paths


def _phase_cmap(plt):
    """Cyclic colour map for phase with black reserved for masked pixels."""
    return plt.get_cmap("hsv").with_extremes(bad="black")


def _length(value_m: float) -> str:
    """A length in µm below 2 mm, else in mm, to 3 significant figures."""
    scale, unit = _display_unit(value_m)
    return f"{value_m * scale:.3g} {unit}"


def _side_by_side(plt, path: Path, images: dict, *, width: float, height: float, unit: str, region,
                  shape: tuple[int, int], units: str, heading: str) -> Path:
    """Full field (top row) and the zoom region (bottom row) of every image, on equal axes and one scale.

    ``shape`` is the ``(H, W)`` grid the layout is made for (the recovery's);
    images on other grids fill the same axes at their own pixels.
    """
    k = magnification(max(shape))
    fits = max(shape) * k <= _MAX_OVERVIEW_PX
    panel_h, panel_w = _panel_px(shape, k, None if fits else 768)
    low, high = _limits(*images.values())
    boxes = [_region_box(width, height, region)] if region is not None else []
    scale = "1:1" if fits and k == 1 else (f"{k}x" if fits else "shrunk")

    def title(name: str, image) -> str:
        return f"{name}, {_size_text(image.shape)} ({scale if image.shape[-2:] == tuple(shape) else 'own pixels'})"

    full = [_Panel(np.asarray(image), title(name, image), vmin=low, vmax=high, extent=_extent(width, height),
                   boxes=boxes, unit=unit) for name, image in images.items()]
    rows = [_Row(panel_w, panel_h, full, f"intensity ({units})")]
    if region is not None:
        crops = {name: region.crop(np.asarray(image)) for name, image in images.items()}
        low_z, high_z = _limits(*crops.values())
        y0, y1, x0, x1 = region.pixels(shape)
        zoom = max(1, round(_TARGET_PX / max(y1 - y0, x1 - x0)))
        panels = [_Panel(crop, f"{name}, zoom", vmin=low_z, vmax=high_z, extent=_extent(width, height, region),
                         unit=unit) for name, crop in crops.items()]
        rows.append(_Row((x1 - x0) * zoom, (y1 - y0) * zoom, panels, f"intensity ({units})"))
        heading += f"\nbottom: zoom on {region.label}"
    fig = _draw(plt, rows, heading)
    return _save(plt, fig, path, tight=False)


def _spectrum(plt, path: Path, spectrum: np.ndarray, centres, radius_px: float, field_width_m: float,
              grid_indices, *, title: str = "Recovered spectrum and aperture footprints") -> Path:
    """log10 |S| in cycles/mm at the object, with the aperture footprints and a colour bar.

    ``spectrum`` covers a field ``field_width_m`` wide (and, for an ``h x w``
    grid, ``h/w`` of that high). ``centres`` are [y, x] offsets from DC in
    spectrum pixels of each axis; ``radius_px`` is in pixels along x (a
    spectrum pixel along y is ``w/h`` of them), so the footprints are drawn as
    the circles they are in cycles/mm.
    """
    magnitude = np.abs(spectrum)
    peak = float(magnitude.max()) or 1.0
    log_mag = np.log10(np.maximum(magnitude / peak, 1e-12))
    floor = float(np.percentile(log_mag[magnitude > 0], 1)) if np.any(magnitude > 0) else -6.0
    rows, cols = spectrum.shape[-2:]
    per_px = 1.0 / (field_width_m * 1e3)              # spectrum pixel along x → cycles per mm at the object
    per_px_y = per_px * cols / rows                   # along y: the field is rows/cols as high
    half_x, half_y = cols / 2 * per_px, rows / 2 * per_px_y
    fig, ax = plt.subplots(figsize=(7.2, 6.8), dpi=_DPI)
    shown = ax.imshow(log_mag, cmap="magma", vmin=max(floor, -8.0), vmax=0.0, interpolation="nearest",
                      extent=(-half_x - per_px / 2, half_x - per_px / 2, half_y - per_px_y / 2, -half_y - per_px_y / 2))
    fig.colorbar(shown, ax=ax, label="log10 |S| / max |S|", shrink=0.85)
    centres = np.asarray(centres, np.float64)
    centres_mm = centres * np.array([per_px_y, per_px])    # cycles per mm
    radius = radius_px * per_px
    theta = np.linspace(0, 2 * np.pi, 128)
    centre = int(np.argmin(np.hypot(centres[:, 0], centres[:, 1])))
    outline = _border(centres, grid_indices)
    for i in outline:
        cy, cx = centres_mm[i]
        ax.plot(cx + radius * np.cos(theta), cy + radius * np.sin(theta), color="#00e5ff", lw=0.9, alpha=0.9)
    ax.scatter(centres_mm[:, 1], centres_mm[:, 0], s=4, color="#00e5ff", linewidths=0)
    cy, cx = centres_mm[centre]
    ax.plot(cx + radius * np.cos(theta), cy + radius * np.sin(theta), color="white", lw=1.8)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color="white", lw=1.8,
                      label=f"centre aperture (R = {radius_px:.1f} px = {radius_px * per_px:.3g} cycles/mm)"),
               Line2D([], [], color="#00e5ff", lw=0.9, label="outer apertures" if len(outline) < len(centres)
                      else "aperture footprints"),
               Line2D([], [], color="#00e5ff", marker="o", ms=3, lw=0, label=f"all {len(centres)} aperture centres")]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.11), ncol=2, fontsize=7,
              facecolor="#303030", labelcolor="white", framealpha=1.0)
    reach = (float(np.max(np.abs(centres_mm))) + radius) * 1.08
    ax.set_xlim(-min(reach, half_x), min(reach, half_x))
    ax.set_ylim(min(reach, half_y), -min(reach, half_y))
    ax.set_xlabel("spatial frequency at object, x (cycles/mm)")
    ax.set_ylabel("spatial frequency at object, y (cycles/mm)")
    ax.set_title(title, fontsize=10)
    return _save(plt, fig, path)


def _border(centres: np.ndarray, grid_indices) -> list[int]:
    """Footprints to outline: all of them when few, else those on the border of the capture grid."""
    if len(centres) <= 60 or grid_indices is None or len(grid_indices) != len(centres):
        return list(range(len(centres)))
    g = np.asarray(grid_indices)
    edge = (g[:, 0] == g[:, 0].min()) | (g[:, 0] == g[:, 0].max()) | (g[:, 1] == g[:, 1].min()) \
        | (g[:, 1] == g[:, 1].max())
    return [int(i) for i in np.flatnonzero(edge)]


def _contrast(plt, path: Path, summary: dict) -> Path:
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=_DPI)
    for key, style, name in (("contrast_observed", "--", "observed"), ("contrast_recovered", "-", "recovered")):
        table = summary[key]
        widths = np.asarray(table["widths_px"])
        ax.plot(widths, table["horizontal"], style, marker="o", ms=3, label=f"{name}, horizontal bars")
        ax.plot(widths, table["vertical"], style, marker="s", ms=3, label=f"{name}, vertical bars")
    ax.axhline(summary.get("mtf_threshold", 0.2), color="gray", lw=0.8, ls=":", label="threshold")
    ax.set_xlabel("bar width (truth-grid px)")
    ax.set_ylabel("contrast (w̄ − b̄)/(w̄ + b̄)")
    ax.invert_xaxis()
    limits = [f"{name} {summary.get(f'mtf20_{name}_px')} px" for name in ("observed", "recovered")]
    ax.set_title("Bar contrast vs width; MTF20: " + ", ".join(limits), fontsize=10)
    ax.legend(fontsize=7)
    return _save(plt, fig, path)


def _convergence(plt, path: Path, residual, change, summary: dict, held_back=None) -> Path:
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=_DPI)
    it = np.arange(1, len(residual) + 1)
    ax.semilogy(it, residual, label="data residual")
    if held_back is not None:
        ax.semilogy(it, held_back, label="held-back captures' residual")
        best = summary.get("held_back_best_iteration")
        if best:
            ax.axvline(best, color="gray", lw=0.8, ls="--", label=f"best held-back fit (iteration {best})")
    ax.semilogy(it, np.maximum(change, 1e-12), label="relative change")
    tol = summary.get("tol")
    if tol:
        ax.axhline(tol, color="gray", lw=0.8, ls=":", label=f"tol {tol:g}")
    stopped = {"tol": "change fell below tol", "plateau": "misfit stopped falling (plateau)",
               "held_back": "held-back captures stopped improving",
               "cap": "iteration cap reached before tol"}.get(summary.get("stopped_by"))
    ax.set_xlabel("iteration")
    ax.set_ylabel("relative value")
    ax.set_title("Convergence" + (f": {stopped}" if stopped else ""), fontsize=10)
    ax.legend(fontsize=8)
    return _save(plt, fig, path)


def write_comparison_figures(directory: Path, images: dict, summary: dict, *, field_width_m: float | None = None,
                             region=None, units: str = "irradiance") -> list[Path]:
    """Side-by-side images (truth, observed, baselines, recovered) and contrast curves with the baselines.

    Parameters
    ----------
    directory : Path
    images : dict
        ``name → intensity`` on the truth grid (``truth``, ``observed``, ``recovered`` and baseline labels).
    summary : dict
        The report; ``baselines`` entries provide the baselines' contrast tables.
    field_width_m : float, optional
        Field width (m), for the axes.
    region : Region, optional
        Zoom region, drawn as a second row.
    units : str
        Intensity units.

    Returns
    -------
    list of Path
    """
    plt = _plt()
    directory = Path(directory)
    paths = []
    order = [n for n in ("truth", "observed") if n in images]
    order += [n for n in images if n not in ("truth", "observed", "recovered")]
    order += ["recovered"]
    titled = {}
    for name in order:
        extra = ""
        if name in summary.get("baselines", {}):
            mtf = summary["baselines"][name].get("mtf20_px")
            extra = f" (MTF20 {mtf} px)" if mtf is not None else ""
        elif name in ("observed", "recovered") and summary.get(f"mtf20_{name}_px") is not None:
            extra = f" (MTF20 {summary[f'mtf20_{name}_px']} px)"
        reading = (summary.get("usaf") or {}).get(name)
        if isinstance(reading, dict) and reading.get("group") is not None:
            extra += f" (USAF G{reading['group']} E{reading['element']})"
        titled[name.replace("_", " ") + extra] = np.asarray(images[name], np.float32)
    shape = next(iter(titled.values())).shape[-2:]
    width_m = field_width_m or 1e-3
    height_m = width_m * shape[0] / shape[1]
    scale, unit = _display_unit(max(width_m, height_m))
    width, height = width_m * scale, height_m * scale
    longest = max(shape)   # whole pixels, or shrunk when the grid is large
    panel_h, panel_w = _panel_px(shape, max(1, 420 // longest)) if longest <= 420 else _panel_px(shape, 1, 420)
    low, high = _limits(*titled.values())
    boxes = [_region_box(width, height, region)] if region is not None else []
    rows = [_Row(panel_w, panel_h, [_Panel(image, name, vmin=low, vmax=high, extent=_extent(width, height),
                                           boxes=boxes, unit=unit) for name, image in titled.items()],
                 f"intensity ({units})")]
    if region is not None:
        crops = {name: region.crop(image) for name, image in titled.items()}
        low_z, high_z = _limits(*crops.values())
        crop_h = max(c.shape[-2] for c in crops.values())
        crop_w = max(c.shape[-1] for c in crops.values())
        zoom = max(1, round(300 / max(crop_h, crop_w)))
        rows.append(_Row(crop_w * zoom, crop_h * zoom,
                         [_Panel(crop, f"{name.split(' (')[0]}: zoom", vmin=low_z, vmax=high_z,
                                 extent=_extent(width, height, region), unit=unit) for name, crop in crops.items()],
                         f"intensity ({units})"))
    title = "Recovery vs single lenses, same field and scale" + (f"; zoom: {region.label}" if region else "")
    paths.append(_save(plt, _draw(plt, rows, title), directory / "comparison.png", tight=False))

    tables = {}
    for name in ("contrast_observed", "contrast_recovered"):
        if name in summary:
            tables[name.split("_", 1)[1]] = summary[name]
    for name, entry in summary.get("baselines", {}).items():
        if "contrast" in entry:
            tables[name] = entry["contrast"]
    if tables:
        fig, ax = plt.subplots(figsize=(6.5, 4.2), dpi=110)
        for name, table in tables.items():
            widths = np.asarray(table["widths_px"])
            worst = np.minimum(table["horizontal"], table["vertical"])
            ax.plot(widths, worst, marker="o", ms=3, lw=2 if name == "recovered" else 1,
                    label=name.replace("_", " "))
        ax.axhline(summary.get("mtf_threshold", 0.2), color="gray", lw=0.8, ls=":")
        ax.set_xlabel("bar width (truth-grid px)")
        ax.set_ylabel("contrast, worse orientation")
        ax.invert_xaxis()
        ax.set_title("Bar contrast: recovery vs single lenses")
        ax.legend(fontsize=7)
        paths.append(_save(plt, fig, directory / "contrast_baselines.png"))
    return paths


def write_coverage_figure(path: Path, coverage: np.ndarray, band: np.ndarray, summary: dict) -> Path:
    """Fourier coverage of a multiplexed design: measurements constraining each spectrum pixel.

    Holes (pixels of the design band that no measurement constrains) are drawn
    red; the band's outline is drawn in white.

    Parameters
    ----------
    path : Path
        PNG to write.
    coverage : ndarray, int, (M, M)
        Measurement count per spectrum pixel (centred).
    band : ndarray, bool, (M, M)
        Every region the array could measure.
    summary : dict
        Supplies ``coverage_zero_fraction`` and the design counts for the title.

    Returns
    -------
    Path
    """
    plt = _plt()
    from matplotlib.colors import ListedColormap

    m = coverage.shape[-1]
    half = m / 2
    extent = (-half, half, half, -half)
    fig, ax = plt.subplots(figsize=(6, 5.2), dpi=110)
    shown = np.ma.masked_where(coverage == 0, coverage)
    image = ax.imshow(shown, cmap="viridis", extent=extent, interpolation="nearest", vmin=1,
                      vmax=max(int(coverage.max()), 2))
    holes = np.ma.masked_where(~(band & (coverage == 0)), np.ones_like(coverage))
    ax.imshow(holes, cmap=ListedColormap(["red"]), extent=extent, interpolation="nearest", alpha=0.85)
    ax.contour(np.arange(m) - half + 0.5, np.arange(m) - half + 0.5, band.astype(float), levels=[0.5],
               colors="white", linewidths=0.6)
    ax.set_facecolor("black")
    n_mux = summary.get("multiplex_n_mux") or []
    mux_text = f"N_mux {n_mux[0]}" if n_mux and len(set(n_mux)) == 1 else f"N_mux {n_mux}"
    ax.set_title(f"Fourier coverage ({mux_text}, T {summary.get('multiplex_patterns')}): "
                 f"holes {100 * summary.get('coverage_zero_fraction', 0):.1f}% of band", fontsize=9)
    ax.set_xlabel("spectrum px (x)")
    ax.set_ylabel("spectrum px (y)")
    fig.colorbar(image, ax=ax, label="measurements per spectrum pixel")
    return _save(plt, fig, Path(path))


def write_calibration_figures(directory: Path, calibration: dict) -> list[Path]:
    """Figures of what a calibrating engine found: pupils, position changes, brightness, per-image residuals.

    Parameters
    ----------
    directory : Path
    calibration : dict
        ``nominal_px`` (K, 2) and ``refined_px`` (K, 2) pupil centres, ``radius_px``,
        ``bright_field`` (K,) bool, ``residual_per_image`` (K,), and optionally
        ``pupil`` (P, b, b) complex, ``brightness`` (K,), ``pixels_per_sine`` (LED
        arrays: spectrum pixels per unit sin θ) and ``zernike`` (names → waves).

    Returns
    -------
    list of Path
    """
    plt = _plt()
    paths = []
    if calibration.get("pupil") is not None:
        paths.append(_pupil_figure(plt, directory / "pupil.png", calibration))
    moved = np.asarray(calibration["refined_px"]) - np.asarray(calibration["nominal_px"])
    if np.any(np.abs(moved) > 1e-6):
        paths.append(_positions_figure(plt, directory / "positions.png", calibration))
    if calibration.get("brightness") is not None and np.ptp(calibration["brightness"]) > 0:
        paths.append(_brightness_figure(plt, directory / "brightness.png", calibration))
    paths.append(_residual_figure(plt, directory / "residual_per_image.png", calibration))
    return paths


def _pupil_figure(plt, path: Path, calibration: dict) -> Path:
    """Amplitude and phase of the recovered pupil(s); one row per camera (up to 6) on the NA disc."""
    from cca_cli.engines.pupil_recovery import tilt_of, untilt_ramp

    pupils = np.asarray(calibration["pupil"])
    shown = pupils[:6]
    b = pupils.shape[-1]
    radius = float(calibration["radius_px"])
    centre = b // 2  # where /calibration/pupil's disc is centred
    grid = (np.arange(b) - centre) / radius
    inside = (grid[:, None] ** 2 + grid[None, :] ** 2) <= 1.0
    extent = ((-0.5 - centre) / radius, (b - 1 - centre + 0.5) / radius,
              (b - 1 - centre + 0.5) / radius, (-0.5 - centre) / radius)
    fig, axes = plt.subplots(len(shown), 2, figsize=(8.4, 3.6 * len(shown)), squeeze=False)
    for row, pupil in enumerate(shown):
        # A pupil's tilt is a shift of the image, not an aberration: shown without it (its size in the title).
        tilt = tilt_of(pupil, inside.astype(np.float64))
        flat = pupil * untilt_ramp(tilt, b)
        reference = np.sum(flat[inside])
        phase = np.angle(flat * np.exp(-1j * np.angle(reference)))
        amplitude = np.abs(pupil)
        ids = calibration.get("camera_ids")
        label = "pupil" if len(pupils) == 1 else \
            f"camera {ids[row] if ids is not None and len(ids) == len(pupils) else row}"
        tilt_waves = float(np.hypot(*tilt)) * 2.0 * radius / (2.0 * np.pi)
        phase_title = f"{label}: phase" + (f"\n(a tilt of {tilt_waves:.2f} waves across the NA removed)"
                                           if tilt_waves >= 0.005 else "")
        for ax, image, title, cmap, bar in (
                (axes[row, 0], amplitude, f"{label}: amplitude", "gray", "relative amplitude"),
                (axes[row, 1], phase / (2 * np.pi), phase_title, _phase_cmap(plt), "waves")):
            masked = np.ma.masked_where(~inside, image)
            limit = max(float(np.max(np.abs(masked))), 1e-3) if bar == "waves" else None
            shown_image = ax.imshow(masked, cmap=cmap, extent=extent, interpolation="nearest",
                                    vmin=-limit if limit else None, vmax=limit)
            ax.set_title(title, fontsize=10)
            ax.set_xlabel("pupil x (units of NA)", fontsize=8)
            ax.set_ylabel("pupil y (units of NA)", fontsize=8)
            ax.tick_params(labelsize=7)
            fig.colorbar(shown_image, ax=ax, label=bar, fraction=0.046, pad=0.04)
    zernike = calibration.get("zernike") or {}
    if zernike:
        items = [f"{name} {value:+.3f}" for name, value in list(zernike.items())[:6]]
        text = ", ".join(items[:3]) + ("\n" + ", ".join(items[3:]) if len(items) > 3 else "")
        fig.suptitle(f"Recovered pupil. Zernike coefficients (waves RMS):\n{text}", fontsize=9)
    if len(pupils) > len(shown):
        fig.text(0.5, 0.005, f"first {len(shown)} of {len(pupils)} cameras shown", ha="center", fontsize=8)
    return _save(plt, fig, path)


def _sines(calibration: dict, key: str) -> tuple[np.ndarray, str]:
    """Pupil centres as illumination sin θ (LED arrays) or spectrum pixels, with the axis label."""
    centres = np.asarray(calibration[key], np.float64)
    per_sine = calibration.get("pixels_per_sine")
    if per_sine:
        return centres / per_sine, "sin θ"
    return centres, "spectrum px"


def _positions_figure(plt, path: Path, calibration: dict) -> Path:
    """Nominal pupil centres and the change calibration made, as arrows (scaled up to be seen)."""
    nominal, unit = _sines(calibration, "nominal_px")
    refined, _ = _sines(calibration, "refined_px")
    moves_px = np.asarray(calibration["refined_px"]) - np.asarray(calibration["nominal_px"])
    largest = float(np.max(np.hypot(moves_px[:, 0], moves_px[:, 1]))) if len(moves_px) else 0.0
    fig, ax = plt.subplots(figsize=(6.4, 5.8))
    bright = np.asarray(calibration["bright_field"], bool)
    ax.scatter(nominal[~bright, 1], nominal[~bright, 0], s=10, c="#777777", label="dark-field (nominal)")
    ax.scatter(nominal[bright, 1], nominal[bright, 0], s=14, c="#d62728", label="bright-field (nominal)")
    if largest > 0:
        span = float(np.ptp(nominal)) or 1.0
        spacing = span / max(np.sqrt(len(nominal)) - 1, 1)
        delta = refined - nominal
        gain = 0.8 * spacing / float(np.max(np.hypot(delta[:, 0], delta[:, 1])))
        ax.quiver(nominal[:, 1], nominal[:, 0], delta[:, 1] * gain, delta[:, 0] * gain, angles="xy",
                  scale_units="xy", scale=1, width=0.004, color="#1f77b4")
        ax.set_title(f"Position calibration: arrows ×{gain:.0f} (largest move {largest:.2f} spectrum px)", fontsize=10)
    else:
        ax.set_title("Pupil positions (not calibrated: nominal)", fontsize=10)
    ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"y ({unit})")
    ax.legend(fontsize=8, loc="upper right")
    return _save(plt, fig, path)


def _brightness_figure(plt, path: Path, calibration: dict) -> Path:
    """Each capture's fitted illumination brightness at its nominal pupil centre."""
    nominal, unit = _sines(calibration, "nominal_px")
    brightness = np.asarray(calibration["brightness"])
    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    shown = ax.scatter(nominal[:, 1], nominal[:, 0], c=brightness, s=40, cmap="viridis", edgecolors="none")
    fig.colorbar(shown, ax=ax, label="brightness (1 = median)")
    ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"y ({unit})")
    ax.set_title(f"Illumination brightness: {brightness.min():.2f} … {brightness.max():.2f}", fontsize=10)
    return _save(plt, fig, path)


def _residual_figure(plt, path: Path, calibration: dict) -> Path:
    """Each capture's relative amplitude residual against its distance from the optical axis."""
    nominal, unit = _sines(calibration, "nominal_px")
    distance = np.hypot(nominal[:, 0], nominal[:, 1])
    residual = np.asarray(calibration["residual_per_image"])
    bright = np.asarray(calibration["bright_field"], bool)
    fig, ax = plt.subplots(figsize=(7.0, 4.2))
    ax.scatter(distance[~bright], residual[~bright], s=12, c="#555555", label="dark-field")
    ax.scatter(distance[bright], residual[bright], s=16, c="#d62728", label="bright-field")
    edge = float(calibration["radius_px"]) / (calibration.get("pixels_per_sine") or 1.0)
    ax.axvline(edge, color="#999999", lw=0.8, ls="--")
    ax.text(edge, ax.get_ylim()[1], " NA", fontsize=8, va="top", color="#666666")
    ax.set_xlabel(f"illumination offset from the axis ({unit})" if unit == "sin θ" else f"pupil offset ({unit})")
    ax.set_ylabel("relative amplitude residual")
    ax.set_yscale("log")
    totals = calibration.get("totals") or {}
    title = "Residual per image"
    if totals:
        title += " — all {all:.3f}, bright-field {bright_field:.3f}, dark-field {dark_field:.3f}".format(**totals)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    return _save(plt, fig, path)


def write_tile_figure(path: Path, tiles: dict, *, field_width_m: float, frame_shape) -> Path:
    """Maps across the field of each tile's pupil aberration (first three Zernike modes) and residual.

    Parameters
    ----------
    path : Path
    tiles : dict
        ``box_px`` (T, 4) tile boxes in frame pixels, ``residual`` (T,), and optionally
        ``zernike_waves`` (T, n_modes) of the first pupil and ``zernike_names``.
    field_width_m : float
        Object-plane width of the frame's columns.
    frame_shape : tuple of int
        ``(H, W)`` of the frame.
    """
    plt = _plt()
    boxes = np.asarray(tiles["box_px"], np.float64)
    centres = boxes[:, :2] + (boxes[:, 2:] - 1) / 2.0
    ys, xs = sorted(set(centres[:, 0])), sorted(set(centres[:, 1]))
    pixel = field_width_m / frame_shape[1]
    scale, unit = _display_unit(field_width_m)
    maps = []
    names = list(tiles.get("zernike_names") or [])[:3]
    waves = tiles.get("zernike_waves")
    truth = tiles.get("truth_waves") or {}
    for j, name in enumerate(names):
        values = [np.abs(waves[:, j])] + ([np.abs(truth[name])] if name in truth else [])
        limit = max(float(np.nanmax(np.concatenate(values), initial=0.0)), 1e-3)
        maps.append((f"{name} (waves RMS)" + (", recovered" if truth else ""), waves[:, j], "RdBu_r", limit))
    maps.append(("amplitude residual, all captures", np.asarray(tiles["residual"], np.float64), "viridis", None))
    # a simulation: the lens's modes under the recovered ones, column by column, on their colour scales
    below = {j: (f"{name} (waves RMS), the lens's", truth[name], "RdBu_r", maps[j][3])
             for j, name in enumerate(names) if name in truth}
    rows = 2 if below else 1
    fig, axes = plt.subplots(rows, len(maps), figsize=(3.9 * len(maps), 3.6 * rows), squeeze=False)
    half_y = (ys[1] - ys[0]) / 2 if len(ys) > 1 else frame_shape[0] / 2
    half_x = (xs[1] - xs[0]) / 2 if len(xs) > 1 else frame_shape[1] / 2
    extent = ((xs[0] - half_x) * pixel * scale, (xs[-1] + half_x) * pixel * scale,
              (ys[-1] + half_y) * pixel * scale, (ys[0] - half_y) * pixel * scale)
    panels = list(zip(axes[0], maps)) + [(axes[1][j], panel) for j, panel in below.items()]
    for j in (range(len(maps)) if below else ()):
        if j not in below:
            axes[1][j].axis("off")
    for ax, (title, values, cmap, limit) in panels:
        grid = np.full((len(ys), len(xs)), np.nan)
        for (cy, cx), value in zip(centres, values):
            grid[ys.index(cy), xs.index(cx)] = value
        image = ax.imshow(grid, cmap=cmap, extent=extent, interpolation="nearest",
                          vmin=-limit if limit else None, vmax=limit)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(f"x ({unit})", fontsize=8)
        ax.set_ylabel(f"y ({unit})", fontsize=8)
        ax.tick_params(labelsize=7)
        fig.colorbar(image, ax=ax, fraction=0.046, pad=0.04)
    fig.suptitle(f"{len(boxes)} tiles of {int(boxes[0, 2])} px: the pupil and the fit across the field", fontsize=11)
    return _save(plt, fig, path)
