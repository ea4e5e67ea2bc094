"""How well a recovery explains its captures: the amplitude residual per capture and over sets of captures.

The residual of a set ``C`` of captures is ``‖s √b_k |ψ_k| − √I_k‖ / ‖√I_k‖``
summed over ``k ∈ C``, with ``ψ_k`` the model's field (calibrated pupils and
positions), ``b_k`` the fitted brightness and ``s`` one least-squares scale
shared by all captures (the recovery is scale-free); ``I_k`` is the measured
intensity less a fitted background (:mod:`~cca_cli.engines.background`). Bright-field captures are
those whose illumination falls inside the NA (pupil centre within one radius
of DC); in them the object's unscattered light reaches the sensor.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

import numpy as np

from cca_cli.engines.background import less_background
from cca_cli.engines.batched import BoxOperator, capture_groups
from cca_cli.engines.illumination import CaptureStatistics, capture_statistics
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.optics import backend
from cca_cli.optics.forward import ForwardModel
from cca_cli.sampling.grid import band_layout

__all__ = ["FitReport", "fit_report", "bright_field", "device_statistics"]


@dataclass(frozen=True)
class FitReport:
    """Amplitude residuals of a recovery.

    Attributes
    ----------
    per_image : ndarray, float64, (K,)
        Each capture's relative residual (with brightness, global scale).
    all, bright_field, dark_field : float
        Relative residual over all, bright-field and dark-field captures (nan for an empty set).
    all_without_brightness, bright_field_without_brightness, dark_field_without_brightness : float
        The same with every brightness set to 1.
    bright_field_mask : ndarray, bool, (K,)
    """

    per_image: np.ndarray
    all: float
    bright_field: float
    dark_field: float
    all_without_brightness: float
    bright_field_without_brightness: float
    dark_field_without_brightness: float
    bright_field_mask: np.ndarray


def bright_field(problem: PhaseRetrievalProblem) -> np.ndarray:
    """Which captures are bright-field (nominal pupil centre within one pupil radius of DC), bool (K,)."""
    layout = problem.model.layout
    return np.hypot(layout.centres_px[:, 0], layout.centres_px[:, 1]) < layout.pupil_radius_px


def _split(statistics: CaptureStatistics, brightness: np.ndarray, masks: list[np.ndarray]) -> tuple[np.ndarray, list]:
    root = np.sqrt(brightness)
    power = statistics.power * brightness
    cross = statistics.cross * root
    scale = float(cross.sum() / max(power.sum(), 1e-300))
    squared = np.maximum(scale * scale * power - 2 * scale * cross + statistics.energy, 0.0)
    per_image = np.sqrt(squared / np.maximum(statistics.energy, 1e-300))  # 0-energy captures: large, not nan
    totals = [float(np.sqrt(squared[m].sum() / statistics.energy[m].sum())) if statistics.energy[m].sum() > 0
              else float("nan") for m in masks]
    return per_image, totals


def fit_report(problem: PhaseRetrievalProblem, spectrum: np.ndarray, calibration=None, *,
               threads: int = 1, device: str = "cpu") -> FitReport:
    """Residuals of ``spectrum`` (and an engine's calibration) against the problem's captures.

    Parameters
    ----------
    problem : PhaseRetrievalProblem
    spectrum : ndarray, complex64, (M, M)
    calibration : Calibration, optional
        Pupils, centres and brightness an engine arrived at; without it the
        problem's own model (nominal pupils and positions, brightness 1).
    threads : int
        Threads that evaluate the model (:func:`~cca_cli.engines.illumination.capture_statistics`).
    device : str
        ``cpu``, or ``cuda`` to evaluate the model on the GPU (:func:`device_statistics`; the figures then
        differ from the CPU's in float32 rounding only).

    Returns
    -------
    FitReport
    """
    model, brightness = problem.model, np.ones(problem.model.n_images)
    amplitudes = problem.amplitudes
    if calibration is not None and calibration.background_planes is not None:
        amplitudes = less_background(amplitudes, calibration.background_planes)
    if calibration is not None:
        nominal = problem.model.layout
        layout = band_layout(calibration.centres_px, nominal.pupil_radius_px, hires_size=nominal.hires_size,
                             lowres_size=nominal.lowres_size)
        model = ForwardModel.sharing(layout, calibration.pupils)   # unchanged while the report runs
        brightness = np.asarray(calibration.brightness, np.float64)
    # Every recorded pixel counts alike (a guard band or a saturated pixel, weight 0, does not): the engines'
    # confidence weights taper region edges, which would leave the misfit there out of the figure.
    recorded = None if problem.weights is None else problem.weights > 0   # a quarter of float32's bytes
    if device == "cpu":
        statistics = capture_statistics(model, spectrum, amplitudes, recorded, threads=threads)
    else:
        statistics = device_statistics(backend.array_module(device), model, spectrum, amplitudes, recorded)
    bright = bright_field(problem)
    masks = [np.ones_like(bright), bright, ~bright]
    per_image, (every, light, dark) = _split(statistics, brightness, masks)
    _, (every_plain, light_plain, dark_plain) = _split(statistics, np.ones_like(brightness), masks)
    return FitReport(per_image, every, light, dark, every_plain, light_plain, dark_plain, bright)


def device_statistics(xp: ModuleType, model: ForwardModel, spectrum: np.ndarray, amplitudes: np.ndarray,
                      recorded: np.ndarray | None = None) -> CaptureStatistics:
    """:func:`~cca_cli.engines.illumination.capture_statistics` (no position terms) on the device of ``xp``.

    The model's fields are formed by the batched engines' box operator, a group of captures per call, and
    only the four sums per capture come back to the host.

    Parameters
    ----------
    xp : module
        numpy or CuPy.
    model : ForwardModel
    spectrum : ndarray, complex64, (M, M)
    amplitudes : ndarray, float32, (K, m, m)
        Measured amplitudes (field layout, model units).
    recorded : ndarray, bool, (K, m, m), optional
        Pixels that count (all without it).

    Returns
    -------
    CaptureStatistics
    """

    operator = BoxOperator(xp, model.layout)
    on_device = backend.to_device(np.asarray(spectrum, np.complex64), xp)
    pupils = backend.to_device(np.ascontiguousarray(model.pupil_boxes, np.complex64), xp)
    sums = xp.zeros((4, model.n_images), xp.float64)
    for group in capture_groups(model.n_images, model.layout.lowres_size):
        magnitude = xp.abs(operator.fields(on_device, group, pupils[group]))
        measured = backend.to_device(amplitudes[group], xp, xp.float32)
        weight = 1 if recorded is None else backend.to_device(recorded[group], xp).astype(xp.float32)
        for row, term in enumerate((xp.square(magnitude - measured), xp.square(magnitude), magnitude * measured,
                                    xp.square(measured))):
            sums[row, group] = xp.sum(weight * term, axis=(1, 2), dtype=xp.float64)
    misfit, power, cross, energy = backend.to_host(sums)
    return CaptureStatistics(misfit, power, cross, energy, None, None)
