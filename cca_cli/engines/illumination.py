"""Illumination calibration: where each capture's pupil sits, and how bright each capture's light was.

Positions
---------
Capture ``i``'s field is ``ψ_i = F⁻¹{P_i(k − c_i) S(k)}``. The derivative of
the field with respect to its pupil centre is ``∂ψ_i/∂c_i = F⁻¹{∂P_i/∂c_i · S}``
(the pupils' anti-aliased edges make it well defined), one more inverse
transform per capture and axis. From it every capture gets the gradient
``g_i`` of its amplitude misfit and its Gauss–Newton curvature ``H_i``
(2 × 2). Captures that carry little light have small ``g_i`` and ``H_i``, so
a fit pooled over captures weighs them little by itself.

*Global* models explain all positions with a few parameters θ: an LED array's
shift, rotation and distance (:class:`LedArrayModel`), or a camera stage's
shift, rotation and scale (:class:`StageModel`). Their Gauss–Newton step is
``Δθ = −(Σ J_iᵀ H_i J_i)⁻¹ Σ J_iᵀ g_i`` with ``J_i = ∂c_i/∂θ``. *Per-image*
steps ``Δδ_i = −H_i⁻¹ g_i`` follow, kept only for captures whose misfit drops.

Brightness
----------
Each capture may have its own illumination brightness ``b_i`` (LED to LED,
or a camera's gain): ``√I_i ≈ √b_i |ψ_i|``. Its least-squares value
``√b_i = Σ|ψ_i|√I_i / Σ|ψ_i|²`` is shrunk towards 1 in proportion to how little
light the capture carries, so noise-dominated dark-field images keep ``b_i ≈ 1``.

References
----------
Eckert, Phillips & Waller, Appl. Opt. 57(19) (2018) (illumination self-calibration);
Tian et al., Biomed. Opt. Express 5(7) (2014).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.engines.options import POSITION_MODES
from cca_cli.engines.side_by_side import run_side_by_side
from cca_cli.optics.forward import ForwardModel, Workspace, chunk_slices

__all__ = ["POSITION_MODES", "CaptureStatistics", "PositionModel", "StageModel", "LedArrayModel",
           "capture_statistics", "global_step", "per_image_steps", "shrunk_brightness"]

#: Largest per-image position step in one round (spectrum pixels).
_MAX_IMAGE_STEP = 0.5


@dataclass(frozen=True)
class CaptureStatistics:
    """Per-capture sums over one evaluation of the model (weighted by the validity weights).

    Attributes
    ----------
    misfit : ndarray, float64, (K,)
        ``Σ w (|ψ| − √I)²``.
    power : ndarray, float64, (K,)
        ``Σ w |ψ|²``.
    cross : ndarray, float64, (K,)
        ``Σ w |ψ| √I``.
    energy : ndarray, float64, (K,)
        ``Σ w I``.
    gradient : ndarray, float64, (K, 2) or None
        ``∂ misfit_i / ∂ c_i`` (per spectrum pixel, ``[y, x]``).
    curvature : ndarray, float64, (K, 2, 2) or None
        Gauss–Newton curvature of ``misfit_i`` in ``c_i``.
    """

    misfit: np.ndarray
    power: np.ndarray
    cross: np.ndarray
    energy: np.ndarray
    gradient: np.ndarray | None = None
    curvature: np.ndarray | None = None


class PositionModel:
    """A few parameters θ that place every capture's pupil centre (spectrum pixels)."""

    #: Names of the parameters, in order.
    names: tuple[str, ...] = ()
    #: What the model describes (``"stage"`` or ``"led_array"``).
    kind: str = ""

    def centres(self, parameters: np.ndarray) -> np.ndarray:
        """Pupil centres ``[y, x]`` (K, 2) for parameters θ."""
        raise NotImplementedError

    @property
    def initial(self) -> np.ndarray:
        """θ of the nominal geometry."""
        return np.zeros(len(self.names))

    def jacobian(self, parameters: np.ndarray) -> np.ndarray:
        """``∂c_i/∂θ`` (K, 2, p) by central differences."""
        steps = self.steps
        out = np.empty(self.centres(parameters).shape + (len(parameters),))
        for j, h in enumerate(steps):
            up, down = parameters.copy(), parameters.copy()
            up[j] += h
            down[j] -= h
            out[..., j] = (self.centres(up) - self.centres(down)) / (2 * h)
        return out

    @property
    def steps(self) -> np.ndarray:
        """Finite-difference steps of the parameters."""
        return np.full(len(self.names), 1e-6)


class StageModel(PositionModel):
    """Scanned camera: nominal stage positions seen through a rotation and a scale about their mean.

    ``c_i = c̄ + (1 + s) R(φ) (c⁰_i − c̄)``: φ in radians, s the relative scale
    error (a wrong distance or pixel pitch). A shift of every position is left
    out: it equals a tilt of the object's phase, which the object takes.
    """

    names = ("rotation_rad", "scale")
    kind = "stage"

    def __init__(self, nominal_px: np.ndarray):
        self.nominal = np.asarray(nominal_px, np.float64).reshape(-1, 2)
        self._mean = self.nominal.mean(axis=0)

    def centres(self, parameters: np.ndarray) -> np.ndarray:
        angle, scale = parameters
        cos, sin = np.cos(angle), np.sin(angle)
        y, x = (self.nominal - self._mean).T
        return self._mean + (1 + scale) * np.stack([cos * y + sin * x, -sin * y + cos * x], axis=1)


class LedArrayModel(PositionModel):
    """Planar LED array: nominal illumination angles seen through the array's shift, rotation and height.

    Each LED's nominal direction ``sin θ`` is taken to the array plane at unit
    height (``u = tan θ``); the array is shifted by ``(d_y, d_x)`` (in units of
    the height), rotated by φ and its height scaled by ``1 + h``:
    ``u' = R(φ)(u + d) / (1 + h)``, ``sin θ' = u' / √(1 + |u'|²)``, and the pupil
    sits at ``pixels_per_sine · sin θ'``, less the mean move of all pupils: moving
    every pupil alike equals a tilt of the object's phase, which the object
    takes, so the shift acts only through how unevenly it moves the pupils.

    Parameters
    ----------
    nominal_px : ndarray, (K, 2)
        Nominal pupil centres (spectrum pixels).
    pixels_per_sine : float
        Spectrum pixels per unit ``sin θ`` (``sign · W / λ``).
    """

    names = ("shift_y", "shift_x", "rotation_rad", "height")
    kind = "led_array"

    def __init__(self, nominal_px: np.ndarray, pixels_per_sine: float):
        self.nominal = np.asarray(nominal_px, np.float64).reshape(-1, 2)
        self.pixels_per_sine = float(pixels_per_sine)
        sine = self.nominal / self.pixels_per_sine
        cosine = np.sqrt(np.clip(1.0 - np.sum(sine ** 2, axis=1, keepdims=True), 1e-12, None))
        self._tangent = sine / cosine

    def centres(self, parameters: np.ndarray) -> np.ndarray:
        dy, dx, angle, height = parameters
        cos, sin = np.cos(angle), np.sin(angle)
        y = self._tangent[:, 0] + dy
        x = self._tangent[:, 1] + dx
        u = np.stack([cos * y + sin * x, -sin * y + cos * x], axis=1) / (1.0 + height)
        sine = u / np.sqrt(1.0 + np.sum(u ** 2, axis=1, keepdims=True))
        centres = self.pixels_per_sine * sine
        return centres - centres.mean(axis=0) + self.nominal.mean(axis=0)


#: Chunks of captures a thread should have before another thread (and its workspace) is worth planning: a
#: workspace's FFTW plans take 10-20 ms to make, about what a thread spends on two to four chunks of 32 captures.
#: On 16 cores the blood smear's fit report planned 8 workspaces (0.10 s) for 0.02 s of work.
SLICES_PER_THREAD = 4


def capture_statistics(model: ForwardModel, spectrum: np.ndarray, amplitudes: np.ndarray,
                       weights: np.ndarray | None = None, *, pupil_derivatives: np.ndarray | None = None,
                       workspace: Workspace | None = None, scale: np.ndarray | None = None,
                       threads: int = 1) -> CaptureStatistics:
    """Evaluate the model once and sum, per capture, what the calibrations need.

    Parameters
    ----------
    model : ForwardModel
    spectrum : ndarray, complex64, (M, M)
    amplitudes : ndarray, float32, (K, m, m)
        Measured amplitudes (field layout, model units, the model's capture order).
    weights : ndarray, float32 or bool, (K, m, m), optional
        Confidence of each pixel (bool: recorded or not, as 1 and 0).
    pupil_derivatives : ndarray, complex64, (2, K, b, b), optional
        ``∂P_i/∂c_i`` along y and x: also compute each capture's position
        gradient and curvature (three inverse transforms per capture instead of one).
    workspace : Workspace, optional
        Reused when given.
    scale : ndarray, (K,), optional
        Factor applied to each capture's measured amplitudes (e.g. ``1/√brightness``).
    threads : int
        Without ``workspace``: chunks of captures run on up to this many threads side by side, each with
        its own workspace (each capture's figures are computed alike, whichever thread takes it); more than
        two threads only where each has :data:`SLICES_PER_THREAD` chunks of 32 captures.

    Returns
    -------
    CaptureStatistics
    """
    k = model.n_images
    misfit, power, cross, energy = (np.zeros(k) for _ in range(4))
    positions = pupil_derivatives is not None
    gradient = np.zeros((k, 2)) if positions else None
    curvature = np.zeros((k, 2, 2)) if positions else None
    derivatives = [ForwardModel(model.layout, d) for d in pupil_derivatives] if positions else None

    def one_chunk(sl: slice, workspace: Workspace) -> None:
        fields = model.forward_into(spectrum, sl, workspace).copy()
        magnitude = np.abs(fields)
        measured = amplitudes[sl] if scale is None else amplitudes[sl] * scale[sl, None, None].astype(np.float32)
        w = np.ones_like(measured) if weights is None else weights[sl]
        misfit[sl] = np.sum(w * (magnitude - measured) ** 2, axis=(1, 2), dtype=np.float64)
        power[sl] = np.sum(w * magnitude ** 2, axis=(1, 2), dtype=np.float64)
        cross[sl] = np.sum(w * magnitude * measured, axis=(1, 2), dtype=np.float64)
        energy[sl] = np.sum(w * measured ** 2, axis=(1, 2), dtype=np.float64)
        if not positions:
            return
        unit = fields / np.maximum(magnitude, 1e-30)
        radial = []
        for axis in range(2):
            derivative = derivatives[axis].forward_into(spectrum, sl, workspace)
            radial.append(np.real(np.conj(unit) * derivative))
        for a in range(2):
            gradient[sl, a] = 2 * np.sum(w * (magnitude - measured) * radial[a], axis=(1, 2), dtype=np.float64)
            for b in range(2):
                curvature[sl, a, b] = 2 * np.sum(w * radial[a] * radial[b], axis=(1, 2), dtype=np.float64)

    def chunks(slices: list[slice], workspace: Workspace) -> None:
        for sl in slices:
            one_chunk(sl, workspace)

    if workspace is not None:
        chunks(chunk_slices(k, workspace.capacity), workspace)
        return CaptureStatistics(misfit, power, cross, energy, gradient, curvature)
    slices = chunk_slices(k, min(32, k))
    count = max(1, min(int(threads), len(slices), max(2, len(slices) // SLICES_PER_THREAD)))
    if count == 1:
        chunks(slices, model.workspace(min(32, k)))
    else:   # each thread its own workspace and chunks; every capture's figures land in its own rows
        spaces = [model.workspace(min(32, k), threads=1) for _ in range(count)]
        run_side_by_side(lambda t: chunks(slices[t::count], spaces[t]), count)
    return CaptureStatistics(misfit, power, cross, energy, gradient, curvature)


def global_step(position_model: PositionModel, parameters: np.ndarray, offsets: np.ndarray,
                statistics: CaptureStatistics, *, damping: float = 1e-3) -> np.ndarray:
    """Gauss–Newton step of the global parameters from per-capture gradients and curvatures.

    Parameters
    ----------
    position_model : PositionModel
    parameters : ndarray, (p,)
        Current θ.
    offsets : ndarray, (K, 2)
        Per-image offsets added to the model's centres (held fixed here).
    statistics : CaptureStatistics
        With gradients and curvatures, evaluated at ``centres(θ) + offsets``.
    damping : float
        Levenberg–Marquardt damping relative to the normal matrix's diagonal.

    Returns
    -------
    ndarray, (p,)
        The parameter change Δθ.
    """
    jacobian = position_model.jacobian(parameters)  # (K, 2, p)
    normal = np.einsum("kap,kab,kbq->pq", jacobian, statistics.curvature, jacobian)
    rhs = np.einsum("kap,ka->p", jacobian, statistics.gradient)
    diagonal = np.diag(normal).copy()
    if not np.all(diagonal > 0):
        return np.zeros_like(parameters)
    damped = normal + damping * np.diag(diagonal) + 1e-12 * diagonal.max() * np.eye(len(parameters))
    return -np.linalg.solve(damped, rhs)


def per_image_steps(statistics: CaptureStatistics, *, damping: float = 0.1,
                    max_step: float = _MAX_IMAGE_STEP) -> np.ndarray:
    """Damped Gauss–Newton position step of every capture on its own, (K, 2) spectrum pixels.

    The damping adds ``damping`` times the mean of the curvature's diagonal over
    all captures, so captures with little light (small curvature) barely move.
    The steps' mean is removed: moving every capture alike is the object's tilt.
    """
    curvature = statistics.curvature
    scale = float(np.mean(np.trace(curvature, axis1=1, axis2=2))) / 2
    damped = curvature + damping * max(scale, 1e-30) * np.eye(2)[None]
    step = -np.linalg.solve(damped, statistics.gradient[..., None])[..., 0]
    step = np.clip(step, -max_step, max_step)
    return step - step.mean(axis=0)


def shrunk_brightness(statistics: CaptureStatistics, current: np.ndarray, *, shrinkage: float = 0.05) -> np.ndarray:
    """Per-capture brightness ``b_i`` (multiplying the modelled intensity), shrunk towards 1.

    ``√b_i = (Σ|ψ|√I + λ) / (Σ|ψ|² + λ)`` with ``λ = shrinkage · median(Σ|ψ|²)``,
    then divided by its median so the object keeps the overall scale, and held to
    ``0.2 … 5`` (``0.001 … 1000`` without a prior: images scaled each on its own).

    Parameters
    ----------
    statistics : CaptureStatistics
        Evaluated against the measured amplitudes divided by ``√current``.
    current : ndarray, (K,)
        The brightness those amplitudes were divided by.
    shrinkage : float
        Relative weight of the prior ``b = 1`` (0: none).

    Returns
    -------
    ndarray, float64, (K,)
    """
    prior = shrinkage * float(np.median(statistics.power))
    cross = statistics.cross * np.sqrt(current)
    root = (cross + prior) / (statistics.power + prior + 1e-300)
    middle = float(np.median(root))
    if not (middle > 0 and np.isfinite(middle)):   # most captures explained by nothing: keep what they had
        return np.asarray(current, np.float64)
    root /= middle
    low, high = (0.2, 5.0) if shrinkage > 0 else (1e-3, 1e3)
    return np.clip(root, low, high) ** 2
