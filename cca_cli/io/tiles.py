"""Files of a tiled reconstruction: one tile's captures read from captures.h5, and one tile's result.

A worker reads only its tile's pixels of every capture (an HDF5 hyperslab), so
its memory follows the tile, not the frame. Each finished tile is written as
its own cca HDF5 file ``<output>.tiles/tile_RRR_CCC.h5`` (temporary file +
rename), holding the tile's blended-grid object, its pupil(s), Zernike
coefficients, residuals and history, and the fingerprint of the inputs and
options it belongs to; a run that is started again reads the matching files and
recovers only the tiles that have none.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError
from cca_cli.io.captures import BOUNDARY_OPEN, read_frame_scale
from cca_cli.library.data import CaptureSet, constant_images
from cca_cli.io.geometry import read_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, open_input, require, write_dataset
from cca_cli.io.measurements import INTENSITY, WEIGHT
from cca_cli.io.outputs import is_cca_hdf5
from cca_cli.io.schema import spec_for

__all__ = ["FrameInfo", "read_frame_info", "read_frame_centre", "read_dead_frames", "read_tile_captures", "TileResult", "tile_folder",
           "tile_path", "write_tile_result", "read_tile_result", "tile_file_problem", "remove_tile_folder"]

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


@dataclass(frozen=True)
class FrameInfo:
    """What the client needs to plan tiles, read without loading any image."""

    n_images: int
    frame_shape: tuple[int, int]
    boundary: str
    units: str | None
    has_weight: bool
    frame_scale: str = "shared"


def read_frame_info(path: Path) -> FrameInfo:
    """Image count, frame shape, boundary, units and frame scale of a captures file's /measurements/intensity."""
    with open_input(path) as handle:
        dataset = require(handle, INTENSITY, ndim=3)
        k, h, w = dataset.shape
        boundary = dataset.attrs.get("boundary", "periodic" if h == w else BOUNDARY_OPEN)
        units = _text(dataset.attrs.get("units"))
        units = None if units in (None, "", spec_for(INTENSITY).units) else units
        has_weight = WEIGHT in handle
        frame_scale = read_frame_scale(dataset.attrs, path)
    return FrameInfo(int(k), (int(h), int(w)), _text(boundary), units, has_weight, frame_scale)


def read_frame_centre(path: Path, centre_index: int) -> tuple[np.ndarray, dict]:
    """The centre capture of a captures file (float32, the whole frame) and its truth (empty for recorded data)."""
    with open_input(path) as handle:
        observed = np.asarray(require(handle, INTENSITY, ndim=3)[centre_index], np.float32)
        truth = {name: np.asarray(handle["truth"][name]) for name in handle["truth"]} if "truth" in handle else {}
    return observed, truth


#: Bytes of images :func:`read_dead_frames` reads at a time.
_SCAN_BYTES = 64 << 20


def read_stray_light(path: Path) -> bool:
    """Whether an LED array's whole frames hold light under every dark-field image
    (:func:`cca_cli.library.stray_light.holds_stray_light`), read one dark-field frame at a time."""
    from cca_cli.io.geometry import read_geometry
    from cca_cli.io.measurements import WEIGHT
    from cca_cli.library.stray_light import holds_stray_light

    with open_input(path) as handle:
        geometry = read_geometry(handle)
        if geometry.kind != "led_array":
            return False
        weights = handle[WEIGHT] if WEIGHT in handle else None
        return holds_stray_light(require(handle, INTENSITY, ndim=3), geometry.spectrum_centres_yx_px,
                                 geometry.pupil_radius_px, weights)


def read_dead_frames(path: Path) -> tuple[np.ndarray, list[float]]:
    """The captures whose whole frame holds one value (dead: nothing was recorded), and those values.

    A tile may hold only dark pixels of a live capture, so whether a capture is dead is decided on
    its whole frame, here, once; the images are read a few at a time.

    Returns
    -------
    dead : ndarray of int64
        Their indices.
    values : list of float
        The value each holds.
    """
    with open_input(path) as handle:
        dataset = require(handle, INTENSITY, ndim=3)
        k, h, w = dataset.shape
        step = max(1, _SCAN_BYTES // max(1, h * w * dataset.dtype.itemsize))
        dead, values = [], []
        for start in range(0, k, step):
            block = np.asarray(dataset[start:start + step])
            constant = constant_images(block)
            dead.extend(int(start + i) for i in constant)
            values.extend(float(block[i].flat[0]) for i in constant)
    return np.asarray(dead, np.int64), values


def read_tile_captures(path: Path, box: tuple[int, int, int, int]) -> CaptureSet:
    """The captures of one tile: every image's ``(y0, x0, h, w)`` box, with the frame's geometry.

    The images are checked as :func:`~cca_cli.io.measurements.read_intensity` checks a whole
    stack, except that a tile may hold only dark pixels of some images. The boundary is always
    ``open``: a tile is a window on the scene.
    """
    y0, x0, h, w = box
    with open_input(path) as handle:
        dataset = require(handle, INTENSITY, ndim=3)
        if dataset.dtype.kind not in "biuf":
            raise InputError(f"{path}: {INTENSITY} holds {dataset.dtype} values, expected real numbers")
        intensity = np.asarray(dataset[:, y0:y0 + h, x0:x0 + w], dtype=np.float32)
        if intensity.shape[1:] != (h, w):
            raise InputError(f"{path}: {INTENSITY} is {dataset.shape[2]}x{dataset.shape[1]} px, too small for a "
                             f"tile at ({y0}, {x0}) of {w}x{h} px")
        weight = None
        if WEIGHT in handle:
            weight = np.asarray(handle[WEIGHT][:, y0:y0 + h, x0:x0 + w], dtype=np.float32)
            if not np.isfinite(weight).all() or weight.min() < 0 or weight.max() > 1:
                raise InputError(f"{path}: {WEIGHT} holds values outside [0, 1] (or NaN) in the tile at "
                                 f"({y0}, {x0}); weights are in [0, 1]")
        geometry = read_geometry(handle)
        units = _text(dataset.attrs.get("units"))
        units = None if units in (None, "", spec_for(INTENSITY).units) else units
        pupil = np.asarray(handle["/calibration/initial_pupil"]) if "/calibration/initial_pupil" in handle else None
        frame_scale = read_frame_scale(dataset.attrs, path)
    bad = ~np.isfinite(intensity).reshape(intensity.shape[0], -1).all(axis=1)
    if bad.any():
        raise InputError(f"{path}: image {int(np.argmax(bad))} of {INTENSITY} contains NaN or Inf in the tile at "
                         f"({y0}, {x0}); fix or mask it")
    return CaptureSet(intensity=intensity, weight=weight, geometry=geometry, truth={}, units=units,
                      boundary=BOUNDARY_OPEN, initial_pupil=pupil, frame_scale=frame_scale)


@dataclass(frozen=True)
class TileResult:
    """One recovered tile.

    Attributes
    ----------
    row, col : int
        Place in the tile grid.
    box : tuple of int
        ``(y0, x0, h, w)`` in frame pixels.
    object : ndarray, complex64, (q·h, q·w) or None
        The recovered field on the blend grid (``q`` samples per frame pixel);
        None in a summary passed between tasks.
    pupil : ndarray, complex64, (P, b, b) or None
        Recovered pupil(s) with the NA disc.
    zernike_waves : ndarray, float64, (P, n_modes) or None
    zernike_modes : list of (n, m)
    residual : dict
        ``all``, ``bright_field``, ``dark_field`` amplitude residuals.
    iterations, seconds, stopped_by, engine
        How the tile's recovery ran.
    history : dict of ndarray
        ``residual``, ``change``, ``seconds`` per iteration.
    shift_px : tuple of float
        Shift applied to register the tile to its centre capture (blend-grid px).
    fingerprint : str
    device : str
        Where the tile's engine ran (``cpu`` or ``cuda``).
    """

    row: int
    col: int
    box: tuple[int, int, int, int]
    object: np.ndarray | None
    pupil: np.ndarray | None
    zernike_waves: np.ndarray | None
    zernike_modes: list
    residual: dict
    iterations: int
    seconds: float
    stopped_by: str
    engine: str
    history: dict
    shift_px: tuple[float, float]
    fingerprint: str
    device: str = "cpu"

    def summary(self) -> "TileResult":
        """The same without the object (what a neighbour's task needs: small to send)."""
        from dataclasses import replace

        return replace(self, object=None)


def tile_folder(output: Path) -> Path:
    """``<output>.tiles`` beside the output."""
    output = Path(output)
    return output.with_name(output.name + ".tiles")


def tile_path(output: Path, row: int, col: int) -> Path:
    """The result file of tile (row, col)."""
    return tile_folder(output) / f"tile_{row:03d}_{col:03d}.h5"


def write_tile_result(path: Path, result: TileResult, provenance: Provenance) -> None:
    """Write one tile's result atomically (a file cca wrote before is replaced; anything else is refused)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_h5(path, provenance, force=path.exists() and is_cca_hdf5(path)) as handle:
        group = handle.create_group("tile")
        write_dataset(handle, "/tile/object", result.object, units="",
                      description="Recovered complex field of the tile on the blend grid (arbitrary global phase).")
        if result.pupil is not None:
            write_dataset(handle, "/tile/pupil", result.pupil, units="1",
                          description="Recovered pupil(s) of the tile on the pupil box, NA disc included.")
        if result.zernike_waves is not None:
            write_dataset(handle, "/tile/zernike_waves", result.zernike_waves, units="waves RMS",
                          description="Zernike coefficients of the tile's pupil phase, per pupil.")
        for name, values in result.history.items():
            write_dataset(handle, f"/tile/history/{name}", np.asarray(values, np.float64),
                          units="s" if name == "seconds" else "1",
                          description=f"The tile recovery's {name} per iteration.")
        group.attrs.update(row=result.row, col=result.col, box=np.asarray(result.box, np.int64),
                           zernike_modes=json.dumps([list(m) for m in result.zernike_modes]),
                           residual=json.dumps(result.residual), iterations=result.iterations,
                           seconds=result.seconds, stopped_by=result.stopped_by, engine=result.engine,
                           shift_px=np.asarray(result.shift_px, np.float64), fingerprint=result.fingerprint,
                           device=result.device)


def read_tile_result(path: Path, fingerprint: str | None = None, *, with_object: bool = True) -> TileResult | None:
    """The tile result at ``path``; None when there is none, it is not cca's, unreadable, or of other inputs."""
    if not path.is_file() or not is_cca_hdf5(path):
        return None
    try:
        with h5py.File(path, "r") as handle:
            group = handle["tile"]
            attrs = dict(group.attrs)
            if fingerprint is not None and _text(attrs["fingerprint"]) != fingerprint:
                return None
            history = {name: np.asarray(data) for name, data in group["history"].items()} if "history" in group else {}
            return TileResult(
                row=int(attrs["row"]), col=int(attrs["col"]), box=tuple(int(v) for v in attrs["box"]),
                object=np.asarray(group["object"]) if with_object else None,
                pupil=np.asarray(group["pupil"]) if "pupil" in group else None,
                zernike_waves=np.asarray(group["zernike_waves"]) if "zernike_waves" in group else None,
                zernike_modes=[tuple(m) for m in json.loads(_text(attrs["zernike_modes"]))],
                residual=json.loads(_text(attrs["residual"])), iterations=int(attrs["iterations"]),
                seconds=float(attrs["seconds"]), stopped_by=_text(attrs["stopped_by"]), engine=_text(attrs["engine"]),
                history=history, shift_px=tuple(float(v) for v in attrs["shift_px"]),
                fingerprint=_text(attrs["fingerprint"]), device=_text(attrs.get("device", "cpu")))
    except (OSError, KeyError, ValueError, TypeError):
        return None


def tile_file_problem(path: Path) -> tuple[str, str] | None:
    """What is wrong with the file at a tile's path, or None when there is none or it is a readable tile result.

    Returns
    -------
    (kind, why) or None
        ``kind`` is ``damaged`` for a file cca wrote that cannot be used (empty, or an HDF5 file that cannot
        be opened — truncated by a crash — or that lacks the tile's datasets: it may be replaced), or
        ``foreign`` for anything else (never replaced); ``why`` says what was found, for a message.
    """
    if not (path.exists() or path.is_symlink()):
        return None
    if path.is_symlink() or not path.is_file():
        return "foreign", "not a regular file"
    try:
        with open(path, "rb") as handle:
            start = handle.read(len(_HDF5_SIGNATURE))
    except OSError as exc:
        return "foreign", f"cannot be read ({exc.strerror})"
    if not start:
        return "damaged", "empty"
    if start != _HDF5_SIGNATURE:
        return "foreign", "not an HDF5 file"
    try:
        with h5py.File(path, "r") as handle:
            schema = handle.attrs.get("cca_schema")
            group = handle.get("tile")
            complete = isinstance(group, h5py.Group) and "object" in group and "fingerprint" in group.attrs
    except (OSError, ValueError, KeyError) as exc:
        return "damaged", f"it cannot be opened ({type(exc).__name__})"
    if not (isinstance(schema, (str, bytes)) and _text(schema).startswith("cca/")):
        return "foreign", "an HDF5 file cca did not write"
    if not complete:
        return "damaged", "it lacks the tile's datasets"
    return None


def remove_tile_folder(output: Path) -> None:
    """Remove the tile files cca wrote for ``output``, and their folder once empty (anything else stays)."""
    folder = tile_folder(output)
    if not folder.is_dir() or folder.is_symlink():
        return
    for path in folder.glob("tile_*.h5"):
        if path.is_file() and not path.is_symlink() and is_cca_hdf5(path):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
    with contextlib.suppress(OSError):
        folder.rmdir()


def _text(value) -> str | None:
    if value is None:
        return None
    return value.decode() if isinstance(value, bytes) else str(value)
