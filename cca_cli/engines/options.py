"""Every engine's options: frozen pydantic models, importable without the engines' numeric code.

A config's ``reconstruct`` section, the Python API's keywords, tiles and
multiplexed runs all read options through these models (by way of
:func:`cca_cli.engines.registry.resolve`), so a value means the same wherever
it is given: ``"1e-3"`` is 0.001, ``2.0`` is the integer 2, ``true`` is no
number, and an unknown key or a value out of range is one line naming the
option (:mod:`cca_cli.values`).
"""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import model_validator

from cca_cli.values import StrictModel

__all__ = ["COSTS", "PUPIL_RECOVERIES", "PUPIL_MODELS", "POSITION_MODES", "ITERATIONS_ALIAS", "EngineOptions",
           "AltMinOptions", "MomentumOptions"]

COSTS = ("amplitude", "poisson")
PUPIL_RECOVERIES = ("none", "shared", "per_camera")
#: ``full``: the complex map inside the NA (EPRY); ``smooth``: that map held to Zernike modes plus a smooth remainder;
#: ``zernike``: the phase in Zernike modes.
PUPIL_MODELS = ("full", "smooth", "zernike")
#: What position refinement fits: nothing, a global model of the array or stage, each capture's own offset, or both.
POSITION_MODES = ("none", "global", "per_image", "both")
#: The friendly name of ``max_iterations`` (configs' ``reconstruct.iterations``, the API's ``iterations=``).
ITERATIONS_ALIAS = ("iterations", "max_iterations")


def _checked(checks) -> None:
    """Raise ValueError with the message of the first failed ``(condition, message)`` check."""
    for ok, message in checks:
        if not ok:
            raise ValueError(message)


class EngineOptions(StrictModel):
    """What every engine takes.

    Attributes
    ----------
    tau : float
        Added to the update denominator (pupil-power units: a spectrum pixel
        seen by one capture has ``Σ |P_i|² = 1``).
    max_iterations : int
        Cap on iterations (passes over all captures).
    tol : float
        Stop when the relative spectrum change of an iteration falls below it.
    threads : int or None
        Worker threads; None uses the cores the process may use.
    """

    tau: float = 1e-3
    max_iterations: int = 1000
    tol: float = 1e-5
    threads: Optional[int] = None

    @property
    def refines_positions(self) -> bool:
        """Whether the engine may move the captures' pupils (its spectrum grid then needs a margin)."""
        return False

    @property
    def recovers_pupil_map(self) -> bool:
        """Whether the engine recovers a full pupil map whose tilt (an image shift) may move the object: register results."""
        return False

    @model_validator(mode="after")
    def _common_ranges(self):
        _checked([
            (self.tau >= 0, f"tau must be ≥ 0, got {self.tau}"),
            (self.max_iterations >= 1, f"max_iterations must be ≥ 1, got {self.max_iterations}"),
            (self.tol >= 0, f"tol must be ≥ 0, got {self.tol}"),
            (self.threads is None or self.threads >= 1, f"threads must be an integer ≥ 1 or null, got {self.threads}"),
        ])
        return self


class AltMinOptions(EngineOptions):
    """Options of the alternating-minimization engine (:mod:`cca_cli.engines.altmin`).

    Attributes
    ----------
    tau : float
        Tikhonov weight τ added to ``Σ |P_i|²``.
    max_iterations : int
        Iteration cap (paper: 1000).
    tol : float
        Stop when the relative spectrum change ``‖ΔS‖/‖S‖`` falls below it (paper: 1e-5).
    chunk : int
        Captures processed together (cache-sized).
    plateau : float
        Also stop when the data misfit fell by less than this fraction over the
        last ``plateau_window`` iterations (0: never; the paper stops on ``tol``).
    plateau_window : int
        Iterations the plateau test looks back.
    threads : int or None
        Worker threads; None uses every core.
    """

    chunk: int = 16
    plateau: float = 0.0
    plateau_window: int = 50

    @model_validator(mode="after")
    def _ranges(self):
        _checked([(self.chunk >= 1, f"chunk must be an integer ≥ 1, got {self.chunk}"),
                  (0 <= self.plateau < 1, f"plateau must be in [0, 1), got {self.plateau}"),
                  (self.plateau_window >= 1, f"plateau_window must be ≥ 1, got {self.plateau_window}")])
        return self


class MomentumOptions(EngineOptions):
    """Options of the sequential momentum engine (:mod:`cca_cli.engines.momentum`).

    Attributes
    ----------
    tau : float
        Added to the update denominator (pupil-power units, as AltMin's τ).
    max_iterations : int
        Cap on passes over all captures.
    tol : float
        Stop when the relative spectrum change of a pass falls below it.
    plateau : float
        Stop when the data misfit fell by less than this fraction over the last
        ``plateau_window`` passes (0: never).
    plateau_window : int
        Passes the plateau test looks back.
    growth_window : int or None
        Passes the plateau test looks back while the batches can still grow
        (``batch_growth``); None: ``plateau_window``.
    alpha : float
        rPIE regularisation α in [0, 1]: 0 divides by the batch's pupil power
        (ePIE-like full projection), 1 by its maximum (small, uniform steps).
    beta : float
        Step size β in (0, 2).
    eta : float
        Momentum η in [0, 1); 0 gives plain (batched) rPIE.
    restart : bool
        Reset the momentum whenever a pass fits the data worse than the previous one.
    batch : int
        Captures updated together (1: strictly one aperture at a time). Shells
        of 2, 2, 4, 4, 8, … batches are visited in turn.
    batch_growth : int
        Each time the misfit reaches a plateau (``plateau`` > 0), the batch
        grows by this factor, until a batch may hold every capture; only then
        does a plateau end the run. 1: the batch stays fixed. Small batches
        make fast progress at first, but on data the model does not explain
        exactly they end in a cycle between the captures' constraints; growing
        batches take the run to a stationary point of the whole misfit.
    cost : {"amplitude", "poisson"}
        Magnitude replacement, or a gradient step on the Poisson likelihood,
        ``ψ' = ψ (1 − μ (1 − I/|ψ|²))``.
    poisson_step : float
        μ of the Poisson step; 0.5 makes the magnitude update a Newton step
        towards ``√I``.
    pupil_recovery : {"none", "shared", "per_camera"}
        No pupil recovery, one pupil for all captures (a scanned camera or an
        LED-array microscope), or one per camera of a camera array (the same as
        ``shared`` when the captures name no cameras).
    pupil_model : {"full", "smooth", "zernike"}
        The complex map inside the NA (amplitude and phase); that map held after
        each step to Zernike modes up to ``pupil_order`` plus a remainder smoothed
        over ``pupil_smoothing`` pupil radii (so the object's detail cannot settle
        in it); or the phase in Zernike modes up to ``pupil_order``.
    pupil_smoothing : float
        ``smooth`` model: width of the remainder's smoothing, in pupil radii.
    pupil_tilt : {"pupil", "object", "pinned"}
        Map models: a phase tilt the pupil step finds stays in the pupil, so the
        object stays where the captures put it (as in mPIE and EPRY); is handed
        to the object, which then moves with it (the predictions are the same);
        or is dropped.
    pupil_lattice : {"free", "filtered"}
        Map models, captures whose pupil centres lie on a lattice (an LED grid):
        the map may take any pattern, or after each step loses the patterns
        periodic on that lattice, which the data cannot tell from the object
        (:mod:`cca_cli.engines.lattice`); a filtered step is never undone.
        ``filtered`` in the LED-array preset.
    pupil_order : {2, 3, 4}
        Highest Zernike radial order fitted (``zernike``) or reported (``full``).
    pupil_amplitude : bool
        ``full`` model: recover the pupil's amplitude as well as its phase.
    pupil_start : int
        Passes before the first pupil step.
    pupil_step : float
        Initial pupil step fraction in (0, 1].
    pupil_damping : float
        Map models: each pupil pixel's step divides its sum of corrections by
        the light it saw plus this fraction of the most light any pixel saw,
        so pixels that saw little light (the object's weak spatial
        frequencies, noise) move the map less than those that saw much.
    pupil_momentum : float
        Map models: momentum of the pupil step in [0, 1), as mPIE gives its probe:
        each step adds this fraction of the steps before it (summed with the same
        decay), so a map that keeps moving one way converges in fewer passes. The
        momentum restarts when a pass fits worse than the one before. 0: none.
    pupil_estimate : bool
        Start the quadratic modes from the neighbour-shift estimate
        (:func:`~cca_cli.engines.calibration.estimate_quadratic_aberration`)
        unless the captures come with a known aberration.
    position_refinement : {"none", "global", "per_image", "both"}
        Nothing, a few parameters of the whole LED array or stage, each
        capture's own offset, or the global model and then each offset
        (``true``/``false`` are read as ``both``/``none``).
    brightness : bool
        Fit each capture's illumination brightness.
    brightness_prior : float
        Weight of the belief that every capture's brightness is 1, relative to the median capture's
        modelled power. With any weight the brightness is also held to 0.04 … 25 (a factor of 5 in
        amplitude); with 0 (images scaled each on its own) nothing pulls it and it may range over
        1e-6 … 1e6.
    background : bool
        Fit a plane of light to each dark-field capture that the object did not
        scatter (stray light, a camera offset left in), at each calibration round,
        and recover the object from the light less it
        (:mod:`~cca_cli.engines.background`).
    calibration_start : int
        Passes before the first position / brightness round.
    calibration_every : int
        Passes between position / brightness rounds.
    hold_back : float
        Share of the captures held back from the updates, spread from the
        bright field to the outermost dark field (0: none). Their misfit says how
        well the recovery predicts data it never fitted: see ``hold_back_patience``.
    hold_back_patience : int
        With captures held back: stop when their misfit has stayed more than 1%
        above its best for this many passes in a row, and return to the state of
        the best one (as also at the end of a run that stops otherwise while
        their misfit is above the best).
    threads : int or None
        Worker threads; None uses two, or one where the process may use one
        core only (on 16 cores the blood smear ran faster on two threads than on
        four; a pass uses at most 4, and more lanes only add hand-overs).
        One and two threads visit the captures in the same order and agree to
        float rounding; more threads split the spectrum further, so the
        visiting order (and the result, slightly) depends on their number. The
        same inputs and thread count give the same result. On a GPU, a given
        ``threads`` makes the engine visit the captures in the CPU engine's
        order for that count (unset: 8 lanes, the most captures per call).
    """

    max_iterations: int = 200
    plateau: float = 0.0
    plateau_window: int = 5
    growth_window: int | None = None
    alpha: float = 0.1
    beta: float = 1.0
    eta: float = 0.7
    restart: bool = True
    batch: int = 12
    batch_growth: int = 1
    cost: Literal["amplitude", "poisson"] = "amplitude"
    poisson_step: float = 0.5
    pupil_recovery: Literal["none", "shared", "per_camera"] = "none"
    pupil_model: Literal["full", "smooth", "zernike"] = "zernike"
    pupil_smoothing: float = 0.25
    pupil_tilt: Literal["pupil", "object", "pinned"] = "pupil"
    pupil_lattice: Literal["free", "filtered"] = "free"
    pupil_order: Literal[2, 3, 4] = 4
    pupil_amplitude: bool = True
    pupil_start: int = 1
    pupil_step: float = 1.0
    pupil_damping: float = 1e-3
    pupil_momentum: float = 0.0
    pupil_estimate: bool = True
    position_refinement: Literal["none", "global", "per_image", "both"] = "none"
    brightness: bool = False
    brightness_prior: float = 0.05
    background: bool = False
    calibration_start: int = 10
    calibration_every: int = 2
    hold_back: float = 0.0
    hold_back_patience: int = 10

    @property
    def refines_positions(self) -> bool:
        return self.position_refinement != "none"

    @property
    def recovers_pupil_map(self) -> bool:
        return self.pupil_recovery != "none" and self.pupil_model != "zernike" and self.pupil_tilt != "pinned"

    @model_validator(mode="before")
    @classmethod
    def _old_position_switch(cls, data):
        """Older configs say ``position_refinement: true`` / ``false``: read them as ``both`` / ``none``."""
        if isinstance(data, dict) and isinstance(data.get("position_refinement"), bool):
            data = dict(data, position_refinement="both" if data["position_refinement"] else "none")
        return data

    @model_validator(mode="after")
    def _ranges(self):
        _checked([
            (0 <= self.plateau < 1, f"plateau must be in [0, 1), got {self.plateau}"),
            (self.plateau_window >= 1, f"plateau_window must be ≥ 1, got {self.plateau_window}"),
            (self.growth_window is None or self.growth_window >= 1,
             f"growth_window must be ≥ 1 (or null: plateau_window), got {self.growth_window}"),
            (0 <= self.alpha <= 1, f"alpha must be in [0, 1], got {self.alpha}"),
            (0 < self.beta < 2, f"beta must be in (0, 2), got {self.beta}"),
            (0 <= self.eta < 1, f"eta must be in [0, 1), got {self.eta}"),
            (self.batch >= 1, f"batch must be ≥ 1, got {self.batch}"),
            (self.batch_growth >= 1, f"batch_growth must be ≥ 1, got {self.batch_growth}"),
            (0 < self.poisson_step <= 1, f"poisson_step must be in (0, 1], got {self.poisson_step}"),
            (self.pupil_start >= 0, f"pupil_start must be ≥ 0, got {self.pupil_start}"),
            (0 < self.pupil_step <= 1, f"pupil_step must be in (0, 1], got {self.pupil_step}"),
            (0 < self.pupil_damping <= 1, f"pupil_damping must be in (0, 1], got {self.pupil_damping}"),
            (0 <= self.pupil_momentum < 1, f"pupil_momentum must be in [0, 1), got {self.pupil_momentum}"),
            (0 < self.pupil_smoothing <= 2, f"pupil_smoothing must be in (0, 2], got {self.pupil_smoothing}"),
            (self.brightness_prior >= 0, f"brightness_prior must be ≥ 0, got {self.brightness_prior}"),
            (self.calibration_start >= 0, f"calibration_start must be ≥ 0, got {self.calibration_start}"),
            (self.calibration_every >= 1, f"calibration_every must be ≥ 1, got {self.calibration_every}"),
            (0 <= self.hold_back <= 0.25, f"hold_back must be in [0, 0.25], got {self.hold_back}"),
            (self.hold_back_patience >= 1, f"hold_back_patience must be ≥ 1, got {self.hold_back_patience}"),
        ])
        return self
