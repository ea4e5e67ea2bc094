"""A reconstruct section and a captures file, handed to the library (:mod:`cca_cli.library.recovery`).

The library takes arrays and options and raises ``ValueError``; here the
section's keys become its arguments, and its errors name the file or the
config key they concern.
"""

from __future__ import annotations

from pathlib import Path

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.options import EngineOptions
from cca_cli.engines.registry import resolve
from cca_cli.errors import CcaError, ConfigError, InputError
from cca_cli.io.measurements import INTENSITY
from cca_cli.io.recon import read_spectrum
from cca_cli.library import recovery as library
from cca_cli.library.data import CaptureSet, Reconstruction
from cca_cli.optics.backend import DeviceUnavailable, resolve_device
from cca_cli.progress import ProgressFn, silent
from cca_cli.sampling.region import RegionEmbedding

__all__ = ["engine_options", "recipe_of", "check_device", "reconstruct_captures", "embed_region", "without_dead_captures"]


def engine_options(section: ReconstructSection, kind: str = "simulation", *, frame_scale: str = "shared",
                   stray_light: bool = False, **overrides) -> tuple[str, EngineOptions]:
    """The engine the section's ``engine`` stands for on ``kind`` of data, and its options object.

    ``frame_scale`` is the captures' (:attr:`~cca_cli.library.data.CaptureSet.frame_scale`), ``stray_light``
    whether their dark-field images never fall near zero (:func:`cca_cli.library.recovery.holds_stray_light`);
    ``overrides`` go on top of what the section gives. One line naming
    ``reconstruct.options`` when the options do not fit the engine
    (:func:`cca_cli.engines.registry.resolve`).
    """
    try:
        return resolve(section.engine, kind, {**section.given(), **overrides}, frame_scale=frame_scale,
                       stray_light=stray_light)
    except ValueError as exc:
        raise ConfigError(f"reconstruct.options: {exc}") from None


def recipe_of(name: str, options: EngineOptions) -> dict:
    """What a result depends on of an engine and its options: the name and every option but ``threads``
    (results are reproducible per thread count, and the count follows the machine)."""
    return {"engine": name, "options": options.model_dump(mode="json", exclude={"threads"})}


def check_device(section: ReconstructSection) -> None:
    """Refuse ``reconstruct.device: cuda`` where CuPy or a GPU is missing, before anything is read or run.

    Raises
    ------
    ConfigError
        One line naming ``reconstruct.device``, what is missing and the fix.
    """
    if section.device != "cuda":
        return
    try:
        resolve_device(section.device)
    except DeviceUnavailable as exc:
        raise ConfigError(f"reconstruct.device: {exc}") from None


def reconstruct_captures(captures: CaptureSet, section: ReconstructSection, *, source: Path,
                         progress: ProgressFn = silent, checkpoint=None) -> Reconstruction:
    """Recover ``captures`` (read from ``source``) as ``section`` says (:func:`cca_cli.library.recovery.reconstruct`).

    ``section.init`` names a recon.h5 whose spectrum the engine starts from; with
    ``checkpoint`` the run continues from a matching checkpoint and writes new ones. ``section.device``
    says where the engine runs; a device that cannot run it is a ConfigError naming ``reconstruct.device``.
    """
    name, options = engine_options(section, captures.kind, frame_scale=captures.frame_scale,
                                   stray_light=library.holds_stray_light(captures))
    init = init_pixel = None
    if section.init is not None:
        init, attrs = read_spectrum(Path(section.init))
        init_pixel = attrs.get("pixel_pitch_object_m")
    padding = section.padding
    try:
        return library.reconstruct(captures, engine=name, options=options, padding=padding.mode,
                                   guard_px=padding.guard_px, apodize_px=padding.apodize_px, init=init,
                                   init_pixel_m=init_pixel, progress=progress, checkpoint=checkpoint,
                                   name=INTENSITY, source=source, device=section.device)
    except library.DeviceUnavailable as exc:
        raise ConfigError(f"reconstruct.device: {exc}") from None
    except library.DivergedError as exc:
        raise CcaError(f"reconstruct: the recovery diverged (NaN or Inf after {exc.iterations} iterations), so "
                       "nothing was written; raise reconstruct.tau or choose other reconstruct.options") from None
    except ValueError as exc:
        where = f"{section.init}: reconstruct.init: " if str(exc).startswith("init:") else f"{source}: "
        message = str(exc).removeprefix("init: ") if str(exc).startswith("init:") else str(exc)
        message = message.removeprefix(f"{source}: ")   # a message naming the file already (dead captures)
        raise InputError(f"{where}{message}") from None


def without_dead_captures(captures: CaptureSet, *, source: Path) -> CaptureSet:
    """:func:`cca_cli.library.recovery.without_dead_captures` with one-line errors naming ``source``."""
    return library.without_dead_captures(captures, name=INTENSITY, source=source, error=InputError)


def embed_region(captures: CaptureSet, section: ReconstructSection, *,
                 source: Path) -> tuple[CaptureSet, RegionEmbedding | None]:
    """:func:`cca_cli.library.recovery.embed_region` with the section's padding and errors naming ``source``."""
    padding = section.padding
    try:
        return library.embed_region(captures, padding=padding.mode, guard_px=padding.guard_px,
                                    apodize_px=padding.apodize_px)
    except ValueError as exc:
        raise InputError(f"{source}: {INTENSITY}: {exc}") from None
