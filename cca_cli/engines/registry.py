"""The one list of engines: name → options model, where the engine lives, what it can do.

Everything that names an engine goes through here: the config (checked when it
is read), the command line's help, the Python API, tiles and multiplexed runs.
An engine's code is imported only when it runs, so reading a config or the
help never loads numba or FFTW.

:func:`resolve` turns an engine name (``auto`` included), the kind of data and
the options a user gave into the engine's name and its options object.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Mapping

from pydantic import ValidationError

from cca_cli.engines import presets
from cca_cli.engines.options import ITERATIONS_ALIAS, AltMinOptions, EngineOptions, MomentumOptions
from cca_cli.values import validation_message

__all__ = ["EngineSpec", "ENGINES", "get_engine", "engine_names", "engine_help", "resolve"]


@dataclass(frozen=True)
class EngineSpec:
    """A registered engine.

    Attributes
    ----------
    name : str
        The name configs and the command line use.
    summary : str
        A few words for help texts.
    options : type
        Its options model (:mod:`cca_cli.engines.options`).
    engine : str
        ``module:Class`` of the engine (an :class:`~cca_cli.engines.base.IterativeEngine`).
    multiplexed : str or None
        ``module:Class`` of its form for multiplexed captures, if it has one.
    calibrates : bool
        Whether it can recover pupils, positions and brightness (a
        :class:`~cca_cli.engines.base.CalibratingEngine`).
    batched : str or None
        ``module:Class`` of its batched form, written against an array module (numpy or CuPy), which
        ``device: cuda`` runs (:mod:`cca_cli.engines.batched`); None: the engine runs on the CPU only.
    """

    name: str
    summary: str
    options: type[EngineOptions]
    engine: str
    multiplexed: str | None = None
    calibrates: bool = False
    batched: str | None = None

    def engine_class(self) -> type:
        """The engine class (imported now)."""
        return _load(self.engine)

    def multiplexed_class(self) -> type | None:
        """The engine's form for multiplexed captures (imported now), or None."""
        return None if self.multiplexed is None else _load(self.multiplexed)

    def batched_class(self) -> type | None:
        """The engine's batched form for GPUs (imported now), or None."""
        return None if self.batched is None else _load(self.batched)

    def option_names(self) -> list[str]:
        """Names of the options the engine accepts (``max_iterations`` included)."""
        return list(self.options.model_fields)


def _load(path: str) -> type:
    module, name = path.split(":")
    return getattr(importlib.import_module(module), name)


ENGINES: dict[str, EngineSpec] = {
    "altmin": EngineSpec("altmin", "the paper's alternating minimization", AltMinOptions,
                         "cca_cli.engines.altmin:AlternatingMinimization",
                         multiplexed="cca_cli.engines.multiplex:MultiplexedAlternatingMinimization",
                         batched="cca_cli.engines.batched:BatchedAlternatingMinimization"),
    "momentum": EngineSpec("momentum", "sequential rPIE with mPIE momentum and calibration", MomentumOptions,
                           "cca_cli.engines.momentum:SequentialMomentum", calibrates=True,
                           batched="cca_cli.engines.batched:BatchedMomentum"),
}


def engine_names() -> list[str]:
    """Registered engine names, sorted."""
    return sorted(ENGINES)


def engine_help() -> str:
    """One sentence naming ``auto`` and every engine, for help texts."""
    named = [f"{name} ({ENGINES[name].summary})" for name in engine_names()]
    return f"auto (chosen by the data: {presets.summary()}), " + ", ".join(named[:-1]) + f" or {named[-1]}"


def get_engine(name: str) -> EngineSpec:
    """Look up an engine by name.

    Raises
    ------
    KeyError
        With a message listing the valid names.
    """
    try:
        return ENGINES[name]
    except KeyError:
        raise KeyError(f"{name!r} is not an engine; choose auto or one of {', '.join(engine_names())}") from None


def _without_alias(given: Mapping) -> dict:
    """``given`` with ``iterations`` read as ``max_iterations`` (the one place the two names meet)."""
    out = dict(given)
    alias, name = ITERATIONS_ALIAS
    if alias in out:
        if name in out:
            raise ValueError(f"give {alias} or {name}, not both")
        out[name] = out.pop(alias)
    return out


def _auto_for_checking(given: dict) -> str:
    """The engine ``auto`` options are checked with before the data is known: the first that takes every key."""
    for name in ("momentum", *engine_names()):
        if set(given) <= set(ENGINES[name].option_names()):
            return name
    accepted = sorted(set().union(*(ENGINES[name].option_names() for name in ENGINES)))
    unknown = sorted(set(given) - set(accepted))
    raise ValueError(f"unknown option(s) {', '.join(unknown)} for engine auto; accepted: {', '.join(accepted)}")


def resolve(engine: str, kind: str | None, given: Mapping | None = None, *,
            frame_scale: str = "shared", stray_light: bool = False) -> tuple[str, EngineOptions]:
    """The engine an engine name stands for on a kind of data, and its options.

    ``engine: auto`` takes the preset of the kind (:mod:`cca_cli.engines.presets`),
    and so does the preset's engine named outright on recorded captures; what
    the user gave goes on top.

    Parameters
    ----------
    engine : str
        ``auto`` or a registered name.
    kind : {"simulation", "led_array", "camera_scan"} or None
        The kind of data; None checks the options before the data is known
        (``auto`` then checks them with the first engine that takes them all).
    given : mapping, optional
        The options the user set, by name: ``tau``, ``iterations`` (or
        ``max_iterations``), ``tol`` and the engine's own. Values are read as a
        config reads them (``"1e-3"`` → 0.001, ``2.0`` → 2).
    frame_scale : {"shared", "per_frame"}
        How the captures' images were scaled (:attr:`~cca_cli.library.data.CaptureSet.frame_scale`):
        ``per_frame`` starts an engine that can fit each capture's brightness with ``brightness: true``.
    stray_light : bool
        Whether the captures' dark-field images never fall near zero
        (:func:`~cca_cli.library.stray_light.holds_stray_light`): starts an engine that can fit that
        light with ``background: true``.

    Returns
    -------
    name : str
    options : EngineOptions
        The engine's options model.

    Raises
    ------
    ValueError
        One line: an unknown engine or option (the accepted ones listed), or a
        value the option does not take.
    """
    given = _without_alias(given or {})
    if engine != "auto" and engine not in ENGINES:
        raise ValueError(f"{engine!r} is not an engine; choose auto or one of {', '.join(engine_names())}")
    if kind is None:
        name, start = (_auto_for_checking(given) if engine == "auto" else engine), {}
    else:
        name, start = presets.starting_options(engine, kind)
    spec = ENGINES[name]
    if frame_scale not in presets.FRAME_SCALES:
        raise ValueError(f"frame_scale must be 'shared' or 'per_frame', got {frame_scale!r}")
    if frame_scale == "per_frame" and kind is not None and "brightness" in spec.option_names():
        # images scaled each on its own: their brightness is unknown, and nothing says it is near 1
        start = {**start, "brightness": True, "brightness_prior": 0.0}
    if stray_light and kind is not None and "background" in spec.option_names():
        # light the object did not scatter under every dark-field image: fitted, not taken for the object's
        start = {**start, "background": True}
    unknown = sorted(set(given) - set(spec.option_names()))
    if unknown:
        alias, full = ITERATIONS_ALIAS
        accepted = [alias if option == full else option for option in spec.option_names()]
        raise ValueError(f"unknown option(s) {', '.join(unknown)} for engine {name}; accepted: {', '.join(accepted)}")
    try:
        return name, spec.options.model_validate({**start, **given})
    except ValidationError as exc:
        raise ValueError(validation_message(exc)) from None
