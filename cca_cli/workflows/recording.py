"""Simulated recording from a config: the stored grid, the noise settings, and the captures file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cca_cli.config.model import NoiseSection, RunConfig
from cca_cli.errors import ConfigError
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, write_dataset
from cca_cli.library.simulation import Noise, record
from cca_cli.workflows.scenes import bars_to_table, usaf_to_table

__all__ = ["stored_grid", "noise_settings", "simulation_error", "recorded", "write_captures"]


def stored_grid(config: RunConfig, sensor_pixels: int, lowres_size: int) -> tuple[int, float]:
    """Side and pixel pitch (m) of the stored images: the sensor grid, or the band grid (``simulate.store``)."""
    size = sensor_pixels if config.simulate.store == "sensor" else lowres_size
    return size, config.optics.pixel_pitch_m * sensor_pixels / size


def noise_settings(section: NoiseSection) -> Noise:
    """The library's noise settings from a config's noise section."""
    return Noise(model=section.model, snr_db=section.snr_db, photons_per_unit=section.photons_per_unit,
                 read_noise_e=section.read_noise_e, seed=section.seed)


def simulation_error(exc: ValueError) -> ConfigError:
    """A refusal of :mod:`cca_cli.library.simulation` as one line naming the config key."""
    text = str(exc).replace("raise photons_per_unit", "raise noise.photons_per_unit")
    return ConfigError(("noise." if text.startswith("photons_per_unit") else "simulate: ") + text)


def recorded(band: np.ndarray, size: int, noise: Noise, **kwargs) -> np.ndarray:
    """:func:`cca_cli.library.simulation.record` with its refusals as one line naming the config key."""
    try:
        return record(band, size, noise, **kwargs)
    except ValueError as exc:
        raise simulation_error(exc) from None


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
