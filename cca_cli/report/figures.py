"""PNG figures of a reconstruction. The only module that imports matplotlib."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_figures"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _image(plt, path: Path, image: np.ndarray, title: str, *, cmap: str = "gray", extent_mm: float | None = None,
           label: str = "") -> None:
    fig, ax = plt.subplots(figsize=(5.2, 4.6), dpi=110)
    extent = None if extent_mm is None else (-extent_mm / 2, extent_mm / 2, extent_mm / 2, -extent_mm / 2)
    shown = ax.imshow(image, cmap=cmap, extent=extent, interpolation="nearest")
    ax.set_title(title)
    if extent_mm is not None:
        ax.set_xlabel("x at object (mm)")
        ax.set_ylabel("y at object (mm)")
    fig.colorbar(shown, ax=ax, label=label)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


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
    for cy, cx in np.asarray(pupil_centres_px):
        ax.plot(cx + pupil_radius_px * np.cos(theta), cy + pupil_radius_px * np.sin(theta), lw=0.4, color="cyan",
                alpha=0.6)
    ax.set_title("Recovered spectrum (log10 |S|) and aperture footprints")
    ax.set_xlabel("spectrum px (x)")
    ax.set_ylabel("spectrum px (y)")
    fig.tight_layout()
    fig.savefig(target("spectrum.png"))
    plt.close(fig)

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
        fig.tight_layout()
        fig.savefig(target("contrast.png"))
        plt.close(fig)

    if len(residual):
        fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
        it = np.arange(1, len(residual) + 1)
        ax.semilogy(it, residual, label="data residual")
        ax.semilogy(it, np.maximum(change, 1e-12), label="relative change")
        ax.set_xlabel("iteration")
        ax.set_ylabel("relative value")
        ax.set_title("Convergence")
        ax.legend()
        fig.tight_layout()
        fig.savefig(target("convergence.png"))
        plt.close(fig)
    return paths
