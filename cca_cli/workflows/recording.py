"""Simulated recording: band-grid images → noisy images on the stored grid, and the captures file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cca_cli.config.model import NoiseSection, RunConfig
from cca_cli.errors import ConfigError
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, write_dataset
from cca_cli.optics import fft
from cca_cli.optics.noise import add_gaussian_noise, add_shot_and_read_noise
from cca_cli.progress import ProgressEvent, ProgressFn, silent
from cca_cli.workflows.scenes import bars_to_table, usaf_to_table

__all__ = ["stored_grid", "record", "record_all", "write_captures"]


def stored_grid(config: RunConfig, sensor_pixels: int, lowres_size: int) -> tuple[int, float]:
    """Side and pixel pitch (m) of the stored images: the sensor grid, or the band grid (``simulate.store``)."""
    size = sensor_pixels if config.simulate.store == "sensor" else lowres_size
    return size, config.optics.pixel_pitch_m * sensor_pixels / size


def record(band: np.ndarray, size: int, noise: NoiseSection, rng: np.random.Generator) -> np.ndarray:
    """Band-grid images (K, m, m) → float32 images (K, size, size) with ``noise`` added."""
    block = fft.fourier_resample(band, size)
    if noise.model == "gaussian":
        return add_gaussian_noise(block, noise.snr_db, rng)
    if noise.model == "poisson":
        return add_shot_and_read_noise(block, photons_per_unit=noise.photons_per_unit,
                                       read_noise_e=noise.read_noise_e, rng=rng)
    return block


def record_all(band: np.ndarray, size: int, noise: NoiseSection, rng: np.random.Generator, *,
               progress: ProgressFn = silent, step: int = 16) -> np.ndarray:
    """:func:`record` in blocks of ``step`` images, reporting ``simulate/captures`` progress after each."""
    k = band.shape[0]
    if noise.model == "poisson" and float(band.max(initial=0.0)) * noise.photons_per_unit < 1:
        raise ConfigError(f"noise.photons_per_unit: the brightest pixel would collect "
                          f"{float(band.max(initial=0.0)) * noise.photons_per_unit:.2g} photo-electrons, so the images "
                          "would hold noise only; raise noise.photons_per_unit")
    intensity = np.empty((k, size, size), np.float32)
    for start in range(0, k, step):
        intensity[start:start + step] = record(band[start:start + step], size, noise, rng)
        progress(ProgressEvent("simulate", "captures", min(start + step, k), k))
    if not intensity.any():
        raise ConfigError("simulate: every simulated image is zero (a black scene, or too few photons: "
                          "noise.photons_per_unit); nothing could be recovered from it")
    return intensity


def write_captures(path: Path, simulation, provenance: Provenance, *, force: bool = False,
                   extra=None) -> None:
    """Write ``captures.h5`` atomically.

    ``simulation`` is the simulate stage's :class:`~cca_cli.stages.simulate.Simulation` or a
    :class:`~cca_cli.workflows.multiplex.MultiplexSimulation` (same fields);
    ``extra(handle)`` writes further groups (multiplexed runs add /multiplex).
    """
    geometry = simulation.geometry
    if simulation.pixel_pitch_m != geometry.pixel_pitch_m:
        from dataclasses import replace

        geometry = replace(geometry, pixel_pitch_m=simulation.pixel_pitch_m)
    with atomic_h5(path, provenance, force=force) as handle:
        write_dataset(handle, "/measurements/intensity", simulation.intensity, layout="centred sensor",
                      boundary="periodic")
        write_geometry(handle, geometry)
        write_dataset(handle, "/truth/object", simulation.scene.field)
        if simulation.scene.bars:
            write_dataset(handle, "/truth/bars", bars_to_table(simulation.scene.bars))
        if simulation.scene.usaf:
            write_dataset(handle, "/truth/usaf", usaf_to_table(simulation.scene.usaf, simulation.scene.usaf_size))
        aberration = getattr(simulation, "aberration", None)
        if aberration is not None:
            from cca_cli.optics.field_aberration import MODES

            write_dataset(handle, "/truth/aberration_waves", aberration["waves"], zernike_modes=np.asarray(MODES))
            write_dataset(handle, "/truth/aberration_nodes_px", aberration["nodes_px"])
        if extra is not None:
            extra(handle)
        handle.attrs["simulation_grid"] = simulation.layout.hires_size
