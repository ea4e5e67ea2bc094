"""When an iterative engine stops, and why.

Every engine counts its iterations against a cap and stops early when an
iteration changes the spectrum by less than ``tol``. Engines that report a
data misfit may also stop on a *plateau*: the misfit fell by less than
``plateau`` (relative) over the last ``plateau_window`` iterations. An engine
that can enlarge its batches first grows them at a plateau, judged over the
last ``growth_window`` iterations (a shorter look back: growing early costs
little, the next batch size goes on from where the last left off); only a
plateau it can no longer grow out of, judged over ``plateau_window``, ends the
run.

An engine that holds some captures back from its updates reports their misfit
too: it measures how well the recovery predicts data it never fitted. When
that misfit has stayed more than :data:`HELD_BACK_RISE` above its best for
``held_back_patience`` iterations, the run is fitting the noise and the
model's errors rather than the object, and it stops (``held_back``); the
engine then returns to its best state. Small ups and downs (a batch that grew,
a pupil step undone) end nothing.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["HELD_BACK_RISE", "StoppingPolicy"]

#: How far above its best the held-back misfit must stay (relative) before it counts as rising.
HELD_BACK_RISE = 0.01


class StoppingPolicy:
    """The iteration cap, the change tolerance and the misfit plateau of one run.

    Parameters
    ----------
    max_iterations : int
    tol : float
        Stop when an iteration's relative spectrum change falls below it.
    plateau : float
        Relative misfit drop over ``plateau_window`` iterations below which the
        misfit counts as flat (0: never).
    plateau_window : int
    growth_window : int, optional
        Iterations the plateau test looks back while the engine can still grow its
        batches (None: ``plateau_window``).
    can_grow : callable, optional
        Whether the engine can still enlarge its batches; while it can, a flat
        misfit asks for growth (:meth:`record` returns True) instead of ending the run.
    held_back_patience : int
        Iterations in a row with the held-back misfit more than :data:`HELD_BACK_RISE` above its
        best that end the run (0: the held-back misfit never ends it).
    """

    def __init__(self, *, max_iterations: int, tol: float, plateau: float = 0.0, plateau_window: int = 1,
                 growth_window: int | None = None, can_grow: Callable[[], bool] = lambda: False,
                 held_back_patience: int = 0):
        self.max_iterations = int(max_iterations)
        self.tol = float(tol)
        self.plateau = float(plateau)
        self.window = int(plateau_window)
        self.growth_window = self.window if growth_window is None else int(growth_window)
        self._can_grow = can_grow
        self.iteration = 0
        self.change = np.inf
        self.misfits: list[float] = []
        self.plateau_from = 0   # first misfit of the current batch size: the plateau test looks no further back
        self.patience = int(held_back_patience)
        self.best_held_back = np.inf
        self.best_iteration = 0
        self.improved = False
        self.rising_since: int | None = None   # first iteration of the current run above the best by the margin

    def record(self, misfit: float, change: float, held_back: float = np.nan) -> bool:
        """Count one iteration; True when the misfit is flat and the engine should grow its batches now.

        ``held_back`` is the misfit of the captures held back from the updates (NaN: none are);
        :attr:`improved` then says whether it reached a new best.
        """
        self.misfits.append(float(misfit))
        self.change = float(change)
        self.iteration += 1
        self.improved = bool(held_back < self.best_held_back)
        if self.improved:
            self.best_held_back, self.best_iteration = float(held_back), self.iteration
        if held_back > (1 + HELD_BACK_RISE) * self.best_held_back:
            self.rising_since = self.iteration if self.rising_since is None else self.rising_since
        else:
            self.rising_since = None
        return self._can_grow() and self.flat(self.growth_window)

    def held_back_rose(self) -> bool:
        """Whether the held-back misfit has stayed clearly above its best for ``held_back_patience`` iterations."""
        return self.patience > 0 and self.rising_since is not None and \
            self.iteration - self.rising_since + 1 >= self.patience

    def held_back_above_best(self) -> bool:
        """Whether the held-back misfit now is clearly above its best (the engine then returns to the best state)."""
        return self.rising_since is not None

    def grew(self) -> None:
        """The engine enlarged its batches: the plateau test starts afresh from the next iteration."""
        self.plateau_from = len(self.misfits)

    def flat(self, window: int | None = None) -> bool:
        """Whether the misfit fell by less than ``plateau`` over the last ``window`` iterations
        (default ``plateau_window``) of the current batch size."""
        window = self.window if window is None else window
        if self.plateau <= 0 or len(self.misfits) - self.plateau_from <= window:
            return False
        then, now = self.misfits[-1 - window], self.misfits[-1]
        return (then - now) < self.plateau * now

    def on_plateau(self) -> bool:
        """Whether the run is on its plateau: the misfit is flat and the batches can grow no more."""
        return not self._can_grow() and self.flat()

    def done(self) -> bool:
        """Whether the run ends now: the cap, a change below ``tol``, the plateau, or a stale held-back misfit."""
        return (self.iteration >= self.max_iterations or self.change < self.tol or self.on_plateau()
                or self.held_back_rose())

    def reason(self) -> str:
        """Why the run ended (or would end now): ``tol``, ``plateau``, ``held_back`` or ``cap``."""
        if self.change < self.tol:
            return "tol"
        if self.held_back_rose():
            return "held_back"
        if self.on_plateau():
            return "plateau"
        return "cap" if self.iteration >= self.max_iterations else "tol"

    def state(self) -> dict:
        """The counters a restored run continues from."""
        return {"iteration": self.iteration, "change": self.change, "misfits": np.asarray(self.misfits, np.float64),
                "plateau_from": self.plateau_from, "best_held_back": self.best_held_back,
                "best_iteration": self.best_iteration,
                "rising_since": -1 if self.rising_since is None else self.rising_since}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state`."""
        self.iteration = int(state["iteration"])
        self.change = float(state["change"])
        self.misfits = [float(v) for v in state.get("misfits", ())]
        self.plateau_from = int(state.get("plateau_from", 0))
        self.best_held_back = float(state.get("best_held_back", np.inf))
        self.best_iteration = int(state.get("best_iteration", 0))
        rising = int(state.get("rising_since", -1))
        self.rising_since = None if rising < 0 else rising
