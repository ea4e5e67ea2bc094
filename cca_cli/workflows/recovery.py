"""Choose a phase-retrieval engine from the reconstruct section and run it on captures to a :class:`Recovery`."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.base import CalibratingEngine, History, IterationRecord, run_engine
from cca_cli.engines.calibration import defocus_zernike
from cca_cli.engines.calibrator import Calibration
from cca_cli.engines.fit import FitReport, fit_report
from cca_cli.engines.illumination import LedArrayModel
from cca_cli.engines.options import EngineOptions
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.registry import get_engine, resolve
from cca_cli.errors import CcaError, ConfigError, InputError
from cca_cli.io.captures import Captures
from cca_cli.io.checkpoint import read_spectrum
from cca_cli.io.measurements import INTENSITY
from cca_cli.library.data import constant_images
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.progress import ProgressEvent, ProgressFn, silent
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import BandLayout, band_layout, smallest_fft_size
from cca_cli.sampling.region import RegionEmbedding, plan_embedding

__all__ = ["Recovery", "engine_options", "drive_engine", "initial_spectrum_from",
           "embed_region", "build_model", "data_kind", "problem_calibration", "recover", "calibrated_pupils",
           "MAX_DEAD_FRACTION", "without_dead_captures"]

_log = logging.getLogger("cca")
#: Share of the captures that may be dead (constant) and left out; more is refused as a broken recording.
MAX_DEAD_FRACTION = 0.05


@dataclass(frozen=True)
class Recovery:
    """Result of a reconstruction.

    ``calibration`` is what a calibrating engine found (pupils, positions,
    brightness), ``fit`` the residuals of the final model; both None for engines
    without them (multiplexed captures).
    """

    spectrum: np.ndarray
    layout: BandLayout
    history: History
    engine: str
    options: dict
    seconds: float
    stopped_by: str = "tol"   # "tol": the change fell below tol; "plateau": the misfit stopped falling; "cap"
    calibration: Calibration | None = None
    fit: FitReport | None = None

    @property
    def hires_size(self) -> int:
        """Side of the recovery's object grid."""
        return self.layout.hires_size


def engine_options(section: ReconstructSection, kind: str = "simulation", **overrides) -> tuple[str, EngineOptions]:
    """The engine the section's ``engine`` stands for on ``kind`` of data, and its options object.

    ``overrides`` go on top of what the section gives. One line naming
    ``reconstruct.options`` when the options do not fit the engine
    (:func:`cca_cli.engines.registry.resolve`).
    """
    try:
        return resolve(section.engine, kind, {**section.given(), **overrides})
    except ValueError as exc:
        raise ConfigError(f"reconstruct.options: {exc}") from None


def drive_engine(engine, options, layout: BandLayout, name: str, *, progress: ProgressFn = silent,
                 on_iteration=None, history: History | None = None, checkpoint=None) -> Recovery:
    """Run ``engine`` to completion, reporting every iteration as a progress event (and to ``on_iteration``).

    ``history`` holds the iterations a restored engine already ran; ``checkpoint`` (an object with
    ``start()`` and ``after_iteration(engine, history)``, e.g. the reconstruct stage's
    ``Checkpointing``) saves the state as it goes.
    """
    total = options.max_iterations
    history = History() if history is None else history

    def report(record: IterationRecord) -> None:
        progress(ProgressEvent("reconstruct", "iterations", record.iteration, total,
                               {"residual": record.residual, "change": record.change}))
        if on_iteration is not None:
            on_iteration(record)
        if checkpoint is not None:
            checkpoint.after_iteration(engine, history)

    start = time.perf_counter()
    if checkpoint is not None:
        checkpoint.start()
    spectrum, history = run_engine(engine, on_iteration=report, history=history)
    if not np.all(np.isfinite(spectrum)):
        raise CcaError(f"reconstruct: the recovery diverged (NaN or Inf after {history.iterations} iterations), so "
                       "nothing was written; raise reconstruct.tau or choose other reconstruct.options")
    return Recovery(spectrum=spectrum, layout=layout, history=history, engine=name,
                    options=options.model_dump(), seconds=time.perf_counter() - start,
                    stopped_by=engine.stop_reason())


def initial_spectrum_from(path: Path, layout: BandLayout, field_width_m: float) -> np.ndarray:
    """/recon/spectrum of the recon.h5 at ``path``, checked against this reconstruction's grid."""
    spectrum, attrs = read_spectrum(Path(path))
    m = layout.hires_size
    if spectrum.shape != (m, m):
        raise InputError(f"{path}: /recon/spectrum is {spectrum.shape[0]}x{spectrum.shape[1]} but this "
                         f"reconstruction's grid is {m}x{m}; reconstruct.init needs a recon.h5 of the same captures "
                         "and padding")
    pitch = attrs.get("pixel_pitch_object_m")
    if pitch is not None and not np.isclose(float(pitch), field_width_m / m, rtol=1e-6):
        raise InputError(f"{path}: its object pixels are {float(pitch):.6g} m but this reconstruction's are "
                         f"{field_width_m / m:.6g} m; reconstruct.init needs a recon.h5 of the same geometry")
    return spectrum


def _listed(indices, grid: np.ndarray, limit: int = 6) -> str:
    """``image 3 (row 0, col 3), image 7 (row 1, col 2)`` for the first ``limit`` indices."""
    items = [f"image {int(i)} (row {int(grid[i, 0])}, col {int(grid[i, 1])})" for i in indices[:limit]]
    return ", ".join(items) + (", …" if len(indices) > limit else "")


def without_dead_captures(captures: Captures, *, name: str = INTENSITY, source=None,
                          error: type[Exception] = InputError) -> Captures:
    """Leave out the captures whose images hold one value only (a camera that recorded nothing).

    Such an image carries no information, and fitting it would pull the recovery
    towards a dark (or flat) patch of spectrum. Up to :data:`MAX_DEAD_FRACTION` of
    the captures are left out with one warning naming them and their grid
    positions. More, or a dead centre capture (the one that holds the object's
    lowest frequencies, and the single-camera image the report compares with),
    are refused.

    Parameters
    ----------
    captures : Captures
    name, source, error
        How messages name the images and their file, and the exception a refusal raises
        (see :func:`cca_cli.io.measurements.check_intensity`).

    Returns
    -------
    Captures
        ``captures`` itself, or the live captures with their weights and geometry
        (``dropped`` lists the indices left out).
    """
    dead = constant_images(captures.intensity)
    if dead.size == 0:
        return captures
    where = f"{source}: " if source else ""
    geometry = captures.geometry
    grid = np.asarray(geometry.grid_indices)
    k = captures.intensity.shape[0]
    centre = geometry.centre_index
    holds = "holds" if dead.size == 1 else "hold"
    if centre in dead:
        value = float(captures.intensity[centre].flat[0])
        raise error(f"{where}image {centre} of {name}, the centre capture (row {int(grid[centre, 0])}, col "
                    f"{int(grid[centre, 1])}), holds one value (every pixel {value:g}): nothing was recorded there, "
                    "and the recovery needs it for the object's lowest frequencies; re-take it")
    allowed = int(MAX_DEAD_FRACTION * k)
    if dead.size > allowed:
        each = "" if dead.size == 1 else " each"
        raise error(f"{where}{dead.size} of {k} images of {name} {holds} one value{each}, so nothing was recorded "
                    f"there ({_listed(dead, grid)}); at most {MAX_DEAD_FRACTION:.0%} of the captures ({allowed} "
                    f"here) may be left out: check the camera and re-take them")
    values = ", ".join(f"{float(captures.intensity[i].flat[0]):g}" for i in dead[:6])
    _log.warning("%sleft out %s of %d images of %s: %s %s one value (%s), nothing was recorded there; the "
                 "recovery uses the other %d", where, dead.size, k, name, _listed(dead, grid), holds, values,
                 k - dead.size)
    keep = np.setdiff1d(np.arange(k), dead)
    weight = None if captures.weight is None else captures.weight[keep]
    return replace(captures, intensity=captures.intensity[keep], weight=weight, geometry=geometry.select(keep),
                   dropped=tuple(int(i) for i in dead))


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
    return ForwardModel.unaberrated(layout)


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


def recover(captures: Captures, engine: str, options, *, progress: ProgressFn = silent,
            on_iteration=None, init=None, checkpoint=None, aberration=None) -> Recovery:
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
    init : path or ndarray, optional
        A recon.h5 (or a complex64 (M, M) spectrum) to start from instead of the upsampled centre capture.
    checkpoint : optional
        The reconstruct stage's ``Checkpointing``: continue from its checkpoint when one matches and is
        sound (finite, of this engine's shapes); write new ones as the run goes.
    aberration : ndarray, (n_modes,) or (P, n_modes), optional
        Zernike coefficients (waves) the pupil starts from, in place of what the captures know
        (a tiled reconstruction passes a neighbour tile's).

    Returns
    -------
    Recovery
    """
    margin = 0
    if options.refines_positions:
        margin = int(np.ceil(captures.geometry.pupil_radius_px / 8)) + 2
    try:
        model = build_model(captures.geometry, captures.intensity.shape[-1], margin_px=margin)
    except ValueError as exc:
        raise InputError(f"{captures.path}: {exc}") from None
    calibration = problem_calibration(captures.geometry, model.layout, captures.initial_pupil)
    if aberration is not None:
        calibration["aberration"] = np.asarray(aberration, np.float64)
    problem = PhaseRetrievalProblem.from_sensor_images(model, captures.intensity, captures.weight, **calibration)
    start = None
    if isinstance(init, (str, Path)):
        start = initial_spectrum_from(init, model.layout, captures.geometry.field_width_m)
    elif init is not None:
        start = np.asarray(init, np.complex64)
        if start.shape != model.spectrum_shape:
            raise ValueError(f"init: the spectrum is {start.shape}, this reconstruction's grid "
                             f"{model.spectrum_shape}; start from a result of the same captures")
    engine_class = get_engine(engine).engine_class()
    runner = engine_class(problem, options, spectrum=start)
    history = None
    saved = checkpoint.load(_state_of(runner)) if checkpoint is not None else None
    if saved is not None:
        try:
            runner.restore(saved.state)
            history = History([IterationRecord(i + 1, *values) for i, values in
                               enumerate(zip(*(saved.history[n].tolist() for n in ("residual", "change", "seconds"))))])
            _log.warning("note: resuming from iteration %d (checkpoint %s)", history.iterations, checkpoint.path)
        except (KeyError, ValueError, TypeError, NotImplementedError) as exc:
            _log.warning("%s cannot be resumed (%s): starting afresh", checkpoint.path, exc)
            runner.close()
            runner, history = engine_class(problem, options, spectrum=start), None
    recovery = drive_engine(runner, options, model.layout, engine, progress=progress, on_iteration=on_iteration,
                            history=history, checkpoint=checkpoint)
    calibration = runner.calibration() if isinstance(runner, CalibratingEngine) else None
    return replace(recovery, calibration=calibration, fit=fit_report(problem, recovery.spectrum, calibration))


def _state_of(engine) -> dict | None:
    """The engine's state as it starts (what a checkpoint must match), or None for an engine without one."""
    try:
        return engine.state()
    except NotImplementedError:
        return None


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
