"""PNG figures of a parameter sweep: metric-vs-parameter lines, contrast curves and a crop montage.

matplotlib is imported lazily, through :mod:`cca_cli.report.figures`, only when a figure is drawn.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cca_cli.report.figures import _integer_ticks, _plt, _save

__all__ = ["SweepPlotData", "axis_label", "plot_sweep"]

_LABELS = {
    "array.overlap": ("overlap between neighbouring apertures (%)", 100.0),
    "sar": ("synthetic aperture ratio SAR (1)", 1.0),
    "array.grid": ("grid positions per side n (1)", 1.0),
    "grid_n": ("grid positions per side n (1)", 1.0),
    "noise.snr_db": ("SNR (dB)", 1.0),
    "optics.distance_m": ("object distance (m)", 1.0),
    "n_images": ("captures (1)", 1.0),
}


@dataclass(frozen=True)
class SweepPlotData:
    """What the sweep plots show.

    Attributes
    ----------
    study : str
        Study kind (titles).
    x, group : str
        Table column on the x axis and the one that separates lines (or None).
    series : list of dict
        One dict per completed point: ``x``, ``group`` and the metrics.
    contrast : list of (dict, dict or None)
        Highlighted points and their contrast tables (``recovered``, ``observed``, ``threshold``).
    crops : list of (dict, dict or None)
        Highlighted points and their ``recovered`` / ``observed`` / ``truth`` intensities on one grid.
    """

    study: str
    x: str
    group: str | None
    series: list[dict[str, Any]]
    contrast: list[tuple[dict, dict | None]] = field(default_factory=list)
    crops: list[tuple[dict, dict | None]] = field(default_factory=list)


def axis_label(column: str) -> tuple[str, float]:
    """Axis label (with units) and display scale of a table column."""
    return _LABELS.get(column, (column, 1.0))


def _fmt(column: str | None, value) -> str:
    if column is None or value is None:
        return ""
    label, scale = axis_label(column)
    short = {"array.overlap": "overlap", "sar": "SAR", "noise.snr_db": "SNR", "array.grid": "grid"}.get(column, column)
    if column == "array.overlap":
        return f"{short} {float(value) * scale:.0f}%"
    if column == "noise.snr_db":
        return f"{short} {float(value):g} dB"
    return f"{short} {float(value):.3g}" if isinstance(value, (int, float)) else f"{short} {value}"


def _groups(series: list[dict]) -> dict[Any, list[dict]]:
    out: dict[Any, list[dict]] = {}
    for item in series:
        out.setdefault(item["group"], []).append(item)
    return {k: sorted(v, key=lambda s: s["x"]) for k, v in sorted(out.items(), key=lambda kv: str(kv[0]))}


def _line_plot(plt, path: Path, data: SweepPlotData, key: str, observed_key: str, ylabel: str, title: str) -> bool:
    groups = _groups([s for s in data.series if s.get(key) is not None])
    if not groups:
        return False
    xlabel, scale = axis_label(data.x)
    fig, ax = plt.subplots(figsize=(6.2, 4.2), dpi=110)
    for n, (group, items) in enumerate(groups.items()):
        color = f"C{n % 10}"
        xs = np.array([s["x"] for s in items]) * scale
        name = _fmt(data.group, group) if data.group else "recovered"
        ax.plot(xs, [s[key] for s in items], "-o", color=color, ms=4, label=name)
        obs = [s.get(observed_key) for s in items]
        if any(v is not None for v in obs):
            ax.plot(xs, [np.nan if v is None else v for v in obs], "--", color=color, alpha=0.6, lw=1,
                    label=f"{name}, observed centre image" if data.group else "observed centre image")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if key.endswith("_px"):   # a bar width: whole scene pixels
        _integer_ticks(ax.yaxis)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    _save(plt, fig, path)
    return True


def plot_sweep(data: SweepPlotData, directory: Path) -> list[Path]:
    """Draw the sweep's figures into ``directory``; return their paths.

    Figures: ``rmse_vs_<x>.png`` (RMSE of the recovered and observed
    intensities), ``rmse_band_vs_<x>.png`` (the same against the band-limited
    truth), ``mtf20_vs_<x>.png`` (resolution limit, for charts),
    ``contrast_vs_width.png`` (contrast per bar width of highlighted points)
    and ``montage.png`` (centre crops of truth, observed and recovered images on one grey scale).
    """
    plt = _plt()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stem = data.x.replace(".", "_")
    paths = []
    rmse = directory / f"rmse_vs_{stem}.png"
    if _line_plot(plt, rmse, data, "rmse_recovered", "rmse_observed", "RMSE of intensity (fraction of peak)",
                  f"{data.study} study: reconstruction error"):
        paths.append(rmse)
    band = directory / f"rmse_band_vs_{stem}.png"
    if _line_plot(plt, band, data, "rmse_recovered_band", "rmse_observed_band",
                  "RMSE vs band-limited truth (fraction of peak)", f"{data.study} study: phase-retrieval error"):
        paths.append(band)
    mtf = directory / f"mtf20_vs_{stem}.png"
    if _line_plot(plt, mtf, data, "mtf20_recovered_px", "mtf20_observed_px",
                  "MTF20 limit: smallest resolved bar (scene px)", f"{data.study} study: resolution"):
        paths.append(mtf)
    curves = [(item, table) for item, table in data.contrast if table]
    if curves:
        fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=110)
        first = curves[0][1]
        widths = np.asarray(first["observed"]["widths_px"])
        ax.plot(widths, _mean_contrast(first["observed"]), "k--", lw=1, label="observed centre image")
        for n, (item, table) in enumerate(curves):
            label = _fmt(data.x, item["x"]) + (f", {_fmt(data.group, item['group'])}" if data.group else "")
            ax.plot(np.asarray(table["recovered"]["widths_px"]), _mean_contrast(table["recovered"]), "-o", ms=3,
                    color=f"C{n % 10}", label=label)
        ax.axhline(first.get("threshold", 0.2), color="gray", lw=0.8, ls=":", label="MTF20 threshold")
        ax.set_xlabel("bar width at object (scene px: scene.field_width_m / scene.size_px)")
        _integer_ticks(ax.xaxis)
        ax.set_ylabel("contrast (w̄ − b̄)/(w̄ + b̄) (1)")
        ax.invert_xaxis()
        ax.set_title(f"{data.study} study: contrast vs bar width")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        paths.append(_save(plt, fig, directory / "contrast_vs_width.png"))
    tiles = [(item, images) for item, images in data.crops if images]
    if tiles:
        first = tiles[0][1]
        panels = []
        if first.get("truth") is not None:
            panels.append(("ground truth", first["truth"]))
        panels.append(("observed (" + _fmt(data.x, tiles[0][0]["x"]) + ")", first["observed"]))
        for item, images in tiles:
            title = _fmt(data.x, item["x"]) + (f", {_fmt(data.group, item['group'])}" if data.group else "")
            if item.get("rmse_recovered") is not None:
                title += f"\nRMSE {item['rmse_recovered']:.3f}"
            panels.append((title, images["recovered"]))
        cols = min(4, len(panels))
        rows = int(np.ceil(len(panels) / cols))
        fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 3.0 * rows), dpi=110, squeeze=False)
        for ax in axes.ravel():
            ax.axis("off")
        # one grey scale for every panel (the first's, the truth where there is one), so a recovery that lost
        # contrast or brightness looks it
        top = _crop_top(_centre_crop(panels[0][1]))
        for ax, (title, image) in zip(axes.ravel(), panels):
            ax.imshow(_centre_crop(image), cmap="gray", interpolation="nearest", vmin=0, vmax=top)
            ax.set_title(title, fontsize=8)
        fig.suptitle(f"{data.study} study: centre crops (half the field of view), intensity on one grey scale "
                     f"(0 to the {panels[0][0].split(' (')[0]}'s 99.5th percentile)", fontsize=9)
        paths.append(_save(plt, fig, directory / "montage.png"))
    return paths


def _mean_contrast(table: dict) -> np.ndarray:
    h = np.asarray(table["horizontal"], np.float64)
    v = np.asarray(table["vertical"], np.float64)
    return np.nanmean(np.stack([h, v]), axis=0)


def _centre_crop(image: np.ndarray) -> np.ndarray:
    """The middle half of ``image`` along each axis (float64)."""
    n = image.shape[-1]
    q = n // 4
    return np.asarray(image, np.float64)[q:n - q, q:n - q]


def _crop_top(crop: np.ndarray) -> float:
    """The grey scale's white: the crop's 99.5th percentile (1 for a dark crop)."""
    top = float(np.percentile(crop, 99.5))
    return top if top > 0 else 1.0
