"""Multiplexed-illumination branches of the simulate, reconstruct and report stages (called by each).

Used when a config has a ``multiplex`` section (simulate) or a captures file
has a ``/multiplex`` group (reconstruct, report). Files keep the single-source
schema: ``/measurements/intensity`` holds one image per (pattern, camera),
``/geometry`` describes the virtual captures (one pupil per camera, pattern
and active source) and ``/multiplex`` says which virtual captures add up to
which image. ``/observed/centre`` is the reference a single camera records:
the on-axis camera under the on-axis source alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReconstructSection, RunConfig
from cca_cli.engines.multiplex import MultiplexedProblem
from cca_cli.engines.registry import engine_names, get_engine
from cca_cli.errors import CcaError, ConfigError, InputError
from cca_cli.io.captures import read_measurements
from cca_cli.io.h5 import Provenance, check_output, open_input, write_dataset
from cca_cli.io.measurements import INTENSITY
from cca_cli.io.multiplex import is_multiplexed_file, read_multiplex, write_multiplex
from cca_cli.io.recon import write_recon
from cca_cli.io.schema import OBSERVED
from cca_cli.library.data import CaptureSet, Reconstruction, constant_images
from cca_cli.library.recovery import DivergedError, check_dead_measurements, drive_engine
from cca_cli.optics import fft
from cca_cli.optics.multiplex import (MultiplexGeometry, MultiplexedForwardModel, coverage_map, design_band,
                                      random_patterns, rect_lattice)
from cca_cli.sampling.geometry import CaptureGeometry, camera_scan_geometry
from cca_cli.sampling.grid import BandLayout
from cca_cli.progress import ProgressFn, silent
from cca_cli.workflows.recording import noise_settings, recorded, stored_grid, write_captures
from cca_cli.workflows.recovery import engine_options
from cca_cli.workflows.scenes import Scene, build_scene
from cca_cli.units import FourierScale

__all__ = ["MultiplexSimulation", "MultiplexedCaptures", "multiplex_geometry", "simulate_multiplexed",
           "write_multiplexed_captures", "read_multiplexed_captures", "reconstruct_multiplexed",
           "run_simulate", "run_reconstruct", "is_multiplexed_file", "coverage_summary"]


@dataclass(frozen=True)
class MultiplexSimulation:
    """Simulated multiplexed images, their geometry and the single-camera reference."""

    geometry: CaptureGeometry          # the virtual captures
    multiplex: MultiplexGeometry
    layout: BandLayout
    scene: Scene
    intensity: np.ndarray              # (G, N, N) float32, sensor units
    reference: np.ndarray              # (N, N) on-axis camera, on-axis source
    pixel_pitch_m: float


@dataclass(frozen=True)
class MultiplexedCaptures:
    """Multiplexed images read from a captures file."""

    captures: CaptureSet               # intensity (G, N, N), geometry of the virtual captures
    multiplex: MultiplexGeometry
    reference: np.ndarray | None


def multiplex_geometry(config: RunConfig) -> tuple[MultiplexGeometry, CaptureGeometry, int]:
    """Cameras, sources and patterns of ``config.multiplex`` in spectrum pixels.

    Returns
    -------
    multiplex : MultiplexGeometry
    virtual : CaptureGeometry
        One entry per virtual capture; ``aperture_centres_yx_m`` is the
        equivalent aperture position ``c_p + s_q`` in metres.
    sensor_pixels : int

    Raises
    ------
    ConfigError
        If the sources produce no overlap between neighbouring spectrum regions.
    """
    optics, section = config.optics, config.multiplex
    try:
        single, sensor_pixels = camera_scan_geometry(
            wavelength_m=optics.wavelength_m, focal_length_m=optics.focal_length_m,
            aperture_diameter_m=optics.aperture_diameter_m, pixel_pitch_m=optics.pixel_pitch_m,
            distance_m=optics.distance_m, field_width_m=config.scene.field_width_m, grid=1, overlap=0.0)
    except ValueError as exc:
        raise ConfigError(f"optics/scene: {exc}") from None
    scale = FourierScale.fraunhofer(optics.wavelength_m, optics.distance_m, single.field_width_m)
    radius = single.pupil_radius_px
    diameter_px = 2.0 * radius
    camera_pitch_m = optics.aperture_diameter_m if section.camera_pitch_m == "abutting" else section.camera_pitch_m
    cameras = scale.to_pixels(rect_lattice(*section.camera_grid, camera_pitch_m))
    if section.source_overlap is not None:
        source_pitch_px = (1.0 - section.source_overlap) * diameter_px
        where = "multiplex.source_overlap"
    else:
        source_pitch_px = float(scale.illumination_shift_px(section.source_pitch_m, section.source_distance_m,
                                                            optics.distance_m))
        where = "multiplex.source_pitch_m"
    q = section.n_sources
    if q > 1 and source_pitch_px >= diameter_px:
        limit_m = section.source_distance_m * float(scale.to_metres(diameter_px)) / optics.distance_m \
            if section.source_distance_m else float("nan")
        raise ConfigError(
            f"{where}: neighbouring sources shift the spectrum by {source_pitch_px:.1f} px, at least the aperture's "
            f"{diameter_px:.1f} px, so they produce no overlap and phases cannot be retrieved; "
            + (f"use source_pitch_m < {limit_m:.4g}" if np.isfinite(limit_m) else "use source_overlap in (0, 1)"))
    if q == 1 and section.camera_grid != (1, 1) and float(scale.to_pixels(camera_pitch_m)) >= diameter_px:
        raise ConfigError("multiplex.source_grid: one source and cameras that do not overlap produce no overlap "
                          "between spectrum regions; add sources (source_grid) or bring the cameras closer")
    sources = rect_lattice(*section.source_grid, source_pitch_px)
    if section.pattern_list is not None:
        patterns = tuple(tuple(int(s) for s in p) for p in section.pattern_list)
    else:
        patterns = random_patterns(q, section.n_mux, section.patterns, seed=section.pattern_seed)
    try:
        mux = MultiplexGeometry(camera_centres_px=cameras, source_shifts_px=sources, patterns=patterns,
                                pupil_radius_px=radius, camera_shape=tuple(section.camera_grid),
                                source_shape=tuple(section.source_grid))
    except ValueError as exc:
        raise ConfigError(f"multiplex: {exc}") from None
    cols = section.camera_grid[1]
    camera = mux.virtual_camera
    virtual = CaptureGeometry(
        wavelength_m=single.wavelength_m, focal_length_m=single.focal_length_m,
        aperture_diameter_m=single.aperture_diameter_m, pixel_pitch_m=single.pixel_pitch_m,
        distance_m=single.distance_m, field_width_m=single.field_width_m,
        aperture_centres_yx_m=scale.to_metres(mux.virtual_centres_px),
        spectrum_centres_yx_px=mux.virtual_centres_px,
        grid_indices=np.stack([camera // cols, camera % cols], axis=1).astype(np.int32),
        pupil_radius_px=radius, overlap=mux.neighbour_overlap())
    return mux, virtual, sensor_pixels


def _reference_geometry(mux: MultiplexGeometry) -> MultiplexGeometry:
    """One camera and one source, both on the optical axis."""
    return MultiplexGeometry(camera_centres_px=np.zeros((1, 2)), source_shifts_px=np.zeros((1, 2)),
                             patterns=((0,),), pupil_radius_px=mux.pupil_radius_px, camera_shape=(1, 1),
                             source_shape=(1, 1))


def simulate_multiplexed(config: RunConfig, *, progress: ProgressFn = silent) -> MultiplexSimulation:
    """Simulate every (pattern, camera) image of ``config.multiplex`` (no file I/O)."""
    mux, virtual, sensor_pixels = multiplex_geometry(config)
    try:
        model = MultiplexedForwardModel(mux, sensor_size=sensor_pixels)
    except ValueError as exc:
        raise ConfigError(f"optics/multiplex: {exc}") from None
    # The truth grid is a whole multiple of the scene's pixels (charts stay exact) that holds the design's band.
    scene_px = config.scene.size_px
    truth_size = scene_px * -(-model.layout.hires_size // scene_px)
    model = MultiplexedForwardModel(mux, sensor_size=sensor_pixels, hires_size=truth_size)
    layout = model.layout
    scene = build_scene(config.scene, layout.hires_size)
    spectrum = fft.fft2c(scene.field).astype(np.complex64)
    band = model.sensor_intensity(spectrum)
    reference_band = MultiplexedForwardModel(_reference_geometry(mux), sensor_size=sensor_pixels,
                                             hires_size=layout.hires_size).sensor_intensity(spectrum)

    store_size, pitch = stored_grid(config, sensor_pixels, layout.lowres_size)
    noise = noise_settings(config.noise)
    rng = np.random.default_rng(noise.seed)
    intensity = recorded(band, store_size, noise, rng=rng, progress=progress)
    reference = recorded(reference_band, store_size, noise, rng=rng)[0]
    return MultiplexSimulation(geometry=virtual, multiplex=mux, layout=layout, scene=scene, intensity=intensity,
                               reference=reference, pixel_pitch_m=pitch)


def write_multiplexed_captures(path: Path, simulation: MultiplexSimulation, provenance: Provenance, *,
                               force: bool = False) -> None:
    """Write a multiplexed ``captures.h5`` atomically: the simulate stage's file plus /multiplex and the reference."""

    def extra(handle) -> None:
        write_multiplex(handle, simulation.multiplex)
        write_dataset(handle, OBSERVED, simulation.reference)

    write_captures(path, simulation, provenance, force=force, extra=extra)


def run_simulate(config: RunConfig, output: Path, *, provenance: Provenance, force: bool = False,
                 progress: ProgressFn = silent) -> MultiplexSimulation:
    """Simulate the multiplexed captures of ``config`` and write ``output``."""
    check_output(output, force=force)
    simulation = simulate_multiplexed(config, progress=progress)
    write_multiplexed_captures(output, simulation, provenance, force=force)
    return simulation


def read_multiplexed_captures(path: Path) -> MultiplexedCaptures:
    """Read images, virtual-capture geometry, /multiplex and the reference, checking their agreement."""
    with open_input(path) as handle:
        captures = read_measurements(handle, Path(path))
        mux = read_multiplex(handle)
        reference = np.asarray(handle[OBSERVED], np.float32) if OBSERVED in handle else None
    g = captures.intensity.shape[0]
    if g != mux.n_measurements:
        raise InputError(f"{path}: {g} images but /multiplex describes {mux.n_cameras} cameras x "
                         f"{mux.n_patterns} patterns = {mux.n_measurements}")
    if captures.geometry.n_images != mux.n_virtual:
        raise InputError(f"{path}: /geometry has {captures.geometry.n_images} positions but /multiplex has "
                         f"{mux.n_virtual} virtual captures")
    return MultiplexedCaptures(captures=captures, multiplex=mux, reference=reference)


def reconstruct_multiplexed(data: MultiplexedCaptures, section: ReconstructSection, *, source: Path,
                            progress: ProgressFn = silent) -> Reconstruction:
    """Run the configured engine's multiplexed form on ``data`` (read from ``source``)."""
    captures = data.captures
    name, options = engine_options(section, "simulation")
    engine_class = get_engine(name).multiplexed_class()
    if engine_class is None:
        able = [n for n in engine_names() if get_engine(n).multiplexed is not None]
        raise ConfigError(f"reconstruct.engine: {section.engine!r} cannot use multiplexed captures ({source}); "
                          f"choose one of {', '.join(able)}")
    weight, dead = _without_dead_measurements(data, source)
    try:
        model = MultiplexedForwardModel(data.multiplex, sensor_size=captures.intensity.shape[-1])
        problem = MultiplexedProblem.from_sensor_images(model, captures.intensity, weight)
    except ValueError as exc:
        raise InputError(f"{source}: {exc}") from None
    engine = engine_class(problem, options)
    try:
        spectrum, history, seconds = drive_engine(engine, options, progress=progress)
    except DivergedError as exc:
        raise CcaError(f"reconstruct: the recovery diverged (NaN or Inf after {exc.iterations} iterations), so "
                       "nothing was written; raise reconstruct.tau or choose other reconstruct.options") from None
    observed = data.reference if data.reference is not None else captures.intensity[0]
    return Reconstruction(object=fft.ifft2c(spectrum).astype(np.complex64), spectrum=spectrum, history=history,
                          geometry=captures.geometry, engine=name, options=options.model_dump(), seconds=seconds,
                          stopped_by=engine.stop_reason(), observed=observed, truth=dict(captures.truth),
                          units=captures.units, band_grid_px=model.layout.lowres_size, dropped=dead)


def _without_dead_measurements(data: MultiplexedCaptures, source: Path) -> tuple[np.ndarray | None, tuple[int, ...]]:
    """The measurements' weights with dead ones (an image of one value: nothing was recorded) at 0, and those,
    by the rule dead captures follow (:func:`~cca_cli.library.recovery.check_dead_measurements`)."""
    intensity = data.captures.intensity
    dead = constant_images(intensity)
    if dead.size == 0:
        return data.captures.weight, ()
    check_dead_measurements(dead, [float(intensity[i].flat[0]) for i in dead], intensity.shape[0],
                            observed_first=data.reference is None, name=INTENSITY, source=source, error=InputError)
    weight = np.ones(intensity.shape, np.float32) if data.captures.weight is None \
        else np.array(data.captures.weight, np.float32)
    weight[dead] = 0.0
    return weight, tuple(int(i) for i in dead)


def run_reconstruct(captures_path: Path, section: ReconstructSection, output: Path, *, provenance: Provenance,
                    force: bool = False, progress: ProgressFn = silent) -> Reconstruction:
    """Read multiplexed captures, reconstruct, write ``output`` (with /multiplex, and the reference as the
    observed image)."""
    check_output(output, force=force)
    data = read_multiplexed_captures(captures_path)
    result = reconstruct_multiplexed(data, section, source=captures_path, progress=progress)
    write_recon(output, result, provenance, force=force, extra=lambda handle: write_multiplex(handle, data.multiplex))
    return result


def coverage_summary(multiplex: MultiplexGeometry, size: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """Coverage numbers of a multiplexed design on a ``size`` spectrum grid.

    Returns
    -------
    stats : dict
        ``coverage_zero_fraction`` (share of the design band that no
        measurement constrains: holes), ``coverage_single_fraction`` (share
        constrained by exactly one measurement: no redundancy to retrieve
        phase from), ``coverage_mean`` and ``coverage_max`` inside the band,
        plus the design's counts.
    coverage : ndarray, int32, (size, size)
    band : ndarray, bool, (size, size)
        Union of every (camera, source) region the array could measure.
    """
    coverage = coverage_map(multiplex, size)
    band = design_band(multiplex, size)
    inside = coverage[band]
    n = max(int(band.sum()), 1)
    stats = {
        "multiplex_cameras": multiplex.n_cameras,
        "multiplex_sources": multiplex.n_sources,
        "multiplex_patterns": multiplex.n_patterns,
        "multiplex_n_mux": [len(p) for p in multiplex.patterns],
        "multiplex_measurements": multiplex.n_measurements,
        "multiplex_source_overlap": round(multiplex.neighbour_overlap(), 4),
        "coverage_zero_fraction": round(float(np.count_nonzero(inside == 0)) / n, 4),
        "coverage_single_fraction": round(float(np.count_nonzero(inside == 1)) / n, 4),
        "coverage_mean": round(float(inside.mean()), 3) if inside.size else 0.0,
        "coverage_max": int(coverage.max()),
    }
    return stats, coverage, band
