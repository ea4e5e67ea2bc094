"""recon.h5 of a tiled reconstruction: the blended object, and every tile's box, pupil and residuals.

The file reads like any recon.h5 (the report needs nothing else): the blended
object is placed on a square grid (``q`` samples per frame pixel, the frame
centred, /recon/region_px marking it when the frame is not square) whose
spectrum is /recon/spectrum. On top of that it holds /tiles: the box of every
tile in frame pixels, its residuals, iterations and time, its pupil(s) and
their Zernike coefficients, so the report can map the aberration across the field.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from cca_cli.engines.base import History, IterationRecord
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, open_input, write_dataset
from cca_cli.io.measurements import INTENSITY
from cca_cli.optics import fft
from cca_cli.sampling.capture import with_field_width

__all__ = ["combined_history", "write_tiled_recon"]


def combined_history(results) -> History:
    """One history for the tiles: per iteration the median residual and change over the tiles.

    A tile that stopped earlier holds its last values; ``seconds`` is the longest tile's time so far.
    """
    histories = [r.history for r in results if r.history and len(r.history.get("residual", ())) > 0]
    if not histories:
        return History()
    n = max(len(h["residual"]) for h in histories)

    def column(name: str) -> np.ndarray:
        return np.stack([np.concatenate([h[name], np.full(n - len(h[name]), h[name][-1])]) for h in histories])

    residual, change, seconds = column("residual"), column("change"), column("seconds")
    return History([IterationRecord(i + 1, float(np.median(residual[:, i])), float(np.median(change[:, i])),
                                    float(np.max(seconds[:, i]))) for i in range(n)])


def write_tiled_recon(path: Path, tiled, provenance: Provenance, *, force: bool = False, extra=None) -> None:
    """Write the recon.h5 of a :class:`~cca_cli.workflows.tiled.TiledRecovery` atomically.

    Parameters
    ----------
    path : Path
    tiled : TiledRecovery
    provenance : Provenance
    force : bool
        Replace an existing output (one cca wrote).
    extra : callable, optional
        ``extra(handle)`` writes further groups (registration records of the captures).
    """
    plan = tiled.plan
    h, w = plan.frame.frame_shape
    q = plan.upsampling
    side = max(h, w)
    grid = q * side
    oy, ox = (side - h) // 2, (side - w) // 2
    square = np.zeros((grid, grid), np.complex64)
    square[oy * q:(oy + h) * q, ox * q:(ox + w) * q] = tiled.object
    spectrum = fft.fft2c(square).astype(np.complex64)
    del square
    geometry = with_field_width(plan.geometry, plan.geometry.field_width_m * side / w)
    units = plan.frame.units
    with open_input(plan.captures_path) as source:
        observed = np.asarray(source[INTENSITY][geometry.centre_index], np.float32)
        truth = {name: np.asarray(source["truth"][name]) for name in source["truth"]} if "truth" in source else {}
    results = tiled.results
    history = combined_history(results)
    with atomic_h5(path, provenance, force=force) as handle:
        write_dataset(handle, "/recon/spectrum", spectrum, units=units and f"√({units}) · px")
        write_dataset(handle, "/recon/object", tiled.object, units=units and f"√({units})")
        write_dataset(handle, "/recon/intensity", (np.abs(tiled.object) ** 2).astype(np.float32), units=units)
        for name in ("residual", "change", "seconds"):
            write_dataset(handle, f"/history/{name}", history.array(name),
                          description=f"Median over the tiles of the {name} per iteration (seconds: the longest "
                                      "tile's); a tile that stopped earlier holds its last value.")
        write_dataset(handle, "/observed/centre", observed, units=units)
        for name, data in truth.items():
            write_dataset(handle, f"/truth/{name}", data)
        write_geometry(handle, replace(geometry, pixel_pitch_m=plan.geometry.pixel_pitch_m))
        if (h, w) != (side, side):
            write_dataset(handle, "/recon/region_px", np.array([[oy * q, ox * q, h * q, w * q], [oy, ox, h, w]],
                                                              np.int32),
                          guard_px=0, apodize_px=0, sensor_grid_px=side)
        _write_tiles(handle, tiled)
        if extra is not None:
            extra(handle)
        recon = handle["recon"]
        recon.attrs["engine"] = tiled.engine
        recon.attrs["engine_options"] = json.dumps(tiled.options)
        recon.attrs["iterations"] = history.iterations
        recon.attrs["stopped_by"] = tiled.stopped_by
        recon.attrs["seconds"] = tiled.seconds
        recon.attrs["hires_size"] = grid
        recon.attrs["lowres_size"] = side
        recon.attrs["pixel_pitch_object_m"] = geometry.field_width_m / grid
        recon.attrs["fft_backend"] = fft.backend_name()
        for name in ("all", "bright_field", "dark_field"):
            values = [r.residual.get(name) for r in results if r.residual.get(name) is not None]
            values = [v for v in values if np.isfinite(v)]
            if values:
                recon.attrs[f"residual_{name}_tile_median"] = float(np.median(values))


def _write_tiles(handle, tiled) -> None:
    """The /tiles group: boxes, residuals, iterations and times, pupils and Zernike coefficients per tile."""
    plan, results = tiled.plan, tiled.results
    write_dataset(handle, "/tiles/box_px", np.array([r.box for r in results], np.int32))
    write_dataset(handle, "/tiles/grid_index", np.array([[r.row, r.col] for r in results], np.int32))
    write_dataset(handle, "/tiles/residual", np.array([[r.residual.get(n, np.nan) for n in
                                                        ("all", "bright_field", "dark_field")] for r in results],
                                                      np.float64))
    write_dataset(handle, "/tiles/iterations", np.array([r.iterations for r in results], np.int32))
    write_dataset(handle, "/tiles/seconds", np.array([r.seconds for r in results], np.float64))
    write_dataset(handle, "/tiles/shift_px", np.array([r.shift_px for r in results], np.float64))
    if all(r.pupil is not None for r in results):
        write_dataset(handle, "/tiles/pupil", np.stack([r.pupil for r in results]).astype(np.complex64))
    if all(r.zernike_waves is not None for r in results):
        write_dataset(handle, "/tiles/zernike_waves", np.stack([np.atleast_2d(r.zernike_waves) for r in results]))
        write_dataset(handle, "/tiles/zernike_modes", np.asarray(results[0].zernike_modes, np.int32))
    group = handle["tiles"]
    group.attrs.update(size_px=plan.tiles.size, overlap_px=plan.tiles.overlap, rows=plan.tiles.grid_shape[0],
                       cols=plan.tiles.grid_shape[1], upsampling=plan.upsampling, ran=tiled.ran,
                       pupil=tiled.pupil_mode)
