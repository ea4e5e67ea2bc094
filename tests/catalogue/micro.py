"""The micro config and the library of files the catalogue's cases copy.

The micro run (a 64-px chart, 3 x 3 grid, 3 iterations) simulates, reconstructs
and reports in about a second, so every case can copy real, complete files.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import yaml

#: 64-px chart, 8 mm field at 50 m (125 µm object pixels), 3 x 3 grid at 61 %, band storage, 3 iterations.
MICRO_CONFIG = {
    "run": {"stages": ["simulate", "reconstruct", "report"]},
    "optics": {"wavelength_m": 550e-9, "focal_length_m": 0.8, "aperture_diameter_m": 18e-3,
               "pixel_pitch_m": 2e-6, "distance_m": 50.0},
    "scene": {"kind": "resolution_chart", "size_px": 64, "field_width_m": 8e-3, "widths_px": [4, 3, 2, 1]},
    "array": {"grid": 3, "overlap": 0.61},
    "noise": {"model": "gaussian", "snr_db": 30.0, "seed": 1},
    "simulate": {"store": "band"},
    "reconstruct": {"engine": "altmin", "tau": 1e-3, "iterations": 3, "tol": 0.0},
    "report": {"mtf_threshold": 0.2, "figures": False},
}


@dataclass(frozen=True)
class Library:
    """Complete files of one micro run: what the cases copy."""

    config: Path
    captures: Path
    recon: Path
    report: Path          # report folder (no figures)
    run_dir: Path         # a `cca run` folder with figures (captures.h5, recon.h5, report/)
    manifest_dir: Path    # a tiny lab capture: manifest.yaml + PNGs


def micro_config() -> dict:
    """A fresh copy of :data:`MICRO_CONFIG`."""
    return copy.deepcopy(MICRO_CONFIG)


def write_manifest(directory: Path) -> None:
    import numpy as np

    from cca_cli.io.images import write_image

    directory.mkdir()
    images = []
    for r in range(3):
        for c in range(3):
            name = f"view_r{r}c{c}.png"
            pixels = (np.random.default_rng(r * 3 + c).random((32, 32)) * 4000).astype(np.uint16)
            write_image(directory / name, pixels)
            images.append({"path": name, "exposure_s": 0.01, "grid": [r, c]})
    manifest = {
        "optics": {"wavelength_m": 550e-9, "focal_length_m": 0.1, "aperture_diameter_m": 4.6e-3,
                   "pixel_pitch_m": 2.5e-6, "distance_m": 10},
        "sensor": {"black_level": 0, "bit_depth": 12},
        "stage_pitch_mm": 1.8,
        "images": images,
    }
    (directory / "manifest.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))


