"""Stage `reconstruct`: captures → recovered high-resolution object (recon.h5)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.calibration import defocus_zernike
from cca_cli.engines.fit import FitReport, fit_report
from cca_cli.engines.illumination import LedArrayModel
from cca_cli.engines.momentum import Calibration
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.registry import get_engine
from cca_cli.errors import InputError
from cca_cli.io.captures import Captures, read_measurements
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, open_input, write_dataset
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import BandLayout, band_layout, smallest_fft_size
from cca_cli.sampling.region import RegionEmbedding, plan_embedding
from cca_cli.stages.progress import ProgressFn, silent
from cca_cli.workflows.recovery import Recovery, drive_engine, engine_options, resolve_engine

__all__ = ["SECTIONS", "Captures", "Recovery", "read_captures", "read_measurements", "build_model", "reconstruct",
           "embed_region", "run"]

SECTIONS = ("reconstruct",)


def read_captures(path: Path) -> Captures:
    """Read /measurements, /geometry and (if present) /truth, checking shapes and values."""
    with open_input(path) as handle:
        captures = read_measurements(handle, Path(path))
    k = captures.intensity.shape[0]
    if k != captures.geometry.n_images:
        raise InputError(f"{path}: {k} images but /geometry describes {captures.geometry.n_images} positions")
    return captures


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


def build_model(geometry: CaptureGeometry, sensor_pixels: int, *, hires_size: int | None = None,
                margin_px: int = 0) -> ForwardModel:
    """The forward model of a capture set on the smallest grids its band allows.

    ``margin_px`` widens the high-resolution grid so that pupils may move that
    far outwards (position calibration).
    """
    layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px,
                         sensor_size=sensor_pixels, hires_size=hires_size)
    if margin_px > 0 and hires_size is None:
        layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, sensor_size=sensor_pixels,
                             hires_size=smallest_fft_size(layout.hires_size + 2 * margin_px))
    return ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px))


def data_kind(captures: Captures) -> str:
    """``simulation`` (a ground truth is known), else the geometry's kind (``led_array``, ``camera_scan``)."""
    return "simulation" if captures.truth else captures.geometry.kind


def problem_calibration(geometry: CaptureGeometry, layout: BandLayout, initial_pupil=None) -> dict:
    """What the captures tell a calibrating engine: cameras, how positions may move, a known pupil or defocus."""
    out = {} if initial_pupil is None else {"initial_pupil": np.asarray(initial_pupil, np.complex64)}
    if geometry.camera_index is not None:
        out["pupil_index"] = np.asarray(geometry.camera_index, np.int64)
    if geometry.kind == "led_array":
        out["position_model"] = LedArrayModel(layout.centres_px, geometry.field_width_m / geometry.wavelength_m)
    if np.isfinite(geometry.defocus_m) and geometry.defocus_m != 0 and geometry.kind == "led_array":
        out["aberration"] = defocus_zernike(geometry.defocus_m, wavelength_m=geometry.wavelength_m,
                                            numerical_aperture=geometry.numerical_aperture)
    return out


def reconstruct(captures: Captures, section: ReconstructSection, *, progress: ProgressFn = silent) -> Recovery:
    """Run the configured engine on ``captures`` (``engine: auto`` resolved for the kind of data)."""
    kind = data_kind(captures)
    name, _ = resolve_engine(section, kind)
    return recover(captures, name, engine_options(section, kind), progress=progress)


def recover(captures: Captures, engine: str, options, *, progress: ProgressFn = silent,
            on_iteration=None) -> Recovery:
    """Phase retrieval of ``captures`` with a named engine and its options object.

    Builds the forward model on the smallest grids the band allows (wider when
    positions are calibrated), tells the engine what the geometry knows (cameras,
    how positions may move, a known defocus), runs it, and evaluates the final
    model's residuals.

    Parameters
    ----------
    captures : Captures
    engine : str
        Registered engine name.
    options
        The engine's options object.
    progress : callable, optional
        Receives a progress event per iteration.
    on_iteration : callable, optional
        Also called with each :class:`~cca_cli.engines.base.IterationRecord`.

    Returns
    -------
    Recovery
    """
    margin = 0
    if getattr(options, "position_refinement", "none") != "none":
        margin = int(np.ceil(captures.geometry.pupil_radius_px / 8)) + 2
    try:
        model = build_model(captures.geometry, captures.intensity.shape[-1], margin_px=margin)
    except ValueError as exc:
        raise InputError(f"{captures.path}: {exc}") from None
    problem = PhaseRetrievalProblem.from_sensor_images(model, captures.intensity, captures.weight,
                                                       **problem_calibration(captures.geometry, model.layout,
                                                                             captures.initial_pupil))
    runner = get_engine(engine).engine(problem, options)
    recovery = drive_engine(runner, options, model.layout, engine, progress=progress, on_iteration=on_iteration)
    calibration = runner.calibration() if hasattr(runner, "calibration") else None
    return replace(recovery, calibration=calibration, fit=fit_report(problem, recovery.spectrum, calibration))


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
        if recovery.fit is not None:
            write_fit(handle, recovery.fit)
        if recovery.calibration is not None:
            write_calibration(handle, recovery.calibration, captures.geometry)
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


def write_fit(handle, fit: FitReport) -> None:
    """The residuals of the final model: per capture, and over all / bright-field / dark-field captures."""
    write_dataset(handle, "/recon/residual_per_image", fit.per_image)
    write_dataset(handle, "/calibration/bright_field", fit.bright_field_mask)
    recon = handle["recon"]
    for name in ("all", "bright_field", "dark_field"):
        recon.attrs[f"residual_{name}"] = getattr(fit, name)
        recon.attrs[f"residual_{name}_without_brightness"] = getattr(fit, f"{name}_without_brightness")


def calibrated_pupils(calibration: Calibration, radius_px: float) -> np.ndarray | None:
    """Each recovered pupil on its box with its NA disc, complex64 (P, b, b).

    The disc is centred on box pixel ``b // 2``, where the box centre of a capture whose pupil
    centre falls on a whole spectrum pixel lies (:func:`~cca_cli.sampling.grid.band_layout`).
    """
    if calibration.pupil is None:
        return None
    b = calibration.pupils.shape[-1]
    disc = circular_pupils(b, np.full((1, 2), float(b // 2)), radius_px)[0]
    return (disc[None] * calibration.pupil.maps).astype(np.complex64)


def write_calibration(handle, calibration: Calibration, geometry: CaptureGeometry) -> None:
    """Pupils, refined positions and brightness under /calibration, SI next to pixels."""
    group = handle.require_group("calibration")
    if calibration.pupil is not None:
        estimate = calibration.pupil
        write_dataset(handle, "/calibration/pupil", calibrated_pupils(calibration, geometry.pupil_radius_px))
        write_dataset(handle, "/calibration/pupil_map", estimate.maps.astype(np.complex64))
        write_dataset(handle, "/calibration/zernike_waves", estimate.coefficients)
        write_dataset(handle, "/calibration/zernike_modes", np.asarray(estimate.modes, np.int32))
        group.attrs["pupil_model"] = estimate.model
        group.attrs["pupil_radius_px"] = geometry.pupil_radius_px
        group.attrs["spectrum_pixel_per_m"] = 1.0 / geometry.field_width_m
    write_dataset(handle, "/calibration/pupil_index", calibration.pupil_index.astype(np.int32))
    write_dataset(handle, "/calibration/spectrum_centres_yx_px", calibration.centres_px)
    metres_per_px = geometry.aperture_centres_yx_m / np.where(geometry.spectrum_centres_yx_px == 0, np.nan,
                                                               geometry.spectrum_centres_yx_px)
    scale = float(np.nanmedian(metres_per_px)) if np.isfinite(metres_per_px).any() else float("nan")
    write_dataset(handle, "/calibration/aperture_centres_yx_m", calibration.centres_px * scale)
    write_dataset(handle, "/calibration/brightness", calibration.brightness)
    if calibration.position_model is not None:
        group.attrs["position_model"] = calibration.position_model
        group.attrs["position_parameters"] = json.dumps(calibration.position_parameters)


def run(captures_path: Path, section: ReconstructSection, output: Path, *, provenance: Provenance,
        force: bool = False, progress: ProgressFn = silent) -> Recovery:
    """Read captures, reconstruct, write ``output``."""
    check_output(output, force=force)
    from cca_cli.workflows import multiplex

    if multiplex.is_multiplexed_file(captures_path):
        return multiplex.run_reconstruct(captures_path, section, output, provenance=provenance, force=force,
                                         write_recon=write_recon,
                                         progress=progress)
    captures, region = embed_region(read_captures(captures_path), section)
    recovery = reconstruct(captures, section, progress=progress)
    from cca_cli.io.capture_info import capture_extras

    write_recon(output, captures, recovery, provenance, force=force, extra=capture_extras(captures_path),
                region=region)
    return recovery
