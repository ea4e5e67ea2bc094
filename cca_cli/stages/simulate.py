"""Stage `simulate`: a scene seen by a scanned camera → captures.h5."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.config.model import RunConfig
from cca_cli.errors import ConfigError
from cca_cli.io.h5 import Provenance, check_output
from cca_cli.library.simulation import simulate as simulate_images
from cca_cli.library.simulation import simulation_layout
from cca_cli.optics.field_aberration import node_positions, seidel_waves
from cca_cli.sampling.geometry import CaptureGeometry, camera_scan_geometry
from cca_cli.sampling.grid import BandLayout
from cca_cli.sampling.overlap import grid_for_sar
from cca_cli.stages.progress import ProgressFn, silent
from cca_cli.workflows.recording import noise_settings, simulation_error, stored_grid, write_captures
from cca_cli.workflows.scenes import Scene, build_scene

__all__ = ["SECTIONS", "Simulation", "simulate", "run"]

#: Config sections this stage depends on.
SECTIONS = ("optics", "scene", "array", "noise", "simulate", "multiplex", "aberration")


@dataclass(frozen=True)
class Simulation:
    """Simulated captures and their ground truth."""

    geometry: CaptureGeometry
    layout: BandLayout
    scene: Scene
    intensity: np.ndarray  # (K, N, N) float32, sensor units
    pixel_pitch_m: float
    aberration: dict | None = None   # field-varying aberration: node coefficients and positions (truth)


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
        layout = simulation_layout(geometry)
    except ValueError as exc:
        raise ConfigError(f"optics/array: {exc}") from None
    scene = build_scene(config.scene, layout.hires_size)
    store_size, pitch = stored_grid(config, sensor_pixels, layout.lowres_size)
    aberration = None if config.aberration is None else field_aberration_truth(config.aberration, store_size)
    try:
        intensity = simulate_images(scene.field, geometry, noise=noise_settings(config.noise), store_size=store_size,
                                    aberration=None if aberration is None else aberration["waves"], progress=progress)
    except ValueError as exc:
        raise simulation_error(exc) from None
    return Simulation(geometry=geometry, layout=layout, scene=scene, intensity=intensity, pixel_pitch_m=pitch,
                      aberration=aberration)


def field_aberration_truth(section, frame_pixels: int) -> dict:
    """Zernike coefficients (waves) at the ``nodes x nodes`` field points of ``aberration``, and where they sit."""
    positions = node_positions(section.nodes, frame_pixels)
    half = (frame_pixels - 1) / 2.0
    h = (positions - half) / (frame_pixels / 2.0)
    grid = np.stack(np.meshgrid(h, h, indexing="ij"), axis=-1)
    waves = seidel_waves(grid, defocus_waves=section.defocus_waves, field_curvature_waves=section.field_curvature_waves,
                         astigmatism_waves=section.astigmatism_waves, coma_waves=section.coma_waves)
    return {"waves": waves, "nodes_px": positions}


def run(config: RunConfig, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> Simulation:
    """Simulate and write ``output`` (multiplexed captures when the config has a ``multiplex`` section)."""
    check_output(output, force=force)
    if config.multiplex is not None:
        if config.aberration is not None:
            raise ConfigError("aberration: multiplexed captures are simulated with a perfect lens; leave out the "
                              "aberration section or multiplex")
        from cca_cli.workflows import multiplex

        return multiplex.run_simulate(config, output, provenance=provenance, force=force, progress=progress)
    simulation = simulate(config, progress=progress)
    write_captures(output, simulation, provenance, force=force)
    return simulation
