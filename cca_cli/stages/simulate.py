"""Stage `simulate`: a scene seen by a scanned camera → captures.h5."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.config.model import NoiseSection, RunConfig
from cca_cli.errors import ConfigError
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, write_dataset
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.noise import add_gaussian_noise, add_shot_and_read_noise
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.geometry import CaptureGeometry, camera_scan_geometry
from cca_cli.sampling.grid import BandLayout, band_layout
from cca_cli.sampling.overlap import grid_for_sar
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent
from cca_cli.stages.scene import Scene, bars_to_table, build_scene, usaf_to_table

__all__ = ["SECTIONS", "Simulation", "simulate", "stored_grid", "record", "record_all", "write_captures", "run"]

#: Config sections this stage depends on.
SECTIONS = ("optics", "scene", "array", "noise", "simulate", "multiplex")


@dataclass(frozen=True)
class Simulation:
    """Simulated captures and their ground truth."""

    geometry: CaptureGeometry
    layout: BandLayout
    scene: Scene
    intensity: np.ndarray  # (K, N, N) float32, sensor units
    pixel_pitch_m: float


def simulation_geometry(config: RunConfig) -> tuple[CaptureGeometry, int]:
    """Capture geometry and sensor pixel count of a config (``array.sar`` resolved to a grid)."""
    optics, array = config.optics, config.array
    grid = array.grid if array.grid is not None else grid_for_sar(array.sar, array.overlap)
    try:
        return camera_scan_geometry(
            wavelength_m=optics.wavelength_m, focal_length_m=optics.focal_length_m,
            aperture_diameter_m=optics.aperture_diameter_m, pixel_pitch_m=optics.pixel_pitch_m,
            distance_m=optics.distance_m, field_width_m=config.scene.field_width_m,
            grid=grid, overlap=array.overlap)
    except ValueError as exc:
        raise ConfigError(f"optics/scene: {exc}") from None


def simulate(config: RunConfig, *, progress: ProgressFn = silent) -> Simulation:
    """Simulate every capture of the configured array (no file I/O).

    Returns
    -------
    Simulation
        Captures on the sensor grid (or on the band grid with ``simulate.store: band``),
        with noise as configured.
    """
    geometry, sensor_pixels = simulation_geometry(config)
    try:
        layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, sensor_size=sensor_pixels)
    except ValueError as exc:
        raise ConfigError(f"optics/array: {exc}") from None
    scene = build_scene(config.scene, layout.hires_size)
    model = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px))
    spectrum = fft.fft2c(scene.field).astype(np.complex64)
    band = model.sensor_intensity(spectrum)

    store_size, pitch = stored_grid(config, sensor_pixels, layout.lowres_size)
    rng = np.random.default_rng(config.noise.seed)
    intensity = record_all(band, store_size, config.noise, rng, progress=progress)
    return Simulation(geometry=geometry, layout=layout, scene=scene, intensity=intensity, pixel_pitch_m=pitch)


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


def write_captures(path: Path, simulation: Simulation, provenance: Provenance, *, force: bool = False,
                   extra=None) -> None:
    """Write ``captures.h5`` atomically.

    ``simulation`` may also be a multiplexed simulation (same fields);
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
        if extra is not None:
            extra(handle)
        handle.attrs["simulation_grid"] = simulation.layout.hires_size


def run(config: RunConfig, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> Simulation:
    """Simulate and write ``output`` (multiplexed captures when the config has a ``multiplex`` section)."""
    check_output(output, force=force)
    if config.multiplex is not None:
        from cca_cli.stages import multiplex

        return multiplex.run_simulate(config, output, provenance=provenance, force=force, progress=progress)
    simulation = simulate(config, progress=progress)
    write_captures(output, simulation, provenance, force=force)
    return simulation
