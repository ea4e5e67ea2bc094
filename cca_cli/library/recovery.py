"""Phase retrieval of a :class:`~cca_cli.library.data.CaptureSet` to a :class:`~cca_cli.library.data.Reconstruction`.

:func:`reconstruct` is the whole way from captures to a result, the same for
the Python interface and the command line: dead captures are left out,
recorded or non-square images are placed on a square grid with a guard band,
the engine is chosen and its options read (:func:`cca_cli.engines.registry.resolve`),
the forward model built on the smallest grids the band allows, the engine run
and the recovery cut back to the region the captures covered. The pieces are
public for callers that need one of them (tiles, benchmarks).

Everything here takes arrays and options; data that cannot be used raise
``ValueError`` naming what is wrong, so a caller can add the file or the key.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from cca_cli.engines.base import CalibratingEngine, History, IterationRecord, run_engine
from cca_cli.engines.calibration import defocus_zernike
from cca_cli.engines.calibrator import Calibration
from cca_cli.engines.fit import fit_report
from cca_cli.engines.illumination import LedArrayModel
from cca_cli.engines.options import EngineOptions
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.registry import get_engine, resolve
from cca_cli.errors import CcaError
from cca_cli.library import stray_light
from cca_cli.library.data import CaptureSet, Reconstruction, constant_images
from cca_cli.optics import backend, fft
from cca_cli.optics.backend import DeviceUnavailable
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.progress import ProgressEvent, ProgressFn, silent
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import BandLayout, band_layout, smallest_fft_size
from cca_cli.sampling.region import RegionEmbedding, plan_embedding

__all__ = ["MAX_DEAD_FRACTION", "DivergedError", "DeviceUnavailable", "reconstruct", "engine_device", "holds_stray_light",
           "without_dead_captures", "check_dead_captures", "check_dead_measurements", "drop_captures", "embed_region", "build_model", "problem_calibration", "recover", "run_threads",
           "drive_engine", "calibrated_pupils"]

_log = logging.getLogger("cca")
#: Share of the captures that may be dead (constant) and left out; more is refused as a broken recording.
MAX_DEAD_FRACTION = 0.05
PADDING_MODES = ("auto", "off")


class DivergedError(CcaError):
    """The recovery ran off to NaN or Inf (too small a regularisation for these data)."""

    def __init__(self, iterations: int):
        super().__init__(f"the recovery diverged (NaN or Inf after {iterations} iterations); raise tau or choose "
                         "other options")
        self.iterations = iterations


def reconstruct(captures: CaptureSet, *, engine: str = "auto", options: dict | EngineOptions | None = None,
                padding: str = "auto", guard_px: int | None = None, apodize_px: int | None = None,
                init: np.ndarray | None = None, init_pixel_m: float | None = None, progress: ProgressFn = silent,
                on_iteration=None, checkpoint=None, name: str = "intensities", source=None,
                device: str = "cpu") -> Reconstruction:
    """Recover the object from captures: the one way the API and the command line both take.

    Parameters
    ----------
    captures : CaptureSet
    engine : str
        ``auto`` or a registered engine.
    options : dict or EngineOptions, optional
        What the user set (``tau``, ``iterations``, ``tol`` and the engine's options), read as a config reads
        them; or the options of ``engine`` already resolved (:func:`cca_cli.engines.registry.resolve`).
    padding : {"auto", "off"}
        ``auto`` places recorded (open-boundary) and non-square images on a square grid with a weight-0
        guard band of ``guard_px`` (and a taper of ``apodize_px``); ``off`` keeps square images as they are.
    init : ndarray, complex64, (M, M), optional
        A spectrum to start from, on this reconstruction's grid.
    init_pixel_m : float, optional
        The object pixel of ``init`` (m), when known: it must be this reconstruction's.
    progress, on_iteration, checkpoint
        As in :func:`recover`.
    name, source
        How messages name the images and their file.
    device : {"cpu", "cuda", "auto"}
        Where the engine runs (:func:`engine_device`).

    Returns
    -------
    Reconstruction

    Raises
    ------
    ValueError
        Options the engine does not take, dead captures beyond what may be left out, or images and a
        geometry no recovery grid can hold.
    DeviceUnavailable
        ``device="cuda"`` without CuPy or a GPU, or with options the GPU engines do not run (a ValueError).
    DivergedError
    """
    if isinstance(options, EngineOptions):
        engine_options = options
    else:
        engine, engine_options = resolve(engine, captures.kind, options or {}, frame_scale=captures.frame_scale,
                                         stray_light=holds_stray_light(captures))
    if getattr(engine_options, "background", False) and holds_stray_light(captures):
        _log.warning("note: the dark-field images never fall near zero (light the object did not scatter: stray "
                     "light, or an offset left in), so from the calibration rounds on (pass %d) a plane of it is "
                     "fitted to each dark-field capture that stays off zero, and taken off (option background; "
                     "false leaves it in)", getattr(engine_options, "calibration_start", 0) + 1)
    if captures.frame_scale == "per_frame" and not hasattr(engine_options, "brightness"):
        _log.warning("note: the images were scaled each on its own (frame_scale per_frame) but engine %s fits no "
                     "brightness; engine momentum does", engine)
    device = engine_device(device, engine, engine_options)
    live = without_dead_captures(captures, name=name, source=source)
    padded, region = embed_region(live, padding=padding, guard_px=guard_px, apodize_px=apodize_px)
    if init is not None and init_pixel_m is not None:
        pixel = padded.geometry.field_width_m / np.shape(init)[-1]
        if not np.isclose(float(init_pixel_m), pixel, rtol=1e-6):
            raise ValueError(f"init: its object pixels are {float(init_pixel_m):.6g} m but this reconstruction's are "
                             f"{pixel:.6g} m; start from a result of the same geometry")
    result = recover(padded, engine, engine_options, progress=progress, on_iteration=on_iteration, init=init,
                     checkpoint=checkpoint, device=device)
    if _one_capture_per_camera(live, engine_options):
        _log.warning("note: each camera's pupil is seen by its one capture only, so its aberration is weakly "
                     "determined: on simulated 3 x 3 arrays the recovered defocus and astigmatism erred by about as "
                     "much as the cameras' aberrations (benchmarks/camera_array_pupils.py); the image gains from "
                     "them, but read the coefficients as no lens test")
    observed = live.centre_image
    obj = result.object
    if region is not None:
        y0, x0, rows, cols = region.hires_box(result.hires_size)
        obj = np.ascontiguousarray(obj[y0:y0 + rows, x0:x0 + cols])
    return replace(result, object=obj, observed=observed, region=region, dropped=live.dropped)


def _one_capture_per_camera(captures: CaptureSet, options: EngineOptions) -> bool:
    """Whether the run recovers one pupil per camera and each camera took a single capture."""
    cameras = captures.geometry.camera_index
    if getattr(options, "pupil_recovery", "none") != "per_camera" or cameras is None:
        return False
    return int(np.bincount(np.asarray(cameras, np.int64)).max()) == 1


def holds_stray_light(captures: CaptureSet) -> bool:
    """Whether an LED array's dark-field images never fall near zero (:mod:`cca_cli.library.stray_light`)."""
    geometry = captures.geometry
    if captures.kind != "led_array":
        return False
    return stray_light.holds_stray_light(captures.intensity, geometry.spectrum_centres_yx_px,
                                         geometry.pupil_radius_px, captures.weight)


def engine_device(device: str, engine: str, options: EngineOptions) -> str:
    """The device an engine runs on: ``cpu`` (the CPU engines, as always) or ``cuda`` (their batched forms on a GPU).

    Parameters
    ----------
    device : {"cpu", "cuda", "auto"}
        ``auto`` is ``cuda`` when CuPy finds a GPU and the engine's batched form runs these options
        (:func:`cca_cli.engines.batched.unsupported_options`), else ``cpu``.
    engine : str
        A registered engine name.
    options : EngineOptions

    Raises
    ------
    DeviceUnavailable
        ``cuda`` without CuPy or a GPU, or for options (or an engine) the GPU does not run: one line
        naming them and the fix.
    ValueError
        An unknown device name.
    """
    if device == "cpu":
        return "cpu"
    from cca_cli.engines.batched import check_options, unsupported_options

    spec = get_engine(engine)
    usable = spec.batched is not None and not unsupported_options(options)
    resolved = backend.resolve_device(device, usable=usable)
    if resolved == "cuda":
        if spec.batched is None:
            raise DeviceUnavailable(f"engine {engine} runs on the CPU only; use device cpu")
        check_options(options)
    elif device == "auto" and backend.device_status().cuda:
        _log.warning("note: device auto runs this reconstruction on the CPU: the GPU engine does not run %s",
                     "; ".join(unsupported_options(options)) or f"engine {engine}")
    return resolved


def _where(geometry, index: int) -> str:
    """``(row 0, col 3)``, or for an LED array (any layout) where its pupil sits, in sines and ``[y, x]`` order as
    ``sin_yx``: ``(its pupil at [y, x] = [-0.1300, +0.0750] in sines)`` (the light's sines times the geometry's
    sign)."""
    if geometry.kind == "led_array":
        y, x = np.asarray(geometry.aperture_centres_yx_m, np.float64)[index]
        return f"(its pupil at [y, x] = [{y:+.4f}, {x:+.4f}] in sines)"
    grid = np.asarray(geometry.grid_indices)
    return f"(row {int(grid[index, 0])}, col {int(grid[index, 1])})"


def without_dead_captures(captures: CaptureSet, *, name: str = "intensities", source=None,
                          error: type[Exception] = ValueError) -> CaptureSet:
    """Leave out the captures whose images hold one value only (a camera that recorded nothing), and the LED-array
    bright-field captures whose LED did not fire (:func:`unlit_bright_field`).

    Such an image carries no information, and fitting it would pull the recovery
    towards a dark (or flat) patch of spectrum. Up to :data:`MAX_DEAD_FRACTION` of
    the captures are left out with one warning naming them and their grid
    positions. More, or a dead centre capture (the one that holds the object's
    lowest frequencies, and the single-camera image the report compares with),
    are refused (:func:`check_dead_captures`).

    Parameters
    ----------
    captures : CaptureSet
    name, source, error
        How messages name the images and their file, and the exception a refusal raises.

    Returns
    -------
    CaptureSet
        ``captures`` itself, or the live captures with their weights and geometry
        (``dropped`` lists the indices left out).
    """
    dead = constant_images(captures.intensity)
    values = [float(captures.intensity[i].flat[0]) for i in dead]
    check_dead_captures(dead, values, captures.geometry, name=name, source=source, error=error)
    unlit, darker = unlit_bright_field(captures)
    unlit, darker = unlit[~np.isin(unlit, dead)], darker[~np.isin(unlit, dead)]
    if unlit.size:
        _check_unlit(unlit, darker, dead.size, captures.geometry, name=name, source=source, error=error)
    gone = np.union1d(dead, unlit)
    return captures if gone.size == 0 else drop_captures(captures, gone)


#: An LED-array capture in the bright field that recorded this many times less light than the median bright-field
#: capture did not get its light (an LED that did not fire): ingest names it, reconstruct leaves it out.
UNLIT_FACTOR = 10.0
#: More than this share of the bright-field captures so dark (three or more) says the LEDs' geometry is wrong, not
#: that LEDs failed: ingest says so, and nothing is left out.
UNLIT_GEOMETRY_SHARE = 0.25


@dataclass(frozen=True)
class BrightFieldLight:
    """How much light an LED array's bright-field captures recorded, judged (:func:`judge_bright_field`).

    Attributes
    ----------
    bright : ndarray of int
        The captures the geometry puts well inside the bright field (within 0.9 pupil radii of the origin).
    typical : float
        Their median light.
    unlit : ndarray of int
        Those :data:`UNLIT_FACTOR` times darker than ``typical`` or more (none when the geometry is wrong).
    times_darker : ndarray of float
        ``typical`` over each unlit one's light (inf where it recorded none).
    wrong_geometry : ndarray of int
        When more than :data:`UNLIT_GEOMETRY_SHARE` of them (three or more) are that much darker than the
        brightest tenth, those captures: the geometry, not an LED, is off. Empty otherwise.
    """

    bright: np.ndarray
    typical: float
    unlit: np.ndarray
    times_darker: np.ndarray
    wrong_geometry: np.ndarray


def judge_bright_field(light: np.ndarray, centres_px: np.ndarray, radius_px: float) -> BrightFieldLight | None:
    """The bright-field captures' light judged: LEDs that did not fire, or a geometry that does not match.

    Parameters
    ----------
    light : ndarray, (K,)
        Each capture's mean intensity (per unit exposure).
    centres_px : ndarray, (K, 2)
        Pupil centres relative to the spectrum's origin (spectrum px).
    radius_px : float
        Pupil radius (spectrum px).

    Returns
    -------
    BrightFieldLight or None
        None with fewer than three bright-field captures, or none of them lit.
    """
    centres = np.asarray(centres_px, np.float64)
    bright = np.flatnonzero(np.hypot(centres[:, 0], centres[:, 1]) < 0.9 * radius_px)
    if bright.size < 3:
        return None
    means = np.asarray(light, np.float64)[bright]
    typical, brightest = float(np.median(means)), float(np.percentile(means, 90))
    if not brightest > 0:
        return None
    # Judged against the brighter captures too: where the geometry is wrong, most "bright-field" captures may be
    # dark, and so is their median.
    against_brightest = bright[means * UNLIT_FACTOR < brightest]
    wrong = against_brightest if against_brightest.size >= 3 and \
        against_brightest.size > UNLIT_GEOMETRY_SHARE * bright.size else np.zeros(0, np.int64)
    off = (means * UNLIT_FACTOR < typical) if typical > 0 and wrong.size == 0 else np.zeros(bright.size, bool)
    with np.errstate(divide="ignore"):
        darker = np.where(means[off] > 0, typical / np.maximum(means[off], 1e-300), np.inf)
    return BrightFieldLight(bright, typical, bright[off], darker, wrong)


def unlit_bright_field(captures: CaptureSet) -> tuple[np.ndarray, np.ndarray]:
    """The LED-array captures in the bright field whose LED did not fire, and how many times less light each got
    (:func:`judge_bright_field` on the images' means); none for frames scaled each on its own
    (``frame_scale: per_frame``).

    Returns
    -------
    indices : ndarray of int
    times_darker : ndarray of float
    """
    none = np.zeros(0, np.int64), np.zeros(0)
    geometry = captures.geometry
    if geometry.kind != "led_array" or captures.frame_scale != "shared":
        return none
    light = np.asarray(captures.intensity, np.float32).mean(axis=(-2, -1), dtype=np.float64)
    judged = judge_bright_field(light, geometry.spectrum_centres_yx_px, geometry.pupil_radius_px)
    return none if judged is None else (judged.unlit, judged.times_darker)


def _check_unlit(unlit, darker, dead: int, geometry: CaptureGeometry, *, name: str, source, error) -> None:
    """Refuse an unlit centre capture, or more left out (dead and unlit) than :data:`MAX_DEAD_FRACTION`; warn once,
    naming each, about the rest."""
    where = f"{source}: " if source else ""
    count = geometry.n_images

    def how_much(times: float) -> str:
        return "no light" if not np.isfinite(times) else \
            f"{times:.3g} times less light than the median bright-field capture"

    def less(times: float) -> str:
        return "none" if not np.isfinite(times) else f"{times:.3g} times less"

    if geometry.centre_index in unlit:
        times = float(darker[int(np.flatnonzero(unlit == geometry.centre_index)[0])])
        raise error(f"{where}image {geometry.centre_index} of {name}, the centre capture "
                    f"{_where(geometry, geometry.centre_index)}, recorded {how_much(times)}: did its LED fire? The "
                    "recovery needs it for the object's lowest frequencies; re-take it")
    allowed = int(MAX_DEAD_FRACTION * count)
    listed = "; ".join(f"image {int(i)} {_where(geometry, int(i))} {less(t)}" for i, t in zip(unlit[:6], darker)) \
        + ("; …" if unlit.size > 6 else "")
    if unlit.size + dead > allowed:
        raise error(f"{where}{unlit.size} bright-field images of {name} recorded {UNLIT_FACTOR:g} times less light "
                    f"than the median one or less ({listed}){f' and {dead} hold one value' if dead else ''}; at most "
                    f"{MAX_DEAD_FRACTION:.0%} of the captures ({allowed} here) may be left out: check the LEDs and "
                    "re-take them")
    _log.warning("%sleft out %d of %d images of %s in the bright field that recorded far less light than the median "
                 "bright-field capture (did their LEDs fire?): %s; the recovery uses the other %d", where, unlit.size,
                 count, name, listed, count - unlit.size - dead)


def check_dead_captures(dead, values, geometry: CaptureGeometry, *, name: str = "intensities", source=None,
                        error: type[Exception] = ValueError) -> None:
    """Refuse dead captures that cannot be left out; warn once, naming them, about those that can.

    Parameters
    ----------
    dead : array_like of int
        Indices of the captures whose images hold one value (:func:`~cca_cli.library.data.constant_images`).
    values : sequence of float
        The value each of them holds.
    geometry : CaptureGeometry
        The captures' geometry (names their grid positions and the centre capture).
    name, source, error
        As :func:`without_dead_captures`.

    Raises
    ------
    error
        The centre capture is dead, or more than :data:`MAX_DEAD_FRACTION` of the captures are.
    """
    centre = geometry.centre_index
    _check_dead(dead, values, geometry.n_images, noun="images", label=lambda i: f"image {i} {_where(geometry, i)}",
                key=(centre, f"image {centre}", f"the centre capture {_where(geometry, centre)}",
                     "and the recovery needs it for the object's lowest frequencies"),
                name=name, source=source, error=error)


def check_dead_measurements(dead, values, count: int, *, observed_first: bool, name: str = "intensities",
                            source=None, error: type[Exception] = ValueError) -> None:
    """:func:`check_dead_captures` for multiplexed measurements (no grid positions; the first measurement is
    the image the report compares with when the captures bring no reference)."""
    key = (0, "measurement 0", "the image the report compares with", "and the report needs it") \
        if observed_first else None
    _check_dead(dead, values, count, noun="measurements", label=lambda i: f"measurement {i}", key=key, name=name,
                source=source, error=error)


def _check_dead(dead, values, count: int, *, noun: str, label, key, name: str, source, error) -> None:
    """The dead-capture rule: ``key`` (index, label, role, why it is needed) refused, more than
    :data:`MAX_DEAD_FRACTION` of ``count`` refused, the rest one warning naming each by ``label``."""
    dead = np.asarray(dead, np.int64).reshape(-1)
    if dead.size == 0:
        return
    where = f"{source}: " if source else ""
    holds = "holds" if dead.size == 1 else "hold"
    if key is not None and key[0] in dead:
        index, key_label, role, why = key
        value = float(values[int(np.flatnonzero(dead == index)[0])])
        raise error(f"{where}{key_label} of {name}, {role}, holds one value (every pixel {value:g}): nothing was "
                    f"recorded there, {why}; re-take it")
    listed = ", ".join(label(int(i)) for i in dead[:6]) + (", …" if dead.size > 6 else "")
    allowed = int(MAX_DEAD_FRACTION * count)
    if dead.size > allowed:
        each = "" if dead.size == 1 else " each"
        raise error(f"{where}{dead.size} of {count} {noun} of {name} {holds} one value{each}, so nothing was "
                    f"recorded there ({listed}); at most {MAX_DEAD_FRACTION:.0%} of the "
                    f"{'captures' if noun == 'images' else noun} ({allowed} here) may be left out: check the camera "
                    "and re-take them")
    shown = ", ".join(f"{float(v):g}" for v in list(values)[:6])
    _log.warning("%sleft out %s of %d %s of %s: %s %s one value (%s), nothing was recorded there; the "
                 "recovery uses the other %d", where, dead.size, count, noun, name, listed, holds, shown,
                 count - dead.size)


def drop_captures(captures: CaptureSet, dead) -> CaptureSet:
    """``captures`` without the images ``dead`` (with their weights and geometry; ``dropped`` names them)."""
    dead = np.asarray(dead, np.int64).reshape(-1)
    if dead.size == 0:
        return captures
    keep = np.setdiff1d(np.arange(captures.intensity.shape[0]), dead)
    weight = None if captures.weight is None else captures.weight[keep]
    return replace(captures, intensity=captures.intensity[keep], weight=weight,
                   geometry=captures.geometry.select(keep), dropped=tuple(int(i) for i in dead))


def embed_region(captures: CaptureSet, *, padding: str = "auto", guard_px: int | None = None,
                 apodize_px: int | None = None) -> tuple[CaptureSet, RegionEmbedding | None]:
    """Place recorded (open-boundary) or non-square images in the middle of a square grid with a guard band.

    Returns the captures on the square grid (geometry widened to it, weights
    0 in the guard band) and the embedding, or the captures unchanged and
    None for periodic square images or ``padding="off"``.
    See :mod:`cca_cli.sampling.region`.

    Raises
    ------
    ValueError
        Non-square images that may not be padded (``padding="off"``, or periodic simulated images).
    """
    if padding not in PADDING_MODES:
        raise ValueError(f"padding must be 'auto' or 'off', got {padding!r}")
    k, h, w = captures.intensity.shape
    if padding == "off" or (captures.boundary != "open" and h == w):
        if h != w:
            why = "with padding off" if captures.boundary == "open" else "simulated (periodic) captures"
            raise ValueError(f"the images are {w}x{h} px; {why} must be square (crop them, e.g. registration.crop_xywh)")
        return captures, None
    region = plan_embedding((h, w), captures.geometry.pupil_radius_px, guard_px=guard_px, apodize_px=apodize_px)
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


def drive_engine(engine, options: EngineOptions, *, progress: ProgressFn = silent, on_iteration=None,
                 history: History | None = None, checkpoint=None) -> tuple[np.ndarray, History, float]:
    """Run ``engine`` to completion, reporting every iteration as a progress event (and to ``on_iteration``).

    ``history`` holds the iterations a restored engine already ran; ``checkpoint`` (an object with
    ``start()`` and ``after_iteration(engine, history)``, e.g. the reconstruct stage's
    ``Checkpointing``) saves the state as it goes. An ``on_iteration`` that returns False ends the run
    after that iteration (``stopped_by`` ``callback``).

    Returns
    -------
    spectrum : ndarray
    history : History
    seconds : float
        Wall time of the iterations, those a restored engine ran before included.

    Raises
    ------
    DivergedError
        The spectrum holds NaN or Inf at the end.
    """
    total = options.max_iterations
    history = History() if history is None else history
    before = history.records[-1].seconds if history.records else 0.0

    def report(record: IterationRecord) -> bool:
        progress(ProgressEvent("reconstruct", "iterations", record.iteration, total,
                               {"residual": record.residual, "change": record.change}))
        go_on = on_iteration(record) if on_iteration is not None else None
        if checkpoint is not None:
            checkpoint.after_iteration(engine, history)
        return go_on is not False

    start = time.perf_counter()
    if checkpoint is not None:
        checkpoint.start()
    spectrum, history = run_engine(engine, on_iteration=report, history=history)
    if not np.all(np.isfinite(spectrum)):
        raise DivergedError(history.iterations)
    return spectrum, history, before + time.perf_counter() - start


def run_threads(engine: str, options: EngineOptions):
    """The thread limit a run of ``engine`` takes when ``options`` name no threads (a context manager).

    An engine that takes at most N threads when none are named (``max_threads``: the momentum engines'
    :data:`~cca_cli.engines.momentum.DEFAULT_THREADS`) runs its set-up, FFTs and fit report on at most N
    too: on 16 cores the blood smear's default run took 3.31 s with every core, 2.80 s with four and 2.47 s
    with two (2026-11-27, ``benchmarks/bench_threads.py``), as threads beyond the lanes only split small
    transforms. Named threads, or fewer cores than N, are left as they are.
    """
    cap = getattr(get_engine(engine).engine_class(), "max_threads", None)
    if cap is None or getattr(options, "threads", None) or fft.default_threads() <= cap:
        return contextlib.nullcontext()
    return fft.limit_threads(cap)


def recover(captures: CaptureSet, engine: str, options: EngineOptions, *, progress: ProgressFn = silent,
            on_iteration=None, init: np.ndarray | None = None, checkpoint=None,
            aberration=None, device: str = "cpu") -> Reconstruction:
    """Phase retrieval of ``captures`` (square, on the grid they are recovered on) with a named engine.

    Builds the forward model on the smallest grids the band allows (wider when
    positions are calibrated), tells the engine what the geometry knows (cameras,
    how positions may move, a known defocus), runs it, and evaluates the final
    model's residuals.

    Parameters
    ----------
    captures : CaptureSet
    engine : str
        Registered engine name.
    options : EngineOptions
        The engine's options.
    progress : callable, optional
        Receives a progress event per iteration.
    on_iteration : callable, optional
        Also called with each :class:`~cca_cli.engines.base.IterationRecord`.
    init : ndarray, complex64, (M, M), optional
        A spectrum to start from instead of the upsampled centre capture.
    checkpoint : optional
        The reconstruct stage's ``Checkpointing``: continue from its checkpoint when one matches and is
        sound (finite, of this engine's shapes); write new ones as the run goes.
    aberration : ndarray, (n_modes,) or (P, n_modes), optional
        Zernike coefficients (waves) the pupil starts from, in place of what the captures know
        (a tiled reconstruction passes a neighbour tile's).
    device : {"cpu", "cuda", "auto"}
        Where the engine runs (:func:`engine_device`): ``cuda`` runs the engine's batched form
        (:mod:`cca_cli.engines.batched`) on CuPy arrays.

    Returns
    -------
    Reconstruction
        Of the whole grid (``object`` is the grid's field).

    Raises
    ------
    ValueError
        A geometry no grid can hold, or ``init`` of another grid.
    """
    with run_threads(engine, options), fft.one_blas_thread():
        return _recover(captures, engine, options, progress=progress, on_iteration=on_iteration, init=init,
                        checkpoint=checkpoint, aberration=aberration, device=device)


def _recover(captures: CaptureSet, engine: str, options: EngineOptions, *, progress: ProgressFn, on_iteration,
             init: np.ndarray | None, checkpoint, aberration, device: str) -> Reconstruction:
    """:func:`recover` within its thread limit (:func:`run_threads`)."""
    margin = 0
    if options.refines_positions:
        margin = int(np.ceil(captures.geometry.pupil_radius_px / 8)) + 2
    model = build_model(captures.geometry, captures.intensity.shape[-1], margin_px=margin)
    calibration = problem_calibration(captures.geometry, model.layout, captures.initial_pupil)
    if aberration is not None:
        calibration["aberration"] = np.asarray(aberration, np.float64)
    problem = PhaseRetrievalProblem.from_sensor_images(model, captures.intensity, captures.weight,
                                                       threads=getattr(options, "threads", None) or fft.default_threads(),
                                                       **calibration)
    start = None
    if init is not None:
        start = np.asarray(init, np.complex64)
        if start.shape != model.spectrum_shape:
            raise ValueError(f"init: the spectrum is {start.shape[0]}x{start.shape[-1]} but this reconstruction's "
                             f"grid is {model.spectrum_shape[0]}x{model.spectrum_shape[1]}; start from a result of "
                             "the same captures (and padding)")
    device = engine_device(device, engine, options)
    engine_class = _engine_factory(engine, device)
    runner = engine_class(problem, options, spectrum=start)
    history = None
    saved = checkpoint.load(_state_of(runner)) if checkpoint is not None else None
    if saved is not None:
        try:
            runner.restore(saved.state)
            history = History.from_columns(saved.history)
            _log.warning("note: resuming from iteration %d (checkpoint %s)", history.iterations, checkpoint.path)
        except (KeyError, ValueError, TypeError, NotImplementedError) as exc:
            _log.warning("%s cannot be resumed (%s): starting afresh", checkpoint.path, exc)
            runner.close()
            runner, history = engine_class(problem, options, spectrum=start), None
    spectrum, history, seconds = drive_engine(runner, options, progress=progress, on_iteration=on_iteration,
                                              history=history, checkpoint=checkpoint)
    found = runner.calibration() if isinstance(runner, CalibratingEngine) else None
    return Reconstruction(
        object=fft.ifft2c(spectrum).astype(np.complex64), spectrum=spectrum, history=history,
        geometry=captures.geometry, engine=engine, options=options.model_dump(), seconds=seconds,
        stopped_by=runner.stop_reason(), observed=captures.centre_image, truth=dict(captures.truth),
        units=captures.units, band_grid_px=model.layout.lowres_size,
        pupil=None if found is None else calibrated_pupils(found, captures.geometry.pupil_radius_px),
        positions_px=None if found is None else found.centres_px, calibration=found,
        fit=fit_report(problem, spectrum, found, threads=getattr(options, "threads", None) or fft.default_threads(),
                       device=device),
        dropped=captures.dropped,
        held_back=tuple(int(i) for i in runner.held_back), device=device)


def _engine_factory(engine: str, device: str):
    """What builds the engine: its CPU class, or its batched form bound to CuPy."""
    spec = get_engine(engine)
    if device == "cpu":
        return spec.engine_class()
    batched, xp = spec.batched_class(), backend.array_module(device)
    return lambda problem, options, spectrum=None: batched(problem, options, spectrum=spectrum, xp=xp)


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
