"""Stage `reconstruct`: captures → recovered high-resolution object (recon.h5)."""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path


from cca_cli.config.model import ReconstructSection
from cca_cli.engines.base import History
from cca_cli.errors import CcaError, ConfigError, InputError
from cca_cli.io.captures import read_captures, read_frame_scale
from cca_cli.io.checkpoint import (checkpoint_damage, checkpoint_path, read_checkpoint, remove_checkpoint,
                                   write_checkpoint)
from cca_cli.io.geometry import read_geometry
from cca_cli.io.h5 import Provenance, check_output, file_sha256, open_input, require
from cca_cli.io.measurements import INTENSITY
from cca_cli.io.multiplex import is_multiplexed_file
from cca_cli.io.outputs import is_cca_hdf5
from cca_cli.io.recon import write_recon
from cca_cli.library.data import Reconstruction, data_kind
from cca_cli.stages.progress import ProgressFn, silent
from cca_cli.version import __version__
from cca_cli.workflows.recovery import check_device, engine_options, reconstruct_captures, recipe_of

__all__ = ["SECTIONS", "Checkpointing", "checkpoint_fingerprint", "run", "run_tiled"]

SECTIONS = ("reconstruct",)
#: Share of the run time checkpoints may take: one is skipped until the time since the last is this many writes.
_CHECKPOINT_SPACING = 20
_log = logging.getLogger("cca")


@dataclass
class Checkpointing:
    """Where and how often a reconstruction saves its state, and what inputs and options it belongs to.

    A checkpoint is written after every ``every`` iterations, but never so often that writing takes more
    than 1/20 of the run time; one whose ``fingerprint`` differs (other captures, options, engine or
    starting spectrum) is ignored with a note and replaced, and so is a damaged one (arrays of NaN or of
    other shapes). A file at ``path`` that cca did not write is neither read nor replaced.
    """

    path: Path
    fingerprint: str
    every: int
    provenance: Provenance
    _usable: bool = field(default=True, repr=False)
    _last: float = field(default=0.0, repr=False)
    _cost: float = field(default=0.0, repr=False)
    _since: int = field(default=0, repr=False)

    def load(self, expected: dict | None = None):
        """The matching checkpoint's state and history, or None (with a note when one is ignored).

        With ``expected`` (the state of the engine about to run) a checkpoint whose arrays are not
        finite or have other shapes is ignored too, and replaced (:func:`~cca_cli.io.checkpoint.checkpoint_damage`).
        """
        if not (self.path.exists() or self.path.is_symlink()):
            return None
        if not self.path.is_file() or not is_cca_hdf5(self.path):
            _log.warning("%s is not a checkpoint cca wrote: it is left alone, and this run writes no checkpoints",
                         self.path)
            self._usable = False
            return None
        checkpoint = read_checkpoint(self.path)
        if checkpoint is None or checkpoint.fingerprint != self.fingerprint:
            _log.warning("%s belongs to other captures or reconstruct options: starting afresh (it will be "
                         "replaced)", self.path)
            return None
        damage = None if expected is None else checkpoint_damage(checkpoint, expected)
        if damage is not None:
            _log.warning("%s is damaged (%s): starting afresh (it will be replaced)", self.path, damage)
            return None
        return checkpoint

    def start(self) -> None:
        """Start counting iterations and time towards the next checkpoint."""
        self._last, self._since = time.perf_counter(), 0

    def after_iteration(self, engine, history: History) -> None:
        """Write a checkpoint when one is due."""
        self._since += 1
        if not self._usable or self.every <= 0 or self._since < self.every or engine.done():
            return
        now = time.perf_counter()
        if now - self._last < _CHECKPOINT_SPACING * self._cost:
            return
        columns = {name: history.array(name) for name in history.keys()}
        write_checkpoint(self.path, self.provenance, self.fingerprint, engine.state(), columns)
        self._last = time.perf_counter()
        self._cost, self._since = self._last - now, 0

    def remove(self) -> None:
        """Remove the checkpoint (once the output is written)."""
        if self._usable:
            remove_checkpoint(self.path)


def checkpoint_fingerprint(section: ReconstructSection, provenance: Provenance, captures_path: Path) -> str:
    """SHA-256 of what a reconstruction's result depends on: the captures' bytes, the section (without
    ``checkpoint_every`` and ``device``), the engine and options it resolves to (``engine_recipe`` in the
    provenance: a preset that changed between cca versions does not resume an older run), the starting
    spectrum's file (size and time) and the cca version."""
    try:
        inputs = [item["sha256"] for item in json.loads(provenance.get("inputs", "[]"))]
    except (ValueError, KeyError, TypeError):
        inputs = []
    init = None
    if section.init is not None and Path(section.init).is_file():
        stat = Path(section.init).stat()
        init = [str(section.init), stat.st_size, stat.st_mtime_ns]
    data = {"inputs": inputs or [file_sha256(captures_path)], "init": init, "version": __version__,
            "recipe": provenance.get("engine_recipe", ""),
            "section": section.model_dump(mode="json", exclude={"checkpoint_every", *section.NOT_RECIPE})}
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def captures_kind_and_scale(captures_path: Path) -> tuple[str, str]:
    """A captures file's :attr:`~cca_cli.library.data.CaptureSet.kind` (from its geometry) and ``frame_scale``."""
    with open_input(captures_path) as handle:
        kind = data_kind("truth" in handle and len(handle["truth"]) > 0, read_geometry(handle).kind)
        return kind, read_frame_scale(require(handle, INTENSITY).attrs, captures_path)


def captures_stray_light(captures_path: Path, kind: str) -> bool:
    """Whether an LED array's captures file holds light under every dark-field image, which turns the background
    fit on (:func:`cca_cli.library.recovery.holds_stray_light`; the images are read)."""
    if kind != "led_array":
        return False
    from cca_cli.library.recovery import holds_stray_light

    return holds_stray_light(read_captures(captures_path))


def engine_recipe(captures_path: Path, section: ReconstructSection) -> str:
    """SHA-256 of the engine and options ``section`` resolves to on these captures, cca's defaults included.

    The stage records it (provenance ``engine_recipe``), so that a recon.h5 made before cca's engine
    defaults changed counts as outdated although its config and captures are the same. It resolves as
    the run does: multiplexed captures with the simulation preset, tiles with their own
    (:func:`~cca_cli.workflows.tiled.tile_engine`), other captures by their kind and what their images say
    (a frame scale, light under the dark field: :func:`captures_stray_light`). Threads are left out
    (results are reproducible per thread count, and the count follows the machine). Empty when the
    captures cannot be read or the section's options do not resolve (the run itself then says why).
    """
    try:
        if is_multiplexed_file(captures_path):
            data = recipe_of(*engine_options(section, "simulation"))
        elif section.tiles is not None:
            from cca_cli.workflows.tiled import tile_recipe

            data = tile_recipe(section, captures_path)
        else:
            kind, frame_scale = captures_kind_and_scale(captures_path)
            data = recipe_of(*engine_options(section, kind, frame_scale=frame_scale,
                                             stray_light=captures_stray_light(captures_path, kind)))
    except (CcaError, OSError, KeyError, ValueError):
        return ""
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def run(captures_path: Path, section: ReconstructSection, output: Path, *, provenance: Provenance,
        force: bool = False, progress: ProgressFn = silent) -> Reconstruction:
    """Read captures, reconstruct, write ``output``.

    The reconstruction saves its state to ``<output>.checkpoint`` every ``section.checkpoint_every``
    iterations and, run again with the same captures and section, continues from it; the checkpoint is
    removed once ``output`` is written. With ``section.tiles`` the frame is recovered in tiles on Dask
    (:func:`run_tiled`).
    """
    check_output(output, force=force)
    check_device(section)
    provenance.setdefault("engine_recipe", engine_recipe(captures_path, section))
    multiplexed = is_multiplexed_file(captures_path)
    if section.device == "cuda" and multiplexed:
        raise ConfigError("reconstruct.device: cuda runs reconstructions of plain captures (whole frames or "
                          "tiles); multiplexed reconstructions run on the CPU: use device cpu or auto")
    if section.tiles is not None:
        if multiplexed:
            raise InputError(f"{captures_path}: multiplexed captures are recovered whole; leave out reconstruct.tiles")
        return run_tiled(captures_path, section, output, provenance=provenance, force=force, progress=progress)
    if multiplexed:
        from cca_cli.workflows import multiplex

        return multiplex.run_reconstruct(captures_path, section, output, provenance=provenance, force=force,
                                         progress=progress)
    checkpoint = Checkpointing(checkpoint_path(output), checkpoint_fingerprint(section, provenance, captures_path),
                               section.checkpoint_every, provenance)
    result = reconstruct_captures(read_captures(captures_path), section, source=captures_path, progress=progress,
                                  checkpoint=checkpoint)
    from cca_cli.io.capture_info import capture_extras

    write_recon(output, result, provenance, force=force, extra=capture_extras(captures_path))
    checkpoint.remove()
    return result


def run_tiled(captures_path: Path, section: ReconstructSection, output: Path, *, provenance: Provenance,
              force: bool = False, progress: ProgressFn = silent, client=None):
    """Recover ``captures_path`` in tiles on Dask and write the blended result to ``output``.

    Finished tiles are kept in ``<output>.tiles/`` until ``output`` is written, so a run that was
    stopped and is started again with the same captures and section recovers only the tiles that
    were not finished (:mod:`cca_cli.workflows.tiled`).

    Returns
    -------
    TiledRecovery
    """
    from cca_cli.io.tiles import remove_tile_folder
    from cca_cli.workflows.tiled import reconstruct_tiled, run_fingerprint

    try:
        inputs = [item["sha256"] for item in json.loads(provenance.get("inputs", "[]"))]
    except (ValueError, KeyError, TypeError):
        inputs = []
    fingerprint = run_fingerprint(section, inputs, captures_path)
    tiled = reconstruct_tiled(captures_path, section, output, run_fingerprint=fingerprint, provenance=provenance,
                              client=client, progress=progress)
    from cca_cli.io.capture_info import capture_extras

    result, tiles = tiled.as_reconstruction()
    write_recon(output, result, provenance, force=force, extra=capture_extras(captures_path), tiles=tiles)
    remove_tile_folder(output)
    return tiled
