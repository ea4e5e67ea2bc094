"""Model calibration of a sequential engine: pupils, capture positions and brightness.

Real captures do what the ideal model does not: the lens is aberrated, LEDs or
stage positions are off, and the light varies. A :class:`Calibrator` keeps
what the engine has learned of these (all optional, as the options say) and
hands the engine the pupils and positions to use:

- *pupil recovery* (:mod:`cca_cli.engines.pupil_recovery`): one pupil shared
  by all captures or one per camera, as a full complex map inside the NA
  (EPRY) or as Zernike modes; its step is formed from the batch residuals of a
  pass and taken at the end of the pass;
- *positions* and *brightness* (:mod:`cca_cli.engines.illumination`): after
  ``calibration_start`` passes and every ``calibration_every`` passes, a
  global position model (LED array shift / rotation / height, or stage shift
  / rotation / scale) and then each capture's own offset take Gauss–Newton
  steps kept only where the misfit drops, and each capture's brightness its
  shrunk least-squares value.

Everything here is in the problem's capture order.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cca_cli.engines import background as bg
from cca_cli.engines import calibration as cal
from cca_cli.engines import illumination as ill
from cca_cli.engines.options import MomentumOptions
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.pupil_recovery import PupilEstimate, PupilRecovery, resample_pupil
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.optics.zernike import zernike_modes
from cca_cli.sampling.grid import BandLayout, band_layout

__all__ = ["Calibration", "Calibrator", "subset_layout"]

#: Captures with less than this share of the brightest capture's energy are left out of the aberration estimate.
_ESTIMATE_LIGHT = 0.01
#: Relative misfit drop a capture's position step must bring to be kept.
_CLEAR_GAIN = 1e-2


@dataclass(frozen=True)
class Calibration:
    """The model calibration an engine arrived at (the problem's capture order).

    Attributes
    ----------
    centres_px : ndarray, float64, (K, 2)
        Pupil centres ``[y, x]`` in use (spectrum pixels from DC).
    offsets : ndarray, float64, (K, 2)
        ``centres_px`` minus the nominal centres (spectrum pixels).
    pupils : ndarray, complex64, (K, b, b)
        Every capture's pupil on its box.
    pupil_index : ndarray, int64, (K,)
        Pupil (camera) each capture uses.
    pupil : PupilEstimate or None
        The recovered pupils (None without pupil recovery).
    brightness : ndarray, float64, (K,)
        Illumination brightness of each capture (1 without brightness fitting).
    position_model : str or None
        ``"led_array"`` or ``"stage"`` when a global position model was fitted.
    position_parameters : dict or None
        Its parameters by name.
    background_planes : ndarray, float64, (K, 3), or None
        Each capture's background plane ``[a, s, t]`` (``a + s y + t x``, model intensity units, pixels from
        the frame's centre; :mod:`~cca_cli.engines.background`), None where none is fitted.
    background : ndarray, float64, (K,), or None
        The mean of each capture's background over the frame, in the captures' intensity units.
    """

    centres_px: np.ndarray
    offsets: np.ndarray
    pupils: np.ndarray
    pupil_index: np.ndarray
    pupil: PupilEstimate | None
    brightness: np.ndarray
    position_model: str | None = None
    position_parameters: dict | None = None
    background_planes: np.ndarray | None = None
    background: np.ndarray | None = None

    @property
    def coefficients(self) -> np.ndarray | None:
        """Zernike coefficients (waves) of the first pupil, None without pupil recovery."""
        return None if self.pupil is None else self.pupil.coefficients[0]


def subset_layout(layout: BandLayout, index: np.ndarray) -> BandLayout:
    """The layout of captures ``index`` (in that order)."""
    return replace(layout, centres_px=layout.centres_px[index], box_origins=layout.box_origins[index],
                   box_centres=layout.box_centres[index])


class Calibrator:
    """Pupils, positions and brightness of a problem's captures, and their calibration steps.

    Parameters
    ----------
    problem : PhaseRetrievalProblem
    options : MomentumOptions
        ``pupil_*``, ``position_refinement``, ``brightness`` and ``calibration_*`` are read.
    threads : int
        Threads the pupil recovery accumulates on (one sum per thread).
    """

    def __init__(self, problem: PhaseRetrievalProblem, options: MomentumOptions, threads: int):
        self.problem = problem
        self.options = options
        self.nominal = problem.model.layout
        k = problem.model.n_images
        self.pupil_index = problem.pupil_indices()
        if options.pupil_recovery == "shared":
            self.pupil_index = np.zeros(k, np.int64)
        self.brightness = np.ones(k)
        self.background = np.zeros((k, 3))   # each capture's background plane (:mod:`cca_cli.engines.background`)
        # the captures a background plane is fitted to: dark-field ones that never fall to zero
        self._floored = None
        self._measured = None   # the measured amplitudes less their background (problem order), while one is fitted
        if options.background:
            dark = bg.dark_field_captures(self.nominal.centres_px, self.nominal.pupil_radius_px)
            self._floored = dark & bg.holds_floor(problem.amplitudes, problem.weights)
        self.offsets = np.zeros((k, 2))
        self.position_model = problem.position_model if options.position_refinement in ("global", "both") else None
        self.parameters = None if self.position_model is None else self.position_model.initial
        self._fixed_coefficients = self._starting_coefficients()
        self._fixed_map = None
        if problem.initial_pupil is not None:
            self._fixed_map = resample_pupil(problem.initial_pupil, self.nominal.box_size, self.nominal.pupil_radius_px)
            self._fixed_coefficients = None
        self.recovery = None
        if options.pupil_recovery != "none":
            self.recovery = PupilRecovery(
                self.nominal, self.pupil_index, model=options.pupil_model, order=options.pupil_order,
                coefficients=self._fixed_coefficients, amplitude=options.pupil_amplitude,
                step=options.pupil_step, threads=threads, maps=self._fixed_map, tilt=options.pupil_tilt,
                smoothing=options.pupil_smoothing, lattice=options.pupil_lattice,
                damping=options.pupil_damping, momentum=options.pupil_momentum,
                known=problem.aberration is not None or problem.initial_pupil is not None)
        self._workspace = None

    def _starting_coefficients(self) -> np.ndarray | None:
        """Zernike coefficients per pupil to start from: the captures' known aberration, or the shift estimate."""
        opts, problem = self.options, self.problem
        n_modes = len(zernike_modes(opts.pupil_order))
        n_pupils = int(self.pupil_index.max()) + 1
        if problem.aberration is not None:
            known = np.zeros((n_pupils, n_modes))
            given = np.atleast_2d(np.asarray(problem.aberration, np.float64))
            known[:, :min(n_modes, given.shape[1])] = given[:, :n_modes]
            return known
        if opts.pupil_recovery == "none" or not opts.pupil_estimate:
            return None
        estimate = np.zeros((n_pupils, n_modes))
        # Shifts are measured on the captures with light to spare: noise-dominated dark-field images only add cost.
        energy = problem.capture_energies
        lit = energy >= _ESTIMATE_LIGHT * energy.max()
        for p in range(n_pupils):
            members = np.flatnonzero((self.pupil_index == p) & lit)
            layout = subset_layout(self.nominal, members)
            weights = None if problem.weights is None else problem.weights[members]
            estimate[p, :3] = cal.estimate_quadratic_aberration(layout, problem.amplitudes[members], weights)
        return estimate

    # ------------------------------------------------------------ the model it gives
    def centres(self, parameters=None, offsets=None) -> np.ndarray:
        """Pupil centres for global parameters and per-image offsets (default: the current ones)."""
        parameters = self.parameters if parameters is None else parameters
        offsets = self.offsets if offsets is None else offsets
        base = self.nominal.centres_px if parameters is None else self.position_model.centres(parameters)
        return base + offsets

    def layout_for(self, centres: np.ndarray) -> BandLayout:
        """The captures laid out at ``centres`` on the nominal grids."""
        nominal = self.nominal
        return band_layout(centres, nominal.pupil_radius_px, hires_size=nominal.hires_size,
                           lowres_size=nominal.lowres_size)

    def pupils_for(self, layout: BandLayout, index: np.ndarray) -> np.ndarray:
        """Pupils of captures laid out by ``layout`` that use pupils ``index``."""
        if self.recovery is not None:
            return self.recovery.pupils_at(layout, index)
        if self._fixed_map is not None:
            return circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px) * self._fixed_map
        coefficients = None
        if self._fixed_coefficients is not None:
            coefficients = self._fixed_coefficients[index]
        return cal.pupil_functions(layout, coefficients=coefficients, order=self.options.pupil_order)

    def target_scale(self, order: np.ndarray) -> np.ndarray:
        """``1/√brightness`` of captures ``order``, float32: measured amplitudes over it are the model's targets."""
        return (1.0 / np.sqrt(self.brightness[order])).astype(np.float32)

    # ------------------------------------------------------------ pupil steps
    def pupil_step(self, misfit: float, iteration: int) -> tuple[complex, np.ndarray] | None:
        """The end-of-pass pupil step; the pupils' common scale and tilt for the spectrum to take over, or None.

        ``iteration`` is the 0-based pass that just ended; none is taken before ``pupil_start`` passes.
        """
        if self.recovery is None or iteration + 1 < self.options.pupil_start:
            return None
        return self.recovery.step(misfit)

    # ------------------------------------------------------------ positions and brightness
    def due(self, iteration: int) -> bool:
        """Whether a position / brightness round is due before pass ``iteration`` (0-based)."""
        opts = self.options
        if opts.position_refinement == "none" and not opts.brightness and not opts.background:
            return False
        since = iteration - opts.calibration_start
        return since >= 0 and since % opts.calibration_every == 0

    def round(self, spectrum: np.ndarray) -> tuple[bool, bool]:
        """One round of position and brightness calibration against ``spectrum``.

        Returns
        -------
        moved : bool
            Positions changed (the engine lays the captures out anew).
        relit : bool
            Brightness changed while positions did not (the engine's targets change).
        """
        opts = self.options
        moved = False
        if self.position_model is not None:
            moved |= self._global_position_step(spectrum)
        if opts.position_refinement in ("per_image", "both"):
            moved |= self._per_image_position_step(spectrum)
        relit = False
        if opts.brightness:
            statistics = self.evaluate(spectrum)
            self.brightness = ill.shrunk_brightness(statistics, self.brightness, shrinkage=opts.brightness_prior)
            relit = not moved
        if opts.background:
            layout = self.layout_for(self.centres())
            model = ForwardModel(layout, self.pupils_for(layout, self.pupil_index))
            self.background = bg.background_planes(model, spectrum, self.problem.amplitudes, self.problem.weights,
                                                   self.brightness, self._floored, self._work(model))
            self._measured = None
            relit = not moved
        return moved, relit

    def exclude(self, captures: np.ndarray) -> None:
        """Fit no background to ``captures`` (held back from the updates: they judge the fit, not join it)."""
        if self._floored is not None:
            self._floored[np.asarray(captures, np.int64)] = False

    def measured(self, captures: np.ndarray | slice = slice(None)) -> np.ndarray:
        """The measured amplitudes of ``captures`` (problem order) less their fitted background, float32."""
        if not np.any(self.background):
            return self.problem.amplitudes[captures]
        if self._measured is None:   # once per background, however often the round evaluates the model
            self._measured = bg.less_background(self.problem.amplitudes, self.background)
        return self._measured[captures]

    def _work(self, model: ForwardModel):
        if self._workspace is None:
            self._workspace = model.workspace(min(32, model.n_images), threads=1)
        return self._workspace

    def evaluate(self, spectrum: np.ndarray, *, parameters=None, offsets=None,
                 positions: bool = False) -> ill.CaptureStatistics:
        """Per-capture statistics of ``spectrum`` at the given positions."""
        layout = self.layout_for(self.centres(parameters, offsets))
        model = ForwardModel(layout, self.pupils_for(layout, self.pupil_index))
        derivatives = self._pupil_derivatives(layout) if positions else None
        scale = 1.0 / np.sqrt(self.brightness)
        return ill.capture_statistics(model, spectrum, self.measured(), self.problem.weights,
                                      pupil_derivatives=derivatives, workspace=self._work(model), scale=scale)

    def _pupil_derivatives(self, layout: BandLayout, step: float = 1e-3) -> np.ndarray:
        """``∂P_i/∂c_i`` along y and x by central differences of the pupils, complex64 (2, K, b, b)."""
        out = []
        for axis in range(2):
            shift = np.zeros(2)
            shift[axis] = step
            up = self.pupils_for(replace(layout, box_centres=layout.box_centres + shift), self.pupil_index)
            down = self.pupils_for(replace(layout, box_centres=layout.box_centres - shift), self.pupil_index)
            out.append((up - down) / np.float32(2 * step))
        return np.stack(out).astype(np.complex64)

    def _global_position_step(self, spectrum: np.ndarray) -> bool:
        statistics = self.evaluate(spectrum, positions=True)
        step = ill.global_step(self.position_model, self.parameters, self.offsets, statistics)
        before = float(statistics.misfit.sum())
        for _ in range(3):
            trial = self.parameters + step
            if self._total_misfit(spectrum, parameters=trial) < before:
                self.parameters = trial
                return True
            step = step / 2
        return False

    def _total_misfit(self, spectrum: np.ndarray, **positions) -> float:
        """Misfit at trial positions; infinite where the pupils would leave the spectrum grid."""
        try:
            return float(self.evaluate(spectrum, **positions).misfit.sum())
        except ValueError:
            return np.inf

    def _per_image_position_step(self, spectrum: np.ndarray) -> bool:
        statistics = self.evaluate(spectrum, positions=True)
        trial = self.offsets + ill.per_image_steps(statistics)
        limit = max(1.0, self.nominal.pupil_radius_px / 8)   # offsets stay within an eighth of a pupil radius
        trial = np.clip(trial, -limit, limit)
        try:  # keep a capture's move only where it lowers that capture's misfit clearly (not just its noise)
            better = self.evaluate(spectrum, offsets=trial).misfit < (1 - _CLEAR_GAIN) * statistics.misfit
        except ValueError:  # a pupil would leave the spectrum grid
            return False
        if not np.any(better):
            return False
        self.offsets[better] = trial[better]
        return True

    # ------------------------------------------------------------ results and checkpoints
    def calibration(self, pupils: np.ndarray) -> Calibration:
        """What was found, with every capture's pupil in use (``pupils``, problem order)."""
        centres = self.centres()
        position_parameters = None
        if self.position_model is not None:
            position_parameters = dict(zip(self.position_model.names, map(float, self.parameters)))
        return Calibration(
            centres_px=centres, offsets=centres - self.nominal.centres_px, pupils=pupils,
            pupil_index=self.pupil_index.copy(), pupil=None if self.recovery is None else self.recovery.estimate(),
            brightness=self.brightness.copy(),
            position_model=None if self.position_model is None else self.position_model.kind,
            position_parameters=position_parameters, **self._background_record())

    def _background_record(self) -> dict:
        """The fitted background planes and their means over the frame in capture units (empty where none)."""
        if not self.options.background:
            return {}
        mean = bg.plane_means(self.background, self.nominal.lowres_size)
        return {"background_planes": self.background.copy(),
                "background": mean / float(self.problem.model.intensity_scale)}

    def state(self) -> dict:
        """Brightness, offsets, global parameters and the pupil recovery's maps, coefficients, step size and momentum.

        Not kept: the pupil recovery's record of its last step (after a restore the
        next pass cannot undo that step if it fits worse; the step size is kept).
        """
        out = {"brightness": self.brightness, "offsets": self.offsets, "background": self.background}
        if self.parameters is not None:
            out["parameters"] = np.asarray(self.parameters, np.float64)
        if self.recovery is not None:
            out.update(pupil_maps=self.recovery.maps, pupil_coefficients=self.recovery.coefficients,
                       pupil_step=self.recovery.step_size)
            if self.recovery.velocity is not None:
                out["pupil_velocity"] = self.recovery.velocity
            if self.recovery.reference is not None:
                out["pupil_reference"] = self.recovery.reference
        return out

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state`."""
        self.brightness = np.array(state["brightness"], np.float64)
        if "background" in state:
            self.background = np.array(state["background"], np.float64).reshape(self.background.shape)
            self._measured = None
        self.offsets = np.array(state["offsets"], np.float64)
        if self.parameters is not None and "parameters" in state:
            self.parameters = np.array(state["parameters"], np.float64)
        if self.recovery is not None and "pupil_maps" in state:
            self.recovery.restore(np.array(state["pupil_maps"], np.complex64),
                                  np.array(state["pupil_coefficients"], np.float64), float(state["pupil_step"]),
                                  velocity=None if "pupil_velocity" not in state
                                  else np.array(state["pupil_velocity"], np.complex64),
                                  reference=state.get("pupil_reference"))
