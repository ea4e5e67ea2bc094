"""Tiled reconstruction of a wide frame on Dask: every tile with its own pupil and illumination angles.

The frame is cut into overlapping square tiles (:mod:`cca_cli.sampling.tiles`).
Each tile is a task on a ``dask.distributed`` cluster (a local cluster of
single-threaded worker processes by default, or the workers of ``--scheduler``):

1. the worker reads only the tile's pixels of every capture (memory follows the
   tile, never the frame), gives it its local geometry (LED arrays with a known
   LED distance: the angle from each LED to the tile's centre; camera scans: the
   same apertures) and a guard band (:func:`~cca_cli.workflows.recovery.embed_region`);
2. it recovers the tile with the configured engine (``engine: auto``: the
   calibrating preset of the kind of data, simulations included, so every tile
   recovers a pupil), its pupil starting from a finished neighbour's (tiles
   run from the centre outwards; the centre tile starts from the data);
3. it puts the tile's object on the common blend grid (``q`` samples per frame
   pixel, a zero-padded spectrum), registers it to the tile's centre capture
   when the pupil model may have moved it (a full pupil map's tilt is a shift
   of the image), and writes it with its pupil to ``<output>.tiles/`` (one
   file per tile, temporary file + rename).

The client then blends the tiles (weights summing to 1, sin² ramps over the
middle half of each overlap), aligning each tile's arbitrary global phase to the
tiles already placed. A run that was killed recovers only the tiles that have
no finished file (a file a crash left damaged is redone); ``pupil: global``
holds the centre tile's pupil fixed on every other tile (one pupil for the whole
field, for comparison).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import hashlib
import json
import logging
import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReconstructSection
from cca_cli.engines.base import History, IterationRecord
from cca_cli.engines.options import EngineOptions
from cca_cli.engines.registry import get_engine
from cca_cli.errors import CcaError, ConfigError, InputError, OutputError
from cca_cli.io.h5 import Provenance
from cca_cli.io.recon import TilesRecord
from cca_cli.io.measurements import INTENSITY
from cca_cli.io.tiles import (FrameInfo, TileResult, read_dead_frames, read_frame_centre, read_frame_info,
                              read_stray_light, read_tile_captures, read_tile_result, tile_file_problem, tile_folder,
                              tile_path, write_tile_result)
from cca_cli.library.data import CaptureSet, Reconstruction
from cca_cli.library.recovery import DeviceUnavailable, check_dead_captures, drop_captures, engine_device, recover
from cca_cli.optics import backend, fft
from cca_cli.progress import ProgressEvent, ProgressFn, silent
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import band_layout
from cca_cli.sampling.region import RegionEmbedding, plan_embedding
from cca_cli.sampling.tiles import Tile, TilePlan, local_illumination, plan_tiles, tile_order
from cca_cli.version import __version__
from cca_cli.workflows.recovery import embed_region, engine_options, recipe_of

__all__ = ["TiledPlan", "TiledRecovery", "plan_tiled", "without_dead_frames", "local_tile_workers", "tile_geometry",
           "tile_engine",
           "tile_recipe", "run_tile",
           "stitch", "reconstruct_tiled"]

#: Seconds between a worker's progress messages for one tile.
_PROGRESS_EVERY_S = 1.0
_log = logging.getLogger("cca")


@dataclass(frozen=True)
class TiledPlan:
    """What a tiled reconstruction will do, known before any image is read (but the dead captures).

    Attributes
    ----------
    captures_path : Path
    frame : FrameInfo
    geometry : CaptureGeometry
        The frame's geometry (field width across the frame's columns).
    tiles : TilePlan
    upsampling : int
        Samples of the blend grid per frame pixel (``q``): the finest any tile's recovery needs.
    dropped : tuple of int
        Dead captures (their whole frame holds one value), which every tile leaves out
        (:func:`without_dead_frames`).
    stray_light : bool
        Whether the whole frames' dark-field images never fall near zero, which turns every tile's background
        fit on (:func:`~cca_cli.io.tiles.read_stray_light`; a tile alone would read its own part).
    """

    captures_path: Path
    frame: FrameInfo
    geometry: CaptureGeometry
    tiles: TilePlan
    upsampling: int
    dropped: tuple[int, ...] = ()
    stray_light: bool = False

    @property
    def frame_pixel_m(self) -> float:
        """Object-plane size of one frame pixel (m)."""
        return self.geometry.field_width_m / self.frame.frame_shape[1]

    @property
    def blend_shape(self) -> tuple[int, int]:
        """``(q·H, q·W)``: the stitched object's shape."""
        h, w = self.frame.frame_shape
        return h * self.upsampling, w * self.upsampling


@dataclass(frozen=True)
class TiledRecovery:
    """The stitched result of a tiled reconstruction.

    ``object`` is the blended field on the blend grid (``q·H x q·W``); ``results`` the
    tiles without their objects (pupils, coefficients, residuals), row by row.
    """

    plan: TiledPlan
    object: np.ndarray
    results: tuple[TileResult, ...]
    seconds: float
    ran: int          # tiles recovered by this run (the others were finished before)
    engine: str
    options: dict
    pupil_mode: str = "per_tile"

    @property
    def history(self) -> History:
        """One history for the tiles: per iteration the median residual and change over the tiles.

        A tile that stopped earlier holds its last values; ``seconds`` is the longest tile's time so far.
        """
        histories = [r.history for r in self.results if r.history and len(r.history.get("residual", ())) > 0]
        if not histories:
            return History()
        n = max(len(h["residual"]) for h in histories)

        def column(name: str) -> np.ndarray:
            return np.stack([np.concatenate([h[name], np.full(n - len(h[name]), h[name][-1])]) for h in histories])

        residual, change, seconds = column("residual"), column("change"), column("seconds")
        return History([IterationRecord(i + 1, float(np.median(residual[:, i])), float(np.median(change[:, i])),
                                        float(np.max(seconds[:, i]))) for i in range(n)])

    @property
    def stopped_by(self) -> str:
        """``cap`` when any tile reached its iteration cap, else the most common reason."""
        reasons = [r.stopped_by for r in self.results]
        return "cap" if "cap" in reasons else max(set(reasons), key=reasons.count)

    @property
    def hires_size(self) -> int:
        """Side of the square grid the blended object is written on."""
        return self.plan.upsampling * max(self.plan.frame.frame_shape)

    def as_reconstruction(self) -> tuple[Reconstruction, TilesRecord]:
        """The blended frame as a Reconstruction (on a square grid, the frame centred) and the tiles' record.

        The square grid holds ``q`` samples per frame pixel; the frame is marked as its region when
        it is not square. Reads the centre capture and the truth from the captures file.
        """
        plan = self.plan
        h, w = plan.frame.frame_shape
        q = plan.upsampling
        side = max(h, w)
        oy, ox = (side - h) // 2, (side - w) // 2
        square = np.zeros((q * side, q * side), np.complex64)
        square[oy * q:(oy + h) * q, ox * q:(ox + w) * q] = self.object
        spectrum = fft.fft2c(square).astype(np.complex64)
        del square
        geometry = with_field_width(plan.geometry, plan.geometry.field_width_m * side / w)
        observed, truth = read_frame_centre(plan.captures_path, geometry.centre_index)
        if plan.dropped:   # the captures the tiles used, as a whole-frame run's geometry holds them
            geometry = geometry.select(np.setdiff1d(np.arange(geometry.n_images), plan.dropped))
        region = None if (h, w) == (side, side) else RegionEmbedding(size=side, offset_yx=(oy, ox), shape=(h, w),
                                                                     guard_px=0, apodize_px=0)
        results = self.results
        result = Reconstruction(
            object=self.object, spectrum=spectrum, history=self.history,
            geometry=replace(geometry, pixel_pitch_m=plan.geometry.pixel_pitch_m), engine=self.engine,
            options=self.options, seconds=self.seconds, stopped_by=self.stopped_by, observed=observed, truth=truth,
            units=plan.frame.units, band_grid_px=side, region=region, dropped=plan.dropped,
            device="+".join(sorted({r.device for r in results})))
        have_pupils = all(r.pupil is not None for r in results)
        have_waves = all(r.zernike_waves is not None for r in results)
        tiles = TilesRecord(
            box_px=np.array([r.box for r in results]), grid_index=np.array([[r.row, r.col] for r in results]),
            residual=np.array([[r.residual.get(n, np.nan) for n in ("all", "bright_field", "dark_field")]
                               for r in results], np.float64),
            iterations=np.array([r.iterations for r in results]), seconds=np.array([r.seconds for r in results]),
            shift_px=np.array([r.shift_px for r in results], np.float64),
            pupil=np.stack([r.pupil for r in results]) if have_pupils else None,
            zernike_waves=np.stack([np.atleast_2d(r.zernike_waves) for r in results]) if have_waves else None,
            zernike_modes=np.asarray(results[0].zernike_modes, np.int32) if have_waves else None,
            attrs=dict(size_px=plan.tiles.size, overlap_px=plan.tiles.overlap, rows=plan.tiles.grid_shape[0],
                       cols=plan.tiles.grid_shape[1], upsampling=plan.upsampling, ran=self.ran,
                       pupil=self.pupil_mode))
        return result, tiles


def tile_geometry(geometry: CaptureGeometry, frame_shape, tile: Tile) -> CaptureGeometry:
    """The geometry one tile sees: its own field width and, for LED arrays with a known LED distance, its own angles.

    Parameters
    ----------
    geometry : CaptureGeometry
        The frame's (field width across its columns, angles at its centre).
    frame_shape : tuple of int
        ``(H, W)`` of the frame.
    tile : Tile
    """
    h, w = frame_shape
    pixel_m = geometry.field_width_m / w
    local = with_field_width(geometry, tile.size * pixel_m)
    if geometry.kind != "led_array" or not np.isfinite(geometry.led_distance_m):
        return local
    cy, cx = tile.centre_yx
    offset_m = ((cy - (h - 1) / 2.0) * pixel_m, (cx - (w - 1) / 2.0) * pixel_m)
    sines = local_illumination(geometry.aperture_centres_yx_m, offset_m, geometry.led_distance_m)
    return with_field_width(replace(geometry, aperture_centres_yx_m=sines), tile.size * pixel_m)


def plan_tiled(captures_path: Path, section: ReconstructSection) -> TiledPlan:
    """Tiles, their grids and the blend grid for ``captures_path``, from shapes and geometry alone."""
    from cca_cli.io.h5 import open_input
    from cca_cli.io.geometry import read_geometry

    if section.tiles is None:
        raise ValueError("the reconstruct section has no tiles")
    if section.init is not None:
        raise ConfigError("reconstruct.init: a tiled reconstruction starts every tile from its own data; leave out "
                          "init or reconstruct.tiles")
    frame = read_frame_info(captures_path)
    with open_input(captures_path) as handle:
        geometry = read_geometry(handle)
    if frame.n_images != geometry.n_images:
        raise InputError(f"{captures_path}: {frame.n_images} images but /geometry describes {geometry.n_images} "
                         "positions")
    try:
        tiles = plan_tiles(frame.frame_shape, section.tiles.size_px, section.tiles.overlap_px)
    except ValueError as exc:
        raise ConfigError(f"reconstruct.tiles: {exc}") from None
    padding = section.padding
    ratio = 1.0
    for tile in tiles.tiles:
        local = tile_geometry(geometry, frame.frame_shape, tile)
        region = plan_embedding((tile.size, tile.size), local.pupil_radius_px, guard_px=padding.guard_px,
                                apodize_px=padding.apodize_px)
        padded = with_field_width(local, local.field_width_m * region.size / tile.size)
        try:
            layout = band_layout(padded.spectrum_centres_yx_px, padded.pupil_radius_px, sensor_size=region.size)
        except ValueError as exc:
            raise InputError(f"{captures_path}: tile at ({tile.y0}, {tile.x0}): {exc}") from None
        ratio = max(ratio, layout.hires_size / region.size)
    return TiledPlan(Path(captures_path), frame, geometry, tiles, int(math.ceil(ratio - 1e-9)))


#: GPU memory a local tile worker on a GPU is given room for: its CUDA context (about 0.5 GB) and CuPy's pool of a
#: tile's arrays, with room to spare.
GPU_BYTES_PER_TILE_WORKER = 2 << 30


def local_tile_workers(workers: int | None, scheduler: str | None, device: str) -> int | None:
    """The local workers a tiled run starts: ``workers`` as asked; none at a ``scheduler``; else None, one per core.

    On a GPU (``device`` ``cuda``, resolved) one per core as well, the workers spread over the GPUs, but no more
    per GPU than its memory holds at :data:`GPU_BYTES_PER_TILE_WORKER` each. A tile's GPU work is small and each
    pass waits on its host's Python, so several processes keep one GPU busy where one would leave it idle.
    """
    if workers is not None or scheduler is not None:
        return workers
    if device != "cuda":
        return None
    gpus = max(1, backend.gpu_count())
    per_gpu = min(max(1, fft.cpu_count() // gpus), max(1, backend.gpu_memory_bytes() // GPU_BYTES_PER_TILE_WORKER))
    return gpus * per_gpu


def _tile_device(section: ReconstructSection, plan: TiledPlan) -> str:
    """Where every tile's engine runs, ``cpu`` or ``cuda`` (``auto`` resolved once, here), said before any
    tile runs: ``cuda`` where CuPy, a GPU or the tiles' options cannot is one line naming reconstruct.device."""
    name, options = tile_engine(section.model_copy(update={"device": "cuda"}), plan.geometry.kind,
                                frame_scale=plan.frame.frame_scale, stray_light=plan.stray_light)
    try:
        return engine_device(section.device, name, options)
    except DeviceUnavailable as exc:
        raise ConfigError(f"reconstruct.device: {exc}") from None


def without_dead_frames(plan: TiledPlan) -> TiledPlan:
    """``plan`` with the captures whose whole frame holds one value to be left out by every tile.

    Decided on the whole frames (a tile may hold only dark pixels of a live capture), with the
    whole-frame run's rule: a dead centre capture, or more than 5% dead, are refused in one line.
    """
    dead, values = read_dead_frames(plan.captures_path)
    check_dead_captures(dead, values, plan.geometry, name=INTENSITY, source=plan.captures_path, error=InputError)
    return replace(plan, dropped=tuple(int(i) for i in dead))


def tile_engine(section: ReconstructSection, kind: str, *, fixed: bool = False,
                frame_scale: str = "shared", stray_light: bool = False) -> tuple[str, EngineOptions]:
    """Engine and options a tile runs: ``auto`` takes the calibrating preset of the geometry's kind.

    Simulated captures included: a tiled reconstruction exists to recover a pupil per tile. On the CPU
    each tile runs single-threaded (``threads: 1``) unless the options say otherwise: the tiles are the
    parallelism; on a GPU (``section.device`` ``cuda``) the engine takes its own lanes. ``fixed`` holds the
    pupil the tile starts from (no pupil recovery); ``frame_scale`` is the captures', ``stray_light`` whether
    their whole frames hold light under the dark field (:attr:`TiledPlan.stray_light`).
    """
    if section.engine == "auto" and kind not in ("led_array", "camera_scan"):
        kind = "camera_scan"
    name, _ = engine_options(section, kind, frame_scale=frame_scale, stray_light=stray_light)
    names = get_engine(name).option_names()
    overrides = {}
    if "threads" in names and "threads" not in section.options and section.device != "cuda":
        overrides["threads"] = 1
    if fixed and "pupil_recovery" in names:
        overrides["pupil_recovery"] = "none"
    return engine_options(section, kind, frame_scale=frame_scale, stray_light=stray_light, **overrides)


@dataclass(frozen=True)
class TileTask:
    """Everything a worker needs to recover one tile (plain data: it travels to another process)."""

    plan: TiledPlan
    section: dict
    tile: Tile
    output: str
    fingerprint: str
    provenance: dict
    topic: str


def task_section(section: ReconstructSection) -> dict:
    """The section as a task carries it: only the keys the user set, so that ``engine: auto``'s preset fills
    the rest on the worker exactly as on the client (a full dump would mark every default as set)."""
    return section.model_dump(mode="json", exclude_unset=True)


def tile_fingerprint(run_fingerprint: str, tile: Tile) -> str:
    """SHA-256 of the run's fingerprint and the tile's box."""
    return hashlib.sha256(f"{run_fingerprint}:{tile.box}".encode()).hexdigest()


def run_tile(task: TileTask, parent: TileResult | None = None, fixed: bool = False) -> TileResult:
    """Recover one tile (a Dask task) and write its result file; return it without the object.

    Parameters
    ----------
    task : TileTask
    parent : TileResult, optional
        A finished neighbour: the tile's pupil starts from its Zernike coefficients.
    fixed : bool
        Hold the parent's pupil fixed (``tiles.pupil: global``) instead of recovering one.
    """
    section = ReconstructSection.model_validate(task.section)
    fingerprint = tile_fingerprint(task.fingerprint, task.tile)
    path = tile_path(Path(task.output), task.tile.row, task.tile.col)
    done = read_tile_result(path, fingerprint, with_object=False)
    if done is not None:
        return done
    threads = section.options.get("threads", 1)  # the tiles are the parallelism: one core each unless told
    with fft.limit_threads(threads), _worker_gpu(section.device):
        result = _recover_tile(task, section, parent, fixed, fingerprint)
    write_tile_result(path, result, Provenance(task.provenance))
    _publish(task.topic, {"tile": task.tile.index, "done": result.iterations, "total": result.iterations,
                          "finished": True})
    return result.summary()


def _worker_gpu(device: str):
    """The GPU this worker's tiles run on: on cca's local cluster, where a machine has several, worker n takes
    GPU n modulo their number; a worker of an existing cluster keeps the GPU its launcher gave it."""
    from cca_cli.workflows.worker_setup import LOCAL_WORKER

    if device != "cuda" or not os.environ.get(LOCAL_WORKER):
        return contextlib.nullcontext()
    count = backend.gpu_count()
    try:
        from distributed import get_worker

        number = int(get_worker().name)
    except (ImportError, ValueError, TypeError):   # not on a Dask worker, or not one of cca's numbered ones
        return contextlib.nullcontext()
    return backend.using_gpu(backend.gpu_for_worker(number, count)) if count > 1 else contextlib.nullcontext()


def _recover_tile(task: TileTask, section: ReconstructSection, parent: TileResult | None, fixed: bool,
                  fingerprint: str) -> TileResult:
    """Read, recover and put one tile on the blend grid (the work of :func:`run_tile`)."""
    plan, tile = task.plan, task.tile
    captures = read_tile_captures(plan.captures_path, tile.box)
    captures = replace(captures, geometry=tile_geometry(plan.geometry, plan.frame.frame_shape, tile))
    captures = drop_captures(captures, plan.dropped)
    padded, region = embed_region(captures, section, source=plan.captures_path)
    name, options = tile_engine(section, plan.geometry.kind, fixed=fixed, frame_scale=plan.frame.frame_scale,
                                stray_light=plan.stray_light)
    start = None
    if parent is not None and parent.zernike_waves is not None:
        start = np.asarray(parent.zernike_waves, np.float64)
    try:
        recovery = recover(padded, name, options, on_iteration=_reporter(task.topic, tile, options.max_iterations),
                           aberration=start, device=section.device)
    except ValueError as exc:
        raise InputError(f"{plan.captures_path}: tile at ({tile.y0}, {tile.x0}): {exc}") from None
    obj, shift = _on_blend_grid(recovery, padded, region, plan.upsampling, register=options.recovers_pupil_map)
    pupil = waves = None
    modes: list = []
    if recovery.calibration is not None and recovery.calibration.pupil is not None:
        estimate = recovery.calibration.pupil
        pupil = recovery.pupil
        waves, modes = np.asarray(estimate.coefficients, np.float64), [tuple(m) for m in estimate.modes]
    elif start is not None:  # a fixed pupil: the coefficients it was held at
        from cca_cli.optics.zernike import zernike_modes

        waves, modes = start, list(zernike_modes(options.pupil_order))
    fit = recovery.fit
    residual = {} if fit is None else {"all": fit.all, "bright_field": fit.bright_field, "dark_field": fit.dark_field}
    result = TileResult(row=tile.row, col=tile.col, box=tile.box, object=obj, pupil=pupil, zernike_waves=waves,
                        zernike_modes=modes, residual=residual, iterations=recovery.history.iterations,
                        seconds=recovery.seconds, stopped_by=recovery.stopped_by, engine=name,
                        history={n: recovery.history.array(n) for n in ("residual", "change", "seconds")},
                        shift_px=shift, fingerprint=fingerprint, device=recovery.device)
    return result


def _on_blend_grid(recovery: Reconstruction, captures: CaptureSet, region, upsampling: int, *, register: bool):
    """The tile's region of the recovered field on the blend grid (``q`` samples per frame pixel).

    The spectrum is zero-padded from the recovery's ``M`` to ``q·S`` (``S`` the padded tile), which puts
    sensor pixel ``i`` at blend sample ``q·i`` exactly; the region is then cut out. With ``register`` the
    field is shifted so that its intensity, below the centre capture's band, lines up with that capture.
    """
    spectrum = recovery.spectrum
    m = spectrum.shape[-1]
    s = region.size
    size = upsampling * s
    shift = (0.0, 0.0)
    field = fft.ifft2c(fft.resize_spectrum(spectrum, (size, size))) * np.float32(size / m)
    oy, ox = region.offset_yx
    h, w = region.shape
    q = upsampling
    crop = field[oy * q:(oy + h) * q, ox * q:(ox + w) * q]
    if register:
        from cca_cli.report.bar_reading import offset_to_observed
        from cca_cli.report.summary import on_grid

        observed = region.crop(captures.intensity[captures.geometry.centre_index])
        cutoff = min(2.0 * captures.geometry.pupil_radius_px * w / s, 0.4 * w)
        shift = offset_to_observed(np.abs(crop) ** 2, on_grid(observed, crop.shape), cutoff)
        ky = np.fft.fftfreq(size)[:, None]
        kx = np.fft.fftfreq(size)[None, :]
        ramp = np.exp(2j * np.pi * (ky * shift[0] + kx * shift[1])).astype(np.complex64)
        field = fft.ifft2(fft.fft2(field) * ramp)
        crop = field[oy * q:(oy + h) * q, ox * q:(ox + w) * q]
    return np.ascontiguousarray(crop.astype(np.complex64)), (float(shift[0]), float(shift[1]))


def _reporter(topic: str, tile: Tile, total: int):
    """An ``on_iteration`` callback that tells the client how far a tile is, at most every half second."""
    last = [0.0]

    def report(record) -> None:
        now = time.monotonic()
        if now - last[0] >= _PROGRESS_EVERY_S:
            last[0] = now
            _publish(topic, {"tile": tile.index, "done": record.iteration, "total": total,
                             "residual": float(record.residual)})

    return report


def _publish(topic: str, message: dict) -> None:
    """Send a progress message to the client (nothing outside a Dask worker)."""
    try:
        from distributed import get_worker

        get_worker().log_event(topic, message)
    except (ImportError, ValueError):
        pass


def warm_up() -> None:
    """Import the engines and compile their kernels in a worker process (run while the centre tile runs)."""
    import importlib

    from cca_cli.optics import kernels

    importlib.import_module("cca_cli.engines.momentum")
    kernels.warm_up()


async def _warm_up_soon() -> None:
    """:func:`warm_up` as Dask's ``client.run(..., wait=False)`` needs it (a coroutine)."""
    warm_up()


def stitch(plan: TiledPlan, read_object) -> np.ndarray:
    """Blend the tiles' objects into the frame's, each tile's global phase aligned to those already placed.

    Parameters
    ----------
    plan : TiledPlan
    read_object : callable
        ``read_object(tile)`` → the tile's object on the blend grid, complex64 ``(q·size, q·size)``.

    Returns
    -------
    ndarray, complex64, ``plan.blend_shape``
    """
    q = plan.upsampling
    out = np.zeros(plan.blend_shape, np.complex64)
    placed = np.zeros(plan.blend_shape, np.float32)
    for tile, _ in tile_order(plan.tiles):
        y0, x0, size = tile.y0 * q, tile.x0 * q, tile.size * q
        box = (slice(y0, y0 + size), slice(x0, x0 + size))
        obj = read_object(tile)
        weight = plan.tiles.weight(tile, q)
        overlap = placed[box] * weight
        if overlap.any():  # the tile's global phase is arbitrary: match the blend so far where both have weight
            inner = np.vdot(obj * overlap, out[box] / np.maximum(placed[box], 1e-12))
            if abs(inner) > 0:
                obj = obj * np.complex64(inner / abs(inner))
        out[box] += weight * obj
        placed[box] += weight
    return out


def reconstruct_tiled(captures_path: Path, section: ReconstructSection, output: Path, *, run_fingerprint: str,
                      provenance: Provenance, client=None, progress: ProgressFn = silent) -> TiledRecovery:
    """Recover every tile of ``captures_path`` on Dask and blend them.

    Parameters
    ----------
    captures_path : Path
    section : ReconstructSection
        With ``tiles`` set.
    output : Path
        The recon.h5 the result is for: tile files go to ``<output>.tiles/``.
    run_fingerprint : str
        What the result depends on (captures and options); tile files of another fingerprint are redone.
    provenance : Provenance
        Written into every tile file.
    client : distributed.Client, optional
        Default: a client of :func:`~cca_cli.workflows.cluster.cluster_settings` (a local cluster).
    progress : callable, optional
        Receives ``reconstruct/tiles`` events and one transient event stream per running tile.

    Returns
    -------
    TiledRecovery
    """
    from cca_cli.workflows.cluster import cluster_settings, open_client

    plan = plan_tiled(captures_path, section)
    plan = replace(plan, stray_light=read_stray_light(captures_path))
    start = time.perf_counter()
    section = section.model_copy(update={"device": _tile_device(section, plan)})   # the tiles all run there
    name, options = tile_engine(section, plan.geometry.kind, frame_scale=plan.frame.frame_scale,
                                stray_light=plan.stray_light)
    plan = without_dead_frames(plan)
    order = tile_order(plan.tiles)
    total = len(order)
    finished: dict[int, TileResult] = {}
    for tile, _ in order:
        path = tile_path(output, tile.row, tile.col)
        done = read_tile_result(path, tile_fingerprint(run_fingerprint, tile), with_object=False)
        if done is not None:
            finished[tile.index] = done
        else:
            _make_way(path)
    ran = total - len(finished)
    progress(ProgressEvent("reconstruct", "tiles", len(finished), total))
    if ran:
        topic = f"cca-tiles-{hashlib.sha256(str(output).encode()).hexdigest()[:12]}-{time.time_ns()}"
        task_data = dict(section=task_section(section), output=str(output), fingerprint=run_fingerprint,
                         provenance=dict(provenance), topic=topic)
        tasks = {tile.index: TileTask(plan=plan, tile=tile, **task_data) for tile, _ in order}
        if client is None:
            settings = cluster_settings()
            with open_client(workers=local_tile_workers(settings.workers, settings.scheduler, section.device),
                             scheduler=settings.scheduler) as own:
                _run_on(own, plan, order, tasks, finished, section, progress, topic)
        else:
            _run_on(client, plan, order, tasks, finished, section, progress, topic)

    def read_object(tile: Tile) -> np.ndarray:
        result = read_tile_result(tile_path(output, tile.row, tile.col), tile_fingerprint(run_fingerprint, tile))
        if result is None:
            raise CcaError(f"{tile_path(output, tile.row, tile.col)}: the tile's result vanished or was changed "
                           "while the tiles were blended; run again")
        return result.object

    blended = stitch(plan, read_object)
    results = tuple(finished[t.index] for t in plan.tiles.tiles)
    return TiledRecovery(plan=plan, object=blended, results=results, seconds=time.perf_counter() - start, ran=ran,
                         engine=name, options=options.model_dump(), pupil_mode=section.tiles.pupil)


def _finished_file(task: TileTask) -> bool:
    """Whether the task's tile has its result file (it may have been written after the client last heard)."""
    fingerprint = tile_fingerprint(task.fingerprint, task.tile)
    path = tile_path(Path(task.output), task.tile.row, task.tile.col)
    return read_tile_result(path, fingerprint, with_object=False) is not None


def _make_way(path: Path) -> None:
    """Let a tile's result be written at ``path``: a damaged file cca wrote there (a crash truncated it) is
    removed with a note; a file cca did not write is refused, before any tile runs."""
    problem = tile_file_problem(path)
    if problem is None:
        return
    kind, why = problem
    if kind == "foreign":
        raise OutputError(f"{path}: the tile's result goes there, but cca did not write this file ({why}) and "
                          "never replaces what it did not write; move it away and run again")
    _log.warning("%s is damaged (%s): the tile is recovered again", path, why)
    path.unlink(missing_ok=True)


def _run_on(client, plan: TiledPlan, order, tasks: dict, finished: dict, section: ReconstructSection,
            progress: ProgressFn, topic: str) -> None:
    """Submit the unfinished tiles, each after the neighbour it starts from; report progress until all are done."""
    from distributed import wait

    from cca_cli.workflows.cluster import scheduler_gone, scheduler_lost

    messages: collections.deque = collections.deque()
    fixed = section.tiles.pupil == "global"
    futures = {}
    total = len(order)
    centre = order[0][0]
    try:
        client.subscribe_topic(topic, lambda event: messages.append(event[1]))
        # Only the centre tile can run at first: the other workers load cca meanwhile, not after it.
        client.run(_warm_up_soon, wait=False)
        for tile, parent in order:
            if tile.index in finished:
                continue
            if fixed:
                source = None if tile is centre else finished.get(centre.index, futures.get(centre.index))
            else:
                source = None if parent is None else finished.get(parent.index, futures.get(parent.index))
            futures[tile.index] = client.submit(run_tile, tasks[tile.index], source, fixed and tile is not centre,
                                                key=f"cca-tile-{topic}-{tile.index}", pure=False, retries=0)
        pending = set(futures.values())
        by_future = {future: index for index, future in futures.items()}
        source = None
        running: dict[int, int] = {}
        while pending:
            try:
                done, pending = wait(pending, timeout=1.0, return_when="FIRST_COMPLETED")
            except (TimeoutError, asyncio.TimeoutError):  # nothing finished yet: show how far the running tiles are
                done = set()
            while messages:
                message = messages.popleft()
                index = int(message["tile"])
                if index in finished:
                    continue
                running[index] = int(message["total"])
                tile = plan.tiles.tiles[index]
                info = {"residual": message["residual"]} if "residual" in message else {}
                progress(ProgressEvent("reconstruct", f"tile {tile.row},{tile.col}", int(message["done"]),
                                       int(message["total"]), info, transient=True))
            for future in list(done):
                index = by_future[future]
                try:
                    finished[index] = future.result()
                except (CcaError, *scheduler_gone()):  # the scheduler went away: below
                    raise
                except Exception as exc:  # a worker died, or the task failed in a way cca did not foresee
                    raise CcaError(f"reconstruct: tile {plan.tiles.tiles[index].row},{plan.tiles.tiles[index].col} "
                                   f"failed ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); "
                                   "run again to redo only the unfinished tiles") from None
                # Drop the client's hold on the result: the workers keep it only while a neighbour needs it,
                # so their memory does not grow with the number of tiles.
                del futures[index], by_future[future]
                tile = plan.tiles.tiles[index]
                if index in running:
                    progress(ProgressEvent("reconstruct", f"tile {tile.row},{tile.col}", running[index],
                                           running[index], transient=True))
                residual = finished[index].residual.get("all")
                progress(ProgressEvent("reconstruct", "tiles", len(finished), total,
                                       {} if residual is None else {"residual": float(residual)}))
    except scheduler_gone():
        kept = sum(_finished_file(task) for task in tasks.values())
        folder = tile_folder(Path(tasks[centre.index].output))
        raise scheduler_lost("reconstruct", f"the finished tiles are kept in {folder} ({kept} of {total})") from None
    except BaseException:
        for future in futures.values():
            future.cancel()
        raise
    finally:
        try:
            client.unsubscribe_topic(topic)
        except Exception:  # the client is already closing
            pass


def tile_recipe(section: ReconstructSection, captures_path: Path) -> dict:
    """The engine and options the tiles of ``captures_path`` resolve to, cca's defaults included
    (:func:`~cca_cli.workflows.recovery.recipe_of`).

    Raises
    ------
    CcaError, OSError, KeyError, ValueError
        When the captures cannot be read or the section's options do not resolve.
    """
    from cca_cli.io.geometry import read_geometry
    from cca_cli.io.h5 import open_input
    from cca_cli.io.tiles import read_frame_info

    frame_scale = read_frame_info(captures_path).frame_scale
    with open_input(captures_path) as handle:
        kind = read_geometry(handle).kind
    recipe = recipe_of(*tile_engine(section, kind, frame_scale=frame_scale,
                                    stray_light=read_stray_light(captures_path)))
    # Dead captures are left out of every tile (earlier tiled results, made with them, are not this recipe's).
    return {**recipe, "dead_captures": "left out"}


def run_fingerprint(section: ReconstructSection, inputs: list[str], captures_path: Path) -> str:
    """SHA-256 of what a tiled result depends on: the captures' bytes, the section, the engine and options the
    tiles resolve to (cca's defaults included: a preset that changed between versions redoes every tile) and
    the cca version."""
    from cca_cli.io.h5 import file_sha256

    try:
        recipe = tile_recipe(section, captures_path)
    except (CcaError, OSError, KeyError, ValueError):
        recipe = None   # the run itself says why
    data = {"inputs": inputs or [file_sha256(captures_path)], "version": __version__, "recipe": recipe,
            "section": section.model_dump(mode="json", exclude={"checkpoint_every", *section.NOT_RECIPE})}
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()
