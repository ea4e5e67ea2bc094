"""Captures held back from the updates: which ones, their misfit, and the state at its best.

A few captures, spread over bright and dark field, are never used to update
the object or the calibration. Their misfit under the current model says how
well the recovery predicts data it never fitted; when it stays above its best
(:class:`~cca_cli.engines.stopping.StoppingPolicy`), the run is fitting noise
and model errors, so it stops and returns to the state of that best. Both
momentum engines (:mod:`~cca_cli.engines.momentum`, :mod:`~cca_cli.engines.batched`)
use this one class.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from cca_cli.engines import illumination as ill
from cca_cli.engines.calibrator import Calibrator, subset_layout
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.stopping import StoppingPolicy
from cca_cli.optics.forward import ForwardModel
from cca_cli.sampling.grid import BandLayout

__all__ = ["held_back_captures", "HeldBack"]


def held_back_captures(centres_px: np.ndarray, radius_px: float, share: float) -> np.ndarray:
    """Which captures to hold back from the updates: ``share`` of them, spread from the bright field outwards.

    The captures are ranked by the distance of their pupil from DC; the picks are spread evenly over the
    ranks of the dark field and of the bright field in proportion (at least one bright-field capture when
    there are more than two). The capture on the axis is never held back: the recovery starts from it.

    Returns
    -------
    ndarray, int64
        Capture indices, ascending (empty for ``share`` 0).
    """
    k = len(centres_px)
    count = min(int(round(share * k)) if share > 0 else 0, k - 2)
    if count <= 0:
        return np.zeros(0, np.int64)
    distance = np.hypot(centres_px[:, 0], centres_px[:, 1])
    ranked = np.argsort(distance, kind="stable")[1:]     # the axis capture stays
    bright = ranked[distance[ranked] < radius_px]
    dark = ranked[distance[ranked] >= radius_px]
    from_bright = min(len(bright), max(1 if len(bright) > 1 else 0, int(round(count * len(bright) / (k - 1)))))
    picks = [group[np.unique(np.round(np.linspace(0, len(group) - 1, n)).astype(int))]
             for group, n in ((bright, from_bright), (dark, count - from_bright)) if n > 0 and len(group)]
    return np.sort(np.concatenate(picks)).astype(np.int64) if picks else np.zeros(0, np.int64)


class HeldBack:
    """The held-back captures of one run: the split, their misfit and the best state seen.

    Parameters
    ----------
    problem : PhaseRetrievalProblem
    share : float
        Share of the captures held back (``hold_back``); 0 holds none back.
    """

    def __init__(self, problem: PhaseRetrievalProblem, share: float):
        layout = problem.model.layout
        self.problem = problem
        self.captures = held_back_captures(layout.centres_px, layout.pupil_radius_px, share)
        self.trained = np.setdiff1d(np.arange(problem.model.n_images), self.captures)
        energies = problem.capture_energies
        self.trained_norm = problem.energy if not self.captures.size else float(energies[self.trained].sum())
        self._norm = float(energies[self.captures].sum())
        self._workspace = None
        self._best = None

    def __len__(self) -> int:
        return int(self.captures.size)

    def misfit(self, spectrum: np.ndarray, calibrator: Calibrator, layout: BandLayout) -> float:
        """Relative amplitude misfit of the held-back captures under ``spectrum`` (host array) and the calibration.

        ``layout`` lays out every capture (problem order) at its current centre. NaN when none is held back.
        """
        held = self.captures
        if not held.size:
            return float("nan")
        sub = subset_layout(layout, held)
        model = ForwardModel(sub, calibrator.pupils_for(sub, calibrator.pupil_index[held]))
        if self._workspace is None:
            self._workspace = model.workspace(held.size, threads=1)
        weights = None if self.problem.weights is None else self.problem.weights[held]
        statistics = ill.capture_statistics(model, spectrum, calibrator.measured(held), weights,
                                            workspace=self._workspace, scale=calibrator.target_scale(held))
        return float(np.sqrt(statistics.misfit.sum() / max(self._norm, 1e-30)))

    def keep_best(self, stopping: StoppingPolicy, spectrum: Callable[[], np.ndarray],
                  calibrator: Calibrator) -> np.ndarray | None:
        """Remember the state at a new best misfit; at the end of a run past its best, return that spectrum.

        Parameters
        ----------
        stopping : StoppingPolicy
            The run's policy, after it recorded this pass.
        spectrum : callable
            Returns the current spectrum on the host (called only to take a copy).
        calibrator : Calibrator
            Restored to the best state's calibration when the run returns to it.

        Returns
        -------
        ndarray or None
            The spectrum to continue from (the calibrator already restored), or None to keep the current one.
        """
        if not self.captures.size:
            return None
        if stopping.improved:
            self._best = (np.array(spectrum(), copy=True),
                          {k: np.copy(v) for k, v in calibrator.state().items()})
        if stopping.done() and self._best is not None and stopping.held_back_above_best():
            best, calibration = self._best
            calibrator.restore(calibration)
            return best
        return None
