"""Stage `reconstruct`: captures → recovered high-resolution object (recon.h5)."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.base import History, IterationRecord, run_engine
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.registry import get_engine
from cca_cli.errors import CcaError, ConfigError, InputError
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, open_input, require, write_dataset
from cca_cli.io.measurements import read_intensity, read_weight
from cca_cli.io.schema import spec_for
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import BandLayout, band_layout
from cca_cli.sampling.region import RegionEmbedding, plan_embedding
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent

__all__ = ["SECTIONS", "Captures", "Recovery", "read_captures", "read_measurements", "build_model", "reconstruct",
           "embed_region", "run"]

SECTIONS = ("reconstruct",)


@dataclass(frozen=True)
class Captures:
    """Measurements and geometry read from a captures file."""

    path: Path
    intensity: np.ndarray
    weight: np.ndarray | None
    geometry: CaptureGeometry
    truth: dict
    units: str | None = None   # units of /measurements/intensity when they are not the schema's (counts/s)
    boundary: str = "periodic"                 # "open": a window on a larger scene (recorded frames)
    defocus_m: float | None = None             # known defocus from the manifest (for the engines)
    initial_pupil: np.ndarray | None = None    # (P, P) complex64 on the NA disc, from the manifest


@dataclass(frozen=True)
class Recovery:
    """Result of a reconstruction."""

    spectrum: np.ndarray
    layout: BandLayout
    history: History
    engine: str
    options: dict
    seconds: float
    stopped_by: str = "tol"   # "tol": the change fell below tol; "cap": the iteration cap ended the run first


def stop_reason(history: History, options) -> str:
    """``"tol"`` when the last relative change fell below ``options.tol``, else ``"cap"`` (the iteration cap)."""
    if history.records and history.records[-1].change < options.tol:
        return "tol"
    return "cap" if history.iterations >= options.max_iterations else "tol"


def read_captures(path: Path) -> Captures:
    """Read /measurements, /geometry and (if present) /truth, checking shapes and values."""
    with open_input(path) as handle:
        captures = read_measurements(handle, Path(path))
    k = captures.intensity.shape[0]
    if k != captures.geometry.n_images:
        raise InputError(f"{path}: {k} images but /geometry describes {captures.geometry.n_images} positions")
    return captures


def read_measurements(handle, path: Path) -> Captures:
    """/measurements, /geometry and /truth of an open captures file, checked except for the image count."""
    intensity = read_intensity(handle, path)
    units = handle["/measurements/intensity"].attrs.get("units")
    units = units.decode() if isinstance(units, bytes) else units
    units = None if units in (None, "", spec_for("/measurements/intensity").units) else str(units)
    geometry = read_geometry(handle)
    weight = read_weight(handle, path, intensity.shape)
    truth = {name: np.asarray(handle["truth"][name]) for name in handle["truth"]} if "truth" in handle else {}
    k, h, w = intensity.shape
    # Recorded frames say "open"; a file without the attribute is a window on a larger scene unless square.
    boundary = handle["/measurements/intensity"].attrs.get("boundary", "periodic" if h == w else "open")
    defocus = handle["geometry"].attrs.get("defocus_m") if "geometry" in handle else None
    pupil = np.asarray(handle["/calibration/initial_pupil"]) if "/calibration/initial_pupil" in handle else None
    return Captures(path=path, intensity=intensity, weight=weight, geometry=geometry, truth=truth, units=units,
                    boundary=boundary.decode() if isinstance(boundary, bytes) else str(boundary),
                    defocus_m=None if defocus is None else float(defocus), initial_pupil=pupil)


def embed_region(captures: Captures, section: ReconstructSection) -> tuple[Captures, RegionEmbedding | None]:
    """Place recorded (open-boundary) or non-square images in the middle of a square grid with a guard band.

    Returns the captures on the square grid (geometry widened to it, weights
    0 in the guard band) and the embedding, or the captures unchanged and
    None for periodic square images or ``padding.mode: off``.
    See :mod:`cca_cli.sampling.region`.
    """
    k, h, w = captures.intensity.shape
    padding = section.padding
    if padding.mode == "off" or captures.boundary != "open":
        if h != w:
            why = ("with reconstruct.padding.mode off" if captures.boundary == "open"
                   else "simulated (periodic) captures")
            raise InputError(f"{captures.path}: /measurements/intensity images are {w}x{h} px; {why} must be square "
                             "(register.crop_xywh)")
        return captures, None
    region = plan_embedding((h, w), captures.geometry.pupil_radius_px, guard_px=padding.guard_px,
                            apodize_px=padding.apodize_px)
    images, weights = region.embed(captures.intensity, captures.weight)
    geometry = with_field_width(captures.geometry, captures.geometry.field_width_m * region.size / w)
    return replace(captures, intensity=images, weight=weights, geometry=geometry), region


def build_model(geometry: CaptureGeometry, sensor_pixels: int, *, hires_size: int | None = None) -> ForwardModel:
    """The forward model of a capture set on the smallest grids its band allows."""
    layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px,
                         sensor_size=sensor_pixels, hires_size=hires_size)
    return ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px))


def engine_options(section: ReconstructSection):
    """The engine's options object from the reconstruct section."""
    entry = get_engine(section.engine)
    try:
        return entry.options(tau=section.tau, max_iterations=section.iterations, tol=section.tol, **section.options)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"reconstruct.options: {exc}") from None


def reconstruct(captures: Captures, section: ReconstructSection, *, progress: ProgressFn = silent) -> Recovery:
    """Run the configured engine on ``captures``."""
    try:
        model = build_model(captures.geometry, captures.intensity.shape[-1])
    except ValueError as exc:
        raise InputError(f"{captures.path}: {exc}") from None
    problem = PhaseRetrievalProblem.from_sensor_images(model, captures.intensity, captures.weight)
    options = engine_options(section)
    engine = get_engine(section.engine).engine(problem, options)
    return drive_engine(engine, options, model.layout, section.engine, progress=progress)


def drive_engine(engine, options, layout: BandLayout, name: str, *, progress: ProgressFn = silent) -> Recovery:
    """Run ``engine`` to completion, reporting every iteration as a progress event."""
    total = options.max_iterations

    def on_iteration(record: IterationRecord) -> None:
        progress(ProgressEvent("reconstruct", "iterations", record.iteration, total,
                               {"residual": record.residual, "change": record.change}))

    start = time.perf_counter()
    spectrum, history = run_engine(engine, on_iteration=on_iteration)
    if not np.all(np.isfinite(spectrum)):
        raise CcaError(f"reconstruct: the recovery diverged (NaN or Inf after {history.iterations} iterations), so "
                       "nothing was written; raise reconstruct.tau or choose other reconstruct.options")
    return Recovery(spectrum=spectrum, layout=layout, history=history, engine=name,
                    options=asdict(options), seconds=time.perf_counter() - start,
                    stopped_by=stop_reason(history, options))


def write_recon(path: Path, captures: Captures, recovery: Recovery, provenance: Provenance, *, force: bool = False,
                observed: np.ndarray | None = None, extra=None, region: RegionEmbedding | None = None) -> None:
    """Write ``recon.h5`` atomically: recovery, history, centre capture, truth and geometry.

    ``observed`` replaces the centre capture as /observed/centre; ``extra(handle)``
    writes further groups (multiplexed runs add /multiplex). With ``region``
    (padded captures) /recon/object, /recon/intensity and /observed/centre
    hold the region only and /recon/region_px says where it sits.
    """
    obj = fft.ifft2c(recovery.spectrum).astype(np.complex64)
    layout = recovery.layout
    units = captures.units   # recorded captures: counts/s instead of the simulation's irradiance
    if region is not None:
        y0, x0, hh, ww = region.hires_box(layout.hires_size)
        obj = np.ascontiguousarray(obj[y0:y0 + hh, x0:x0 + ww])
        if observed is None:
            observed = region.crop(captures.intensity[captures.geometry.centre_index])
    with atomic_h5(path, provenance, force=force) as handle:
        write_dataset(handle, "/recon/spectrum", recovery.spectrum, units=units and f"√({units}) · px")
        write_dataset(handle, "/recon/object", obj, units=units and f"√({units})")
        write_dataset(handle, "/recon/intensity", (np.abs(obj) ** 2).astype(np.float32), units=units)
        for name in ("residual", "change", "seconds"):
            write_dataset(handle, f"/history/{name}", recovery.history.array(name))
        write_dataset(handle, "/observed/centre",
                      captures.intensity[captures.geometry.centre_index] if observed is None else observed, units=units)
        for name, data in captures.truth.items():
            write_dataset(handle, f"/truth/{name}", data)
        write_geometry(handle, captures.geometry)
        if region is not None:
            oy, ox = region.offset_yx
            write_dataset(handle, "/recon/region_px", np.array([[y0, x0, hh, ww], [oy, ox, *region.shape]], np.int32),
                          guard_px=region.guard_px, apodize_px=region.apodize_px, sensor_grid_px=region.size)
        if extra is not None:
            extra(handle)
        recon = handle["recon"]
        recon.attrs["engine"] = recovery.engine
        recon.attrs["engine_options"] = json.dumps(recovery.options)
        recon.attrs["iterations"] = recovery.history.iterations
        recon.attrs["stopped_by"] = recovery.stopped_by
        recon.attrs["seconds"] = recovery.seconds
        recon.attrs["hires_size"] = layout.hires_size
        recon.attrs["lowres_size"] = layout.lowres_size
        recon.attrs["pixel_pitch_object_m"] = captures.geometry.field_width_m / layout.hires_size
        recon.attrs["fft_backend"] = fft.backend_name()


def run(captures_path: Path, section: ReconstructSection, output: Path, *, provenance: Provenance,
        force: bool = False, progress: ProgressFn = silent) -> Recovery:
    """Read captures, reconstruct, write ``output``."""
    check_output(output, force=force)
    from cca_cli.stages import multiplex

    if multiplex.is_multiplexed_file(captures_path):
        return multiplex.run_reconstruct(captures_path, section, output, provenance=provenance, force=force,
                                         progress=progress)
    captures, region = embed_region(read_captures(captures_path), section)
    recovery = reconstruct(captures, section, progress=progress)
    from cca_cli.stages.capture_info import capture_extras

    write_recon(output, captures, recovery, provenance, force=force, extra=capture_extras(captures_path),
                region=region)
    return recovery
