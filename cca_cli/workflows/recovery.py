"""Choose a phase-retrieval engine from the reconstruct section and run it on captures to a :class:`Recovery`."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.base import History, IterationRecord, run_engine
from cca_cli.engines.calibration import defocus_zernike
from cca_cli.engines.fit import FitReport, fit_report
from cca_cli.engines.illumination import LedArrayModel
from cca_cli.engines.momentum import Calibration
from cca_cli.engines.presets import starting_options
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.registry import get_engine
from cca_cli.errors import CcaError, ConfigError, InputError
from cca_cli.io.captures import Captures
from cca_cli.io.checkpoint import read_spectrum
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.progress import ProgressEvent, ProgressFn, silent
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import BandLayout, band_layout, smallest_fft_size
from cca_cli.sampling.region import RegionEmbedding, plan_embedding

__all__ = ["Recovery", "stop_reason", "resolve_engine", "engine_options", "drive_engine", "initial_spectrum_from",
           "embed_region", "build_model", "data_kind", "problem_calibration", "recover", "calibrated_pupils"]

_log = logging.getLogger("cca")


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


def stop_reason(history: History, options, engine=None) -> str:
    """Why a run ended: ``"tol"`` (the last change fell below ``options.tol``), ``"plateau"`` (the engine's
    misfit stopped falling) or ``"cap"`` (the iteration cap ended it first)."""
    if history.records and history.records[-1].change < options.tol:
        return "tol"
    if engine is not None and getattr(engine, "on_plateau", lambda: False)():
        return "plateau"
    return "cap" if history.iterations >= options.max_iterations else "tol"


def resolve_engine(section: ReconstructSection, kind: str) -> tuple[str, dict]:
    """Engine name and its keyword options (``tau``, ``max_iterations``, ``tol`` included).

    ``engine: auto`` takes the preset for the kind of data
    (:func:`cca_cli.engines.presets.preset`), and so does the preset's engine
    named outright on recorded captures (:func:`~cca_cli.engines.presets.starting_options`);
    what the section sets explicitly (``tau``, ``iterations``, ``tol``,
    ``options``) overrides the preset.
    """
    section_values = {"tau": section.tau, "max_iterations": section.iterations, "tol": section.tol}
    name, options = starting_options(section.engine, kind)
    given = section.model_fields_set
    for key, field in (("tau", "tau"), ("max_iterations", "iterations"), ("tol", "tol")):
        if field in given or key not in options:
            options[key] = section_values[key]
    options.update(section.options)
    return name, options


def engine_options(section: ReconstructSection, kind: str = "simulation"):
    """The engine's options object from the reconstruct section (``engine: auto`` resolved for ``kind``)."""
    name, keywords = resolve_engine(section, kind)
    entry = get_engine(name)
    try:
        return entry.options(**keywords)
    except (TypeError, ValueError) as exc:
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
                    options=asdict(options), seconds=time.perf_counter() - start,
                    stopped_by=stop_reason(history, options, engine))


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
    if getattr(options, "position_refinement", "none") != "none":
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
    entry = get_engine(engine)
    runner = entry.engine(problem, options, spectrum=start)
    history = None
    saved = checkpoint.load(_state_of(runner)) if checkpoint is not None else None
    if saved is not None:
        try:
            runner.restore(saved.state)
            history = History([IterationRecord(i + 1, *values) for i, values in
                               enumerate(zip(*(saved.history[n].tolist() for n in ("residual", "change", "seconds"))))])
            _log.warning("resuming from iteration %d (checkpoint %s)", history.iterations, checkpoint.path)
        except (KeyError, ValueError, TypeError, NotImplementedError) as exc:
            _log.warning("%s cannot be resumed (%s): starting afresh", checkpoint.path, exc)
            runner.close()
            runner, history = entry.engine(problem, options, spectrum=start), None
    recovery = drive_engine(runner, options, model.layout, engine, progress=progress, on_iteration=on_iteration,
                            history=history, checkpoint=checkpoint)
    calibration = runner.calibration() if hasattr(runner, "calibration") else None
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
