"""Stage `reconstruct`: captures → recovered high-resolution object (recon.h5)."""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cca_cli.version import __version__
from cca_cli.config.model import ReconstructSection
from cca_cli.engines.base import History
from cca_cli.engines.fit import FitReport
from cca_cli.engines.calibrator import Calibration
from cca_cli.errors import InputError
from cca_cli.io.captures import Captures, read_measurements
from cca_cli.io.checkpoint import (checkpoint_damage, checkpoint_path, read_checkpoint, remove_checkpoint,
                                   write_checkpoint)
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, file_sha256, open_input, write_dataset
from cca_cli.io.outputs import is_cca_hdf5
from cca_cli.optics import fft
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.region import RegionEmbedding
from cca_cli.stages.progress import ProgressFn, silent
from cca_cli.workflows.recovery import (Recovery, build_model, calibrated_pupils, data_kind, embed_region,
                                        engine_options, initial_spectrum_from, problem_calibration, recover,
                                        without_dead_captures)

# recover, build_model, embed_region … live in cca_cli.workflows.recovery; they are re-exported here.
__all__ = ["SECTIONS", "Captures", "Recovery", "Checkpointing", "read_captures", "read_measurements", "build_model",
           "reconstruct", "recover", "embed_region", "data_kind", "problem_calibration", "initial_spectrum_from",
           "engine_options", "write_recon", "calibrated_pupils", "run"]

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
        columns = {name: history.array(name) for name in ("residual", "change", "seconds")}
        write_checkpoint(self.path, self.provenance, self.fingerprint, engine.state(), columns)
        self._last = time.perf_counter()
        self._cost, self._since = self._last - now, 0

    def remove(self) -> None:
        """Remove the checkpoint (once the output is written)."""
        if self._usable:
            remove_checkpoint(self.path)


def checkpoint_fingerprint(section: ReconstructSection, provenance: Provenance, captures_path: Path) -> str:
    """SHA-256 of what a reconstruction's result depends on: the captures' bytes, the section (without
    ``checkpoint_every``), the starting spectrum's file (size and time) and the cca version."""
    try:
        inputs = [item["sha256"] for item in json.loads(provenance.get("inputs", "[]"))]
    except (ValueError, KeyError, TypeError):
        inputs = []
    init = None
    if section.init is not None and Path(section.init).is_file():
        stat = Path(section.init).stat()
        init = [str(section.init), stat.st_size, stat.st_mtime_ns]
    data = {"inputs": inputs or [file_sha256(captures_path)], "init": init, "version": __version__,
            "section": section.model_dump(mode="json", exclude={"checkpoint_every"})}
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def read_captures(path: Path) -> Captures:
    """Read /measurements, /geometry and (if present) /truth, checking shapes and values."""
    with open_input(path) as handle:
        captures = read_measurements(handle, Path(path))
    k = captures.intensity.shape[0]
    if k != captures.geometry.n_images:
        raise InputError(f"{path}: {k} images but /geometry describes {captures.geometry.n_images} positions")
    return captures


def reconstruct(captures: Captures, section: ReconstructSection, *, progress: ProgressFn = silent,
                checkpoint: Checkpointing | None = None) -> Recovery:
    """Run the configured engine on ``captures`` (``engine: auto`` resolved for the kind of data).

    ``section.init`` names a recon.h5 whose spectrum the engine starts from; with
    ``checkpoint`` the run continues from a matching checkpoint and writes new ones.
    """
    name, options = engine_options(section, data_kind(captures))
    return recover(captures, name, options, progress=progress, init=section.init,
                   checkpoint=checkpoint)


def write_recon(path: Path, captures: Captures, recovery: Recovery, provenance: Provenance, *, force: bool = False,
                observed: np.ndarray | None = None, extra=None, region: RegionEmbedding | None = None) -> None:
    """Write ``recon.h5`` atomically: recovery, history, centre capture, truth and geometry.

    ``observed`` replaces the centre capture as /observed/centre; ``extra(handle)``
    writes further groups (multiplexed runs add /multiplex). Captures left out as
    dead (``captures.dropped``) are listed in the /recon attribute ``dropped_captures``. With ``region``
    (padded captures) /recon/object, /recon/intensity and /observed/centre
    hold the region only and /recon/region_px says where it sits.
    """
    obj = fft.ifft2c(recovery.spectrum).astype(np.complex64)
    layout = recovery.layout
    units = captures.units   # recorded captures: counts/s instead of the simulation's irradiance
    if region is not None:
        y0, x0, hh, ww = region.hires_box(layout.hires_size)
        obj = np.ascontiguousarray(obj[y0:y0 + hh, x0:x0 + ww])
        if observed is None:
            observed = region.crop(captures.intensity[captures.geometry.centre_index])
    with atomic_h5(path, provenance, force=force) as handle:
        write_dataset(handle, "/recon/spectrum", recovery.spectrum, units=units and f"√({units}) · px")
        write_dataset(handle, "/recon/object", obj, units=units and f"√({units})")
        write_dataset(handle, "/recon/intensity", (np.abs(obj) ** 2).astype(np.float32), units=units)
        for name in ("residual", "change", "seconds"):
            write_dataset(handle, f"/history/{name}", recovery.history.array(name))
        write_dataset(handle, "/observed/centre",
                      captures.intensity[captures.geometry.centre_index] if observed is None else observed, units=units)
        for name, data in captures.truth.items():
            write_dataset(handle, f"/truth/{name}", data)
        write_geometry(handle, captures.geometry)
        if region is not None:
            oy, ox = region.offset_yx
            write_dataset(handle, "/recon/region_px", np.array([[y0, x0, hh, ww], [oy, ox, *region.shape]], np.int32),
                          guard_px=region.guard_px, apodize_px=region.apodize_px, sensor_grid_px=region.size)
        if recovery.fit is not None:
            write_fit(handle, recovery.fit)
        if recovery.calibration is not None:
            write_calibration(handle, recovery.calibration, captures.geometry)
        if extra is not None:
            extra(handle)
        recon = handle["recon"]
        recon.attrs["engine"] = recovery.engine
        recon.attrs["engine_options"] = json.dumps(recovery.options)
        recon.attrs["iterations"] = recovery.history.iterations
        recon.attrs["stopped_by"] = recovery.stopped_by
        recon.attrs["seconds"] = recovery.seconds
        recon.attrs["hires_size"] = layout.hires_size
        recon.attrs["lowres_size"] = layout.lowres_size
        recon.attrs["pixel_pitch_object_m"] = captures.geometry.field_width_m / layout.hires_size
        recon.attrs["fft_backend"] = fft.backend_name()
        if captures.dropped:
            recon.attrs["dropped_captures"] = np.asarray(captures.dropped, np.int32)


def write_fit(handle, fit: FitReport) -> None:
    """The residuals of the final model: per capture, and over all / bright-field / dark-field captures."""
    write_dataset(handle, "/recon/residual_per_image", fit.per_image)
    write_dataset(handle, "/calibration/bright_field", fit.bright_field_mask)
    recon = handle["recon"]
    for name in ("all", "bright_field", "dark_field"):
        recon.attrs[f"residual_{name}"] = getattr(fit, name)
        recon.attrs[f"residual_{name}_without_brightness"] = getattr(fit, f"{name}_without_brightness")


def write_calibration(handle, calibration: Calibration, geometry: CaptureGeometry) -> None:
    """Pupils, refined positions and brightness under /calibration, SI next to pixels."""
    group = handle.require_group("calibration")
    if calibration.pupil is not None:
        estimate = calibration.pupil
        write_dataset(handle, "/calibration/pupil", calibrated_pupils(calibration, geometry.pupil_radius_px))
        write_dataset(handle, "/calibration/pupil_map", estimate.maps.astype(np.complex64))
        write_dataset(handle, "/calibration/zernike_waves", estimate.coefficients)
        write_dataset(handle, "/calibration/zernike_modes", np.asarray(estimate.modes, np.int32))
        group.attrs["pupil_model"] = estimate.model
        group.attrs["pupil_radius_px"] = geometry.pupil_radius_px
        group.attrs["spectrum_pixel_per_m"] = 1.0 / geometry.field_width_m
    write_dataset(handle, "/calibration/pupil_index", calibration.pupil_index.astype(np.int32))
    write_dataset(handle, "/calibration/spectrum_centres_yx_px", calibration.centres_px)
    metres_per_px = geometry.aperture_centres_yx_m / np.where(geometry.spectrum_centres_yx_px == 0, np.nan,
                                                               geometry.spectrum_centres_yx_px)
    scale = float(np.nanmedian(metres_per_px)) if np.isfinite(metres_per_px).any() else float("nan")
    write_dataset(handle, "/calibration/aperture_centres_yx_m", calibration.centres_px * scale)
    write_dataset(handle, "/calibration/brightness", calibration.brightness)
    if calibration.position_model is not None:
        group.attrs["position_model"] = calibration.position_model
        group.attrs["position_parameters"] = json.dumps(calibration.position_parameters)


def run(captures_path: Path, section: ReconstructSection, output: Path, *, provenance: Provenance,
        force: bool = False, progress: ProgressFn = silent) -> Recovery:
    """Read captures, reconstruct, write ``output``.

    The reconstruction saves its state to ``<output>.checkpoint`` every ``section.checkpoint_every``
    iterations and, run again with the same captures and section, continues from it; the checkpoint is
    removed once ``output`` is written. With ``section.tiles`` the frame is recovered in tiles on Dask
    (:func:`run_tiled`).
    """
    check_output(output, force=force)
    from cca_cli.workflows import multiplex

    if section.tiles is not None:
        if multiplex.is_multiplexed_file(captures_path):
            raise InputError(f"{captures_path}: multiplexed captures are recovered whole; leave out reconstruct.tiles")
        return run_tiled(captures_path, section, output, provenance=provenance, force=force, progress=progress)
    if multiplex.is_multiplexed_file(captures_path):
        return multiplex.run_reconstruct(captures_path, section, output, provenance=provenance, force=force,
                                         write_recon=write_recon,
                                         progress=progress)
    captures, region = embed_region(without_dead_captures(read_captures(captures_path), source=captures_path),
                                    section)
    checkpoint = Checkpointing(checkpoint_path(output), checkpoint_fingerprint(section, provenance, captures_path),
                               section.checkpoint_every, provenance)
    recovery = reconstruct(captures, section, progress=progress, checkpoint=checkpoint)
    from cca_cli.io.capture_info import capture_extras

    write_recon(output, captures, recovery, provenance, force=force, extra=capture_extras(captures_path),
                region=region)
    checkpoint.remove()
    return recovery


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
    from cca_cli.io.tiled_recon import write_tiled_recon

    write_tiled_recon(output, tiled, provenance, force=force, extra=capture_extras(captures_path))
    remove_tile_folder(output)
    return tiled
