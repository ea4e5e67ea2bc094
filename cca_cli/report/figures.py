"""PNG figures of a reconstruction. The only module that imports matplotlib."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_comparison_figures", "write_coverage_figure", "write_figures"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path: Path) -> Path:
    """Lay out ``fig``, write it to ``path`` and close it."""
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _image(plt, path: Path, image: np.ndarray, title: str, *, cmap: str = "gray", extent_mm: float | None = None,
           label: str = "") -> None:
    fig, ax = plt.subplots(figsize=(5.2, 4.6), dpi=110)
    height_mm = None if extent_mm is None else extent_mm * image.shape[0] / image.shape[1]
    extent = None if extent_mm is None else (-extent_mm / 2, extent_mm / 2, height_mm / 2, -height_mm / 2)
    shown = ax.imshow(image, cmap=cmap, extent=extent, interpolation="nearest")
    ax.set_title(title)
    if extent_mm is not None:
        ax.set_xlabel("x at object (mm)")
        ax.set_ylabel("y at object (mm)")
    fig.colorbar(shown, ax=ax, label=label)
    _save(plt, fig, path)


def write_figures(directory: Path, *, observed: np.ndarray, recovered_object: np.ndarray, spectrum: np.ndarray,
                  pupil_centres_px: np.ndarray, pupil_radius_px: float, field_width_m: float,
                  residual: np.ndarray, change: np.ndarray, summary: dict, truth: np.ndarray | None = None) -> list[Path]:
    """Write the report's PNGs into ``directory`` and return their paths."""
    plt = _plt()
    directory = Path(directory)
    width_mm = field_width_m * 1e3
    paths = []

    def target(name: str) -> Path:
        path = directory / name
        paths.append(path)
        return path

    _image(plt, target("observed_centre.png"), observed, "Observed centre image", extent_mm=width_mm,
           label="irradiance")
    _image(plt, target("recovered_magnitude.png"), np.abs(recovered_object),
           f"Recovered magnitude (SAR {summary['sar']:.2f})", extent_mm=width_mm, label="√irradiance")
    _image(plt, target("recovered_phase.png"), np.angle(recovered_object), "Recovered phase", cmap="twilight",
           extent_mm=width_mm, label="rad")
    if truth is not None:
        _image(plt, target("truth.png"), truth, "Ground truth intensity", extent_mm=width_mm, label="irradiance")

    fig, ax = plt.subplots(figsize=(5.6, 5), dpi=110)
    m = spectrum.shape[-1]
    log_mag = np.log10(np.abs(spectrum) + 1e-6 * np.abs(spectrum).max())
    half = m / 2
    ax.imshow(log_mag, cmap="magma", extent=(-half, half, half, -half))
    theta = np.linspace(0, 2 * np.pi, 96)
    centres = np.asarray(pupil_centres_px)
    nearest = int(np.argmin(np.hypot(centres[:, 0], centres[:, 1])))
    faint = 0.25 if len(centres) > 50 else 0.6
    for i, (cy, cx) in enumerate(centres):
        ax.plot(cx + pupil_radius_px * np.cos(theta), cy + pupil_radius_px * np.sin(theta),
                lw=1.2 if i == nearest else 0.3, color="white" if i == nearest else "cyan",
                alpha=1.0 if i == nearest else faint)
    ax.set_title("Recovered spectrum (log10 |S|) and aperture footprints")
    ax.set_xlabel("spectrum px (x)")
    ax.set_ylabel("spectrum px (y)")
    _save(plt, fig, target("spectrum.png"))

    if "contrast_observed" in summary:
        fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
        for key, style, name in (("contrast_observed", "--", "observed"), ("contrast_recovered", "-", "recovered")):
            table = summary[key]
            widths = np.asarray(table["widths_px"])
            ax.plot(widths, table["horizontal"], style, marker="o", ms=3, label=f"{name}, horizontal bars")
            ax.plot(widths, table["vertical"], style, marker="s", ms=3, label=f"{name}, vertical bars")
        ax.axhline(summary.get("mtf_threshold", 0.2), color="gray", lw=0.8, ls=":")
        ax.set_xlabel("bar width (object px)")
        ax.set_ylabel("contrast (w̄ − b̄)/(w̄ + b̄)")
        ax.invert_xaxis()
        ax.set_title("Bar contrast vs width")
        ax.legend(fontsize=7)
        _save(plt, fig, target("contrast.png"))

    if len(residual):
        fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
        it = np.arange(1, len(residual) + 1)
        ax.semilogy(it, residual, label="data residual")
        ax.semilogy(it, np.maximum(change, 1e-12), label="relative change")
        ax.set_xlabel("iteration")
        ax.set_ylabel("relative value")
        ax.set_title("Convergence")
        ax.legend()
        _save(plt, fig, target("convergence.png"))
    return paths


def write_comparison_figures(directory: Path, images: dict, summary: dict) -> list[Path]:
    """Side-by-side images (truth, observed, baselines, recovered) and contrast curves with the baselines.

    Parameters
    ----------
    directory : Path
    images : dict
        ``name → intensity`` on the truth grid (``truth``, ``observed``, ``recovered`` and baseline labels).
    summary : dict
        The report; ``baselines`` entries provide the baselines' contrast tables.

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
    cols = min(3, len(order))
    rows = -(-len(order) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 4 * rows), dpi=100, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, name in zip(axes.ravel(), order):
        image = np.asarray(images[name])
        ax.imshow(image, cmap="gray", vmin=0, vmax=float(np.percentile(image, 99.5)) or None,
                  interpolation="nearest")
        extra = ""
        if name in summary.get("baselines", {}):
            mtf = summary["baselines"][name].get("mtf20_px")
            extra = f"\nMTF20 {mtf} px" if mtf is not None else ""
        elif name in ("observed", "recovered") and f"mtf20_{name}_px" in summary:
            extra = f"\nMTF20 {summary[f'mtf20_{name}_px']} px"
        ax.set_title(name.replace("_", " ") + extra, fontsize=9)
    paths.append(_save(plt, fig, directory / "comparison.png"))

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
        ax.set_xlabel("bar width (object px)")
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
