"""The engine contract and the driver loop that watches it.

An engine exposes one iteration (:meth:`IterativeEngine.update`) and a stopping
test (:meth:`IterativeEngine.done`, with :meth:`~IterativeEngine.stop_reason`).
Optional features are declared by the class an engine derives from, never
looked up by attribute: a :class:`CalibratingEngine` also recovers pupils,
positions and brightness. :func:`run_engine` owns the loop, timing and
history, and reports each iteration through an ``on_iteration`` callback;
engines never print.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np

from cca_cli.engines.stopping import StoppingPolicy

if TYPE_CHECKING:  # the engines' numeric code stays unimported until an engine runs
    from cca_cli.engines.calibrator import Calibration

__all__ = ["IterationRecord", "History", "IterativeEngine", "CalibratingEngine", "run_engine"]


@dataclass(frozen=True)
class IterationRecord:
    """What one iteration reports.

    Attributes
    ----------
    iteration : int
        1-based iteration number.
    residual : float
        Relative data misfit ``‖w (|ψ| − √I)‖ / ‖w √I‖`` before the update.
    change : float
        Relative change of the spectrum ``‖S_new − S‖ / ‖S‖``.
    seconds : float
        Wall time since the run started.
    held_back : float
        Relative misfit of the captures held back from the updates (NaN when none are).
    """

    iteration: int
    residual: float
    change: float
    seconds: float
    held_back: float = float("nan")

    def __getitem__(self, name: str) -> float:
        """``record["residual"]`` as ``record.residual`` (a history's columns are read the same way)."""
        if name not in self.__dataclass_fields__:
            raise KeyError(f"{name!r}: a record holds {', '.join(self.__dataclass_fields__)}")
        return getattr(self, name)


@dataclass
class History:
    """Per-iteration records of one run (kept apart from the engine's options).

    Reads like a mapping of columns too: ``history["residual"]`` is :meth:`array`.
    """

    records: list[IterationRecord] = field(default_factory=list)

    #: The columns every history holds, besides the iteration number.
    COLUMNS = ("residual", "change", "seconds")
    #: Columns a run may add: the misfit of the captures held back from the updates.
    OPTIONAL = ("held_back",)

    @classmethod
    def from_columns(cls, columns) -> History:
        """A history from arrays of equal length by column name (a file's /history; optional columns may lack)."""
        values = [np.asarray(columns[name], np.float64).ravel() for name in cls.COLUMNS]
        n = len(values[0])
        values += [np.asarray(columns[name], np.float64).ravel() if name in columns else np.full(n, np.nan)
                   for name in cls.OPTIONAL]
        return cls([IterationRecord(i + 1, *(float(v) for v in row)) for i, row in enumerate(zip(*values))])

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self.COLUMNS + self.OPTIONAL:
            raise KeyError(f"{name!r}: a history holds {', '.join(self.COLUMNS + self.OPTIONAL)}")
        return self.array(name)

    def keys(self) -> tuple[str, ...]:
        """The column names (``held_back`` only when the run held captures back)."""
        held = self.records and np.isfinite(self.array("held_back")).any()
        return self.COLUMNS + (self.OPTIONAL if held else ())

    @property
    def iterations(self) -> int:
        """Number of iterations run."""
        return len(self.records)

    def array(self, name: str) -> np.ndarray:
        """One column of the history (``residual``, ``change`` or ``seconds``) as float64."""
        return np.array([getattr(r, name) for r in self.records], dtype=np.float64)


class IterativeEngine(ABC):
    """One phase-retrieval algorithm's state and iteration.

    Subclasses set ``stopping`` (a :class:`~cca_cli.engines.stopping.StoppingPolicy`)
    and record every iteration in it; :meth:`done` and :meth:`stop_reason` read it.
    """

    #: Name used in configs and on the command line.
    name: str = ""
    stopping: StoppingPolicy
    #: Relative misfit of the captures held back from the updates after the last iteration (NaN: none held back).
    held_back_residual: float = float("nan")
    #: Indices (problem order) of the captures the engine holds back from its updates.
    held_back: np.ndarray = np.zeros(0, np.int64)

    @abstractmethod
    def update(self) -> tuple[float, float]:
        """Run one iteration; return ``(residual, change)``."""

    def done(self) -> bool:
        """Whether the stopping rule is met."""
        return self.stopping.done()

    #: Set by :func:`run_engine` when its ``on_iteration`` asked the run to end.
    stopped_by_caller = False

    def stop_reason(self) -> str:
        """Why the run ended: ``tol``, ``plateau`` or ``cap`` (see :class:`~cca_cli.engines.stopping.StoppingPolicy`),
        or ``callback`` (the caller's ``on_iteration`` returned False)."""
        return "callback" if self.stopped_by_caller else self.stopping.reason()

    @abstractmethod
    def spectrum(self) -> np.ndarray:
        """Current estimate of the centred high-resolution spectrum (complex64, M x M)."""

    def close(self) -> None:
        """Release worker threads or buffers (optional)."""

    def state(self) -> dict:
        """What the engine needs to continue where it is: arrays (``spectrum`` included) and scalars by name.

        :meth:`restore` on an engine built for the same problem and options takes it back.
        """
        raise NotImplementedError(f"engine {self.name!r} cannot be checkpointed")

    def restore(self, state: dict) -> None:
        """Continue from a :meth:`state` taken earlier (same problem and options)."""
        raise NotImplementedError(f"engine {self.name!r} cannot be checkpointed")


class CalibratingEngine(IterativeEngine):
    """An engine that also recovers the model: pupils, capture positions, brightness."""

    @abstractmethod
    def calibration(self) -> Calibration:
        """What the engine found so far, in the problem's capture order."""


def run_engine(engine: IterativeEngine, *, on_iteration: Callable[[IterationRecord], None] | None = None,
               history: History | None = None) -> tuple[np.ndarray, History]:
    """Iterate ``engine`` until it is done.

    Parameters
    ----------
    engine : IterativeEngine
    on_iteration : callable, optional
        Called with an :class:`IterationRecord` after every iteration (progress bars, logging); when it
        returns False the run ends there, and the engine's :meth:`~IterativeEngine.stop_reason` is
        ``callback``.
    history : History, optional
        The records of the iterations already run (an engine restored from a
        checkpoint): numbering and wall time continue from them, and new records
        are appended to it.

    Returns
    -------
    spectrum : ndarray, complex64, (M, M)
    history : History
    """
    history = History() if history is None else history
    start = time.perf_counter() - (history.records[-1].seconds if history.records else 0.0)
    try:
        while not engine.done():
            residual, change = engine.update()
            record = IterationRecord(history.iterations + 1, float(residual), float(change),
                                     time.perf_counter() - start, float(engine.held_back_residual))
            history.records.append(record)
            if on_iteration is not None and on_iteration(record) is False:
                engine.stopped_by_caller = True
                break
    finally:
        engine.close()
    return engine.spectrum(), history
