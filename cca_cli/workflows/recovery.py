"""Choose a phase-retrieval engine from the reconstruct section and run it to a :class:`Recovery`."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.base import History, IterationRecord, run_engine
from cca_cli.engines.fit import FitReport
from cca_cli.engines.momentum import Calibration
from cca_cli.engines.presets import preset
from cca_cli.engines.registry import get_engine
from cca_cli.errors import CcaError, ConfigError
from cca_cli.progress import ProgressEvent, ProgressFn, silent
from cca_cli.sampling.grid import BandLayout

__all__ = ["Recovery", "stop_reason", "resolve_engine", "engine_options", "drive_engine"]


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
    (:func:`cca_cli.engines.presets.preset`); what the section sets explicitly
    (``tau``, ``iterations``, ``tol``, ``options``) overrides the preset.
    """
    section_values = {"tau": section.tau, "max_iterations": section.iterations, "tol": section.tol}
    if section.engine != "auto":
        return section.engine, {**section_values, **section.options}
    name, options = preset(kind)
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
