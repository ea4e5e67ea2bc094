"""Memory and disk a stage will need, estimated before anything is allocated.

The estimates follow the arrays each stage holds at its peak, from the grid
sizes alone (:func:`~cca_cli.sampling.grid.band_sizes`, the same choice the
stages make, and :func:`~cca_cli.sampling.design.reconstruction_memory_bytes`,
the figure `cca design` prints). :func:`check_footprint` refuses a stage the
machine cannot hold, naming the estimate and the keys to change, and logs a
warning before a stage that will write more than :data:`LARGE_WRITE_BYTES`.

``CCA_MEMORY_LIMIT`` (bytes, or with a K/M/G/T suffix) replaces the memory
available for the check: the free memory (``psutil``) by default.
"""

from __future__ import annotations

import logging
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.config.model import RunConfig
from cca_cli.errors import ConfigError, InputError, ResourceError
from cca_cli.io.capacity import memory_available, size_text
from cca_cli.sampling.design import reconstruction_memory_bytes
from cca_cli.sampling.grid import band_sizes
from cca_cli.sampling.overlap import grid_for_sar
from cca_cli.units import FourierScale, object_pixel_pitch_m

__all__ = ["LARGE_WRITE_BYTES", "Footprint", "SimulationSizes", "simulation_sizes", "simulate_footprint",
           "reconstruct_footprint", "report_footprint",
           "memory_available", "check_footprint", "size_text"]

#: Writes above this size are announced before the stage starts.
LARGE_WRITE_BYTES = 2e9
_COMPLEX, _FLOAT = 8, 4
_BATCH = 16  # images recorded (resampled, noised) together by simulate
_REPORT_FILES_BYTES = 2e7  # report.json and a dozen PNG figures
_PER_CAPTURE = 2048  # positions, pupil boxes and bookkeeping per capture (measured: about 1.5 kB)

log = logging.getLogger("cca")


@dataclass(frozen=True)
class Footprint:
    """What one stage needs.

    Attributes
    ----------
    stage : str
    memory_bytes, disk_bytes : float
        Peak memory and size of what it writes (floats: may exceed any integer type).
    detail : str
        The sizes behind the numbers (``441 images of 512² px, object 1024² px``).
    fix : str
        What to change to make it smaller.
    """

    stage: str
    memory_bytes: float
    disk_bytes: float
    detail: str
    fix: str


def _fft_size(n: float) -> float:
    """The 7-smooth size the stages would choose, or ``n`` itself when it is far beyond any memory."""
    from cca_cli.sampling.grid import smallest_fft_size

    return float(smallest_fft_size(int(n))) if n < 1e12 else float(n)


def _grids(reach_px: float, radius: float, sensor: float) -> tuple[float, float, float]:
    """(m, M, box) for a band reaching ``reach_px`` with pupils of ``radius`` on a ``sensor``-pixel image."""
    if not (math.isfinite(radius) and math.isfinite(reach_px) and math.isfinite(sensor)):
        return math.inf, math.inf, math.inf
    if sensor < 1e9 and reach_px < 1e9:
        try:
            sizes = band_sizes(reach_px, radius, sensor_size=int(sensor))
            return float(sizes.lowres_size), float(sizes.hires_size), float(sizes.box_size)
        except ValueError:
            pass  # too coarse a sensor: the stage itself reports it
    box = 2 * math.ceil(radius) + 4
    lowres = min(_fft_size(4 * radius + 1), sensor)
    hires = max(_fft_size(2 * (reach_px + box / 2 + 1)), _fft_size(sensor), lowres)
    return lowres, hires, box


@dataclass(frozen=True)
class SimulationSizes:
    """The sizes a simulation works with, from the config's numbers alone (floats: they may be huge).

    Attributes
    ----------
    images : float
        Images stored (K, or P·T multiplexed).
    fields : float
        Fields computed (virtual captures when multiplexed).
    stored_px, lowres_px, hires_px, box_px : float
        Side of the stored images, of the per-capture grid m, of the object grid M and of a pupil box.
    fix : str
        The keys that make it smaller.
    """

    images: float
    fields: float
    stored_px: float
    lowres_px: float
    hires_px: float
    box_px: float
    fix: str


def simulation_sizes(config: RunConfig) -> SimulationSizes:
    """The sizes of simulating ``config`` (the same choices as the simulate stage, without arrays).

    Raises
    ------
    ConfigError
        If the optics leave too few sensor pixels (the message the stage would give).
    """
    optics, scene = config.optics, config.scene
    object_pixel = object_pixel_pitch_m(optics.pixel_pitch_m, optics.focal_length_m, optics.distance_m)
    sensor = scene.field_width_m / object_pixel if object_pixel > 0 else math.inf
    if not sensor >= 8:
        raise ConfigError(f"optics/scene: the field of view spans only {sensor:.3g} sensor pixels; widen the scene "
                          "or use smaller pixels")
    sensor = float(round(sensor)) if sensor < 1e15 else sensor  # as units.sensor_pixels_across, without overflow
    scale = FourierScale.fraunhofer(optics.wavelength_m, optics.distance_m, sensor * object_pixel)
    metres_per_px = scale.metres_per_pixel
    radius = scale.pupil_radius_px(optics.aperture_diameter_m)
    if config.multiplex is not None:
        mux = config.multiplex
        cameras = float(mux.camera_grid[0]) * mux.camera_grid[1]
        patterns = len(mux.pattern_list) if mux.pattern_list is not None else mux.patterns
        per_pattern = max(len(p) for p in mux.pattern_list) if mux.pattern_list is not None else mux.n_mux
        images, fields = cameras * patterns, cameras * patterns * per_pattern
        pitch = optics.aperture_diameter_m if mux.camera_pitch_m == "abutting" else mux.camera_pitch_m
        reach = (max(mux.camera_grid) - 1) / 2 * pitch / metres_per_px + (max(mux.source_grid) - 1) * radius
        fix = "lower multiplex.camera_grid, multiplex.patterns or scene.size_px"
    else:
        array = config.array
        grid = array.grid if array.grid is not None else grid_for_sar(array.sar, array.overlap)
        images = fields = float(grid) * float(grid)
        reach = (grid - 1) / 2 * (1 - array.overlap) * optics.aperture_diameter_m / metres_per_px
        fix = f"lower array.{'grid' if array.grid is not None else 'sar'} or scene.size_px"
    lowres, hires, box = _grids(reach, radius, sensor)
    if config.multiplex is not None and math.isfinite(hires):
        hires = float(scene.size_px * math.ceil(hires / scene.size_px))
    stored = sensor if config.simulate.store == "sensor" else lowres
    if config.simulate.store == "sensor":
        fix += ", or use simulate.store: band"
    return SimulationSizes(images, fields, stored, lowres, hires, box, fix)


def simulate_footprint(config: RunConfig) -> Footprint:
    """Memory and disk of ``cca simulate`` for ``config``, from its numbers alone."""
    sizes = simulation_sizes(config)
    chart = float(config.scene.size_px) * config.scene.size_px
    m, big, stored = sizes.lowres_px, sizes.hires_px, sizes.stored_px
    memory = (6 * chart * _COMPLEX + 6 * big * big * _COMPLEX + sizes.fields * m * m * _FLOAT
              + sizes.fields * (2 * sizes.box_px * sizes.box_px * _COMPLEX + _PER_CAPTURE)
              + 2 * _BATCH * m * m * _COMPLEX + sizes.images * stored * stored * _FLOAT
              + 4 * _BATCH * stored * stored * _COMPLEX)
    if config.aberration is not None:  # the blended field, one node's fields and their weighted product
        memory += 3 * sizes.fields * m * m * _COMPLEX
    disk = sizes.images * stored * stored * _FLOAT + big * big * _COMPLEX
    detail = (f"{sizes.images:.4g} images of {stored:.4g}² px, scene {config.scene.size_px:.4g}² px, "
              f"object {big:.4g}² px")
    return Footprint("simulate", memory, disk, detail, sizes.fix)


def _shape(handle, name: str) -> tuple[int, ...]:
    if name not in handle or not hasattr(handle[name], "shape"):
        from cca_cli.io.h5 import missing_dataset

        raise missing_dataset(handle, name)
    return tuple(int(n) for n in handle[name].shape)


def reconstruct_footprint(captures_path: Path, section=None) -> Footprint:
    """Memory and disk of ``cca reconstruct`` on a captures file (shapes and geometry only are read).

    With ``section.tiles`` the memory is that of the client (the blended frame, its square grid and
    spectrum, one tile's result) plus one tile's recovery per local worker process.
    """
    from cca_cli.io.geometry import read_geometry
    from cca_cli.io.h5 import open_input

    with open_input(captures_path) as handle:
        shape = _shape(handle, "/measurements/intensity")
        weighted = "/measurements/weight" in handle
        geometry = read_geometry(handle)
        truth = _shape(handle, "/truth/object") if "/truth/object" in handle else (0, 0)
        boundary = handle["/measurements/intensity"].attrs.get("boundary", "")
        frame_scale = str(handle["/measurements/intensity"].attrs.get("frame_scale", "shared"))
    if len(shape) != 3:
        raise InputError(f"{captures_path}: /measurements/intensity has shape {shape}, expected 3 dimensions")
    if section is not None and getattr(section, "tiles", None) is not None:
        return _tiled_footprint(captures_path, section, shape, geometry, truth)
    grid = _check_pupil_fits(captures_path, geometry.pupil_radius_px, shape[1:], boundary, section)
    k, h, w = (float(v) for v in shape)
    n = float(grid)
    scale = n / w   # a guard band widens the field: spectrum centres and pupil radius grow with it
    centres = geometry.spectrum_centres_yx_px
    reach = float(np.max(np.abs(np.rint(centres * scale)))) if centres.size else 0.0
    lowres, hires, box = _grids(reach, geometry.pupil_radius_px * scale, n)
    if _refines_positions(section, bool(truth[0]), geometry.kind, frame_scale):
        # pupils that may move get a margin on the object grid, as build_model gives them
        hires = _fft_size(hires + 2 * (math.ceil(geometry.pupil_radius_px * scale / 8) + 2))
    threads = _engine_threads(section, bool(truth[0]), geometry.kind, frame_scale)
    memory = (reconstruction_memory_bytes(k, n, lowres, hires, box) + (k * n * n * _FLOAT if weighted else 0)
              + k * h * w * _FLOAT + k * _PER_CAPTURE  # the images as read, besides the engine's own copy
              + _thread_bytes(threads, k, hires, box)
              + (2 * k * lowres * lowres * _FLOAT if _may_fit_background(section, geometry.kind) else 0))
    output = hires * hires * (2 * _COMPLEX + _FLOAT) + h * w * _FLOAT + float(truth[0]) * truth[1] * _COMPLEX
    # A checkpoint (the momentum engines' spectrum, velocity and anchor) lies beside the output until it is
    # written, and a new checkpoint beside the old one until it replaces it.
    checkpoint = 3 * hires * hires * _COMPLEX if getattr(section, "checkpoint_every", 50) else 0.0
    disk = max(output + checkpoint, 2 * checkpoint)
    grid_text = f" (recovered on a {n:.4g}² grid)" if n != w or h != w else ""
    return Footprint("reconstruct", memory, disk,
                     f"{k:.4g} images of {w:.4g} x {h:.4g} px{grid_text}, object {hires:.4g}² px, "
                     f"{threads} thread{'s' * (threads != 1)}",
                     "reconstruct fewer or smaller images (crop them, or simulate with simulate.store: band), "
                     "or use fewer threads (reconstruct.options.threads)")


def _may_fit_background(section, geometry_kind: str) -> bool:
    """Whether the run may fit a background (:mod:`cca_cli.engines.background`: the measured amplitudes less it
    are held twice more): on LED arrays, unless the options turn it off (the captures may turn it on)."""
    options = getattr(section, "options", None)
    return geometry_kind == "led_array" and not (isinstance(options, dict) and options.get("background") is False)


def _refines_positions(section, has_truth: bool, geometry_kind: str, frame_scale: str) -> bool:
    """Whether the engine the section resolves to on these captures moves the pupils (False where it does not
    resolve: the run itself says why)."""
    from cca_cli.config.model import ReconstructSection
    from cca_cli.library.data import data_kind
    from cca_cli.workflows.recovery import engine_options

    try:
        _, options = engine_options(section if section is not None else ReconstructSection(),
                                    data_kind(has_truth, geometry_kind), frame_scale=frame_scale)
    except (ConfigError, ValueError):
        return False
    return bool(getattr(options, "refines_positions", False))


def _engine_threads(section, has_truth: bool = False, geometry_kind: str = "", frame_scale: str = "shared") -> int:
    """Threads the engine is asked for: ``options.threads``, or those it takes unasked (the cores this process
    may use; a momentum engine at most its ``max_threads``)."""
    from cca_cli.optics.fft import default_threads

    options = getattr(section, "options", None)
    asked = options.get("threads") if isinstance(options, dict) else None
    try:
        if asked:
            return max(1, int(asked))
    except (TypeError, ValueError):
        return default_threads()   # the engine's own check names a bad value
    return min(default_threads(), _unasked_thread_cap(section, has_truth, geometry_kind, frame_scale))


def _unasked_thread_cap(section, has_truth: bool, geometry_kind: str, frame_scale: str) -> int:
    """The most threads the engine the section resolves to takes when none are named (no cap: a large number)."""
    from cca_cli.config.model import ReconstructSection
    from cca_cli.engines.registry import get_engine
    from cca_cli.library.data import data_kind
    from cca_cli.workflows.recovery import engine_options

    try:
        name, _ = engine_options(section if section is not None else ReconstructSection(),
                                 data_kind(has_truth, geometry_kind), frame_scale=frame_scale)
        cap = getattr(get_engine(name).engine_class(), "max_threads", None)
    except (ConfigError, ValueError, KeyError):
        return 1 << 16
    return int(cap) if cap else 1 << 16


def _thread_bytes(threads: int, k: float, hires: float, box: float) -> float:
    """Each thread's own work arrays: a spectrum-sized accumulator (``altmin``, on every thread asked for) or
    coverage, and room for a whole batch of update boxes (``momentum``, on at most its
    :data:`~cca_cli.engines.momentum.MAX_THREADS`; its batches may grow to every capture)."""
    from cca_cli.engines.momentum import MAX_THREADS

    return threads * hires * hires * _COMPLEX + min(threads, MAX_THREADS) * k * box * box * _COMPLEX


def _check_pupil_fits(captures_path: Path, radius: float, frame: tuple[int, int], boundary, section=None) -> int:
    """The side of the square grid the images are recovered on (with the guard band recorded or non-square
    frames get, as :func:`~cca_cli.library.recovery.embed_region` places them).

    A pupil the images cannot hold is a wrong geometry, not a memory question: say so before estimating.
    """
    from cca_cli.sampling.region import plan_embedding

    h, w = frame
    boundary = boundary.decode() if isinstance(boundary, bytes) else str(boundary)
    padding = getattr(section, "padding", None)
    padded = getattr(padding, "mode", "auto") != "off"
    if h != w and not padded:
        raise InputError(f"{captures_path}: the images are {w}x{h} px; with reconstruct.padding.mode off they must "
                         "be square (crop them, e.g. registration.crop_xywh, or pad them: mode auto)")
    grid = w
    if (h != w or boundary == "open") and radius >= 1 and padded:
        grid = plan_embedding((h, w), radius, guard_px=getattr(padding, "guard_px", None)).size
    try:
        band_sizes(0.0, radius * grid / w, sensor_size=grid)
    except ValueError as exc:
        where = f" ({radius * grid / w:.4g} px on the {grid}-px grid they are recovered on)" if grid != w else ""
        raise InputError(f"{captures_path}: /geometry pupil_radius_px is {radius:.4g} on the {w}-px images{where}: "
                         f"{exc}; the geometry does not belong to these images (re-run the stage that wrote the file)"
                         ) from None
    return grid


def _tiled_footprint(captures_path: Path, section, shape, geometry, truth) -> Footprint:
    """Client and per-worker memory, and disk (output plus the tile files), of a tiled reconstruction."""
    from cca_cli.workflows.cluster import cluster_settings
    from cca_cli.optics.fft import cpu_count

    k, h, w = (float(v) for v in shape)
    size = float(section.tiles.size_px)
    scale = size / w
    reach = float(np.max(np.abs(np.rint(geometry.spectrum_centres_yx_px)))) * scale if geometry.n_images else 0.0
    radius = geometry.pupil_radius_px * scale
    padded = _fft_size(size + 2 * max(8.0, math.ceil(2.0 * size / max(radius, 1e-9))))
    lowres, hires, box = _grids(reach * padded / size, radius * padded / size, padded)
    per_tile = reconstruction_memory_bytes(k, padded, lowres, hires, box) + 2 * k * padded * padded * _FLOAT
    q = max(1.0, math.ceil(hires / padded))
    side = max(h, w)
    frame_object = q * q * h * w * _COMPLEX
    client = 3 * frame_object + 2 * (q * side) ** 2 * _COMPLEX + h * w * _FLOAT
    settings = cluster_settings()
    from cca_cli.workflows.tiled import local_tile_workers

    # device auto is counted as the CPU's worker per core: the most it may start
    local_workers = 0 if settings.scheduler else (local_tile_workers(settings.workers, None, section.device)
                                                  or cpu_count())
    memory = client + local_workers * per_tile
    disk = 2 * frame_object + (q * side) ** 2 * _COMPLEX + 2 * frame_object + float(truth[0]) * truth[1] * _COMPLEX
    return Footprint("reconstruct", memory, disk,
                     f"{k:.4g} images of {w:.4g} x {h:.4g} px in tiles of {size:.4g}² px ({local_workers} local "
                     f"workers, {size_text(per_tile)} each), object {q * w:.4g} x {q * h:.4g} px",
                     "use fewer local workers (--workers) or smaller tiles (reconstruct.tiles.size_px)")


def report_footprint(recon_path: Path) -> Footprint:
    """Memory of ``cca report`` on a recon file (its grids, baselines and figures)."""
    from cca_cli.io.h5 import open_input

    with open_input(recon_path, stage="reconstruct") as handle:
        sizes = [_shape(handle, "/recon/object")]
        if "/truth/object" in handle:
            sizes.append(_shape(handle, "/truth/object"))
    pixels = max(float(np.prod(s, dtype=np.float64)) for s in sizes)
    return Footprint("report", 24 * pixels * _COMPLEX, _REPORT_FILES_BYTES, f"object {pixels:.4g} px",
                     "report a smaller reconstruction")


def _about(n: float) -> str:
    return f"about {size_text(n)}" if math.isfinite(n) else size_text(n)


def _free_disk(path: Path) -> float:
    here = Path(path).absolute()
    while not here.exists() and here != here.parent:
        here = here.parent
    try:
        return float(shutil.disk_usage(here).free)
    except OSError:
        return math.inf


def check_footprint(footprint: Footprint, output: Path, *, source: str | Path | None = None) -> None:
    """Refuse a stage that needs more memory or disk than there is; announce a large write.

    Parameters
    ----------
    footprint : Footprint
    output : Path
        Where the stage writes (its disk is checked).
    source : str or Path, optional
        The config or input file the sizes come from, named in the message.

    Raises
    ------
    ResourceError
        One line with the estimate, what is available and what to change.
    """
    where = f"{source}: " if source else ""
    available = memory_available()
    if not footprint.memory_bytes <= available:
        raise ResourceError(
            f"{where}{footprint.stage} needs {_about(footprint.memory_bytes)} of memory "
            f"({footprint.detail}) but {size_text(available)} is available; {footprint.fix}")
    free = _free_disk(output)
    if not footprint.disk_bytes <= free:
        raise ResourceError(
            f"{output}: {footprint.stage} will write {_about(footprint.disk_bytes)} ({footprint.detail}) "
            f"but the disk has {size_text(free)} free; free some space, write elsewhere or {footprint.fix}")
    if footprint.disk_bytes > LARGE_WRITE_BYTES:
        log.warning("%s will write about %s to %s (%s)", footprint.stage, size_text(footprint.disk_bytes), output,
                    footprint.detail)
