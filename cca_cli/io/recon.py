"""recon.h5: a :class:`~cca_cli.library.data.Reconstruction` written and read back, the one place that does.

The stage, tiled runs, multiplexed runs and the Python interface write it with
:func:`write_recon`; the report, ``cca export`` and :func:`cca_cli.api.load`
read it with :func:`read_recon`. Every dataset path is :mod:`cca_cli.io.schema`'s.

A tiled reconstruction is a Reconstruction of the blended frame (on a square
grid, ``q`` samples per frame pixel, /recon/region_px marking the frame when it
is not square) plus a :class:`TilesRecord`: the box of every tile, its
residuals, iterations and time, its pupil(s) and their Zernike coefficients.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cca_cli.engines.base import History
from cca_cli.engines.calibrator import Calibration
from cca_cli.engines.fit import FitReport
from cca_cli.errors import InputError
from cca_cli.io.capture_info import read_capture_summary
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, open_input, read_finite, require, require_attr, write_dataset
from cca_cli.io.multiplex import read_multiplex
from cca_cli.io.schema import OBJECT, OBSERVED, RECON_INTENSITY, REGION, SPECTRUM
from cca_cli.library.data import Reconstruction
from cca_cli.library.recovery import calibrated_pupils
from cca_cli.optics import fft
from cca_cli.optics.zernike import zernike_name
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.region import RegionEmbedding

__all__ = ["TilesRecord", "ReconFile", "write_recon", "read_recon", "read_spectrum"]

_RESIDUALS = ("all", "bright_field", "dark_field")


@dataclass(frozen=True)
class TilesRecord:
    """Every tile of a tiled reconstruction (tiles in the frame's row order).

    Attributes
    ----------
    box_px : ndarray, int32, (T, 4)
        ``[y0, x0, height, width]`` in frame pixels.
    grid_index : ndarray, int32, (T, 2)
    residual : ndarray, float64, (T, 3)
        Amplitude residual over all, bright-field and dark-field captures.
    iterations, seconds, shift_px : ndarray
    pupil : ndarray, complex64, (T, P, b, b) or None
    zernike_waves : ndarray, (T, P, n_modes) or None
    zernike_modes : ndarray, int32, (n_modes, 2) or None
    attrs : dict
        ``size_px``, ``overlap_px``, ``rows``, ``cols``, ``upsampling``, ``ran`` and ``pupil``.
    """

    box_px: np.ndarray
    grid_index: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    seconds: np.ndarray
    shift_px: np.ndarray
    pupil: np.ndarray | None
    zernike_waves: np.ndarray | None
    zernike_modes: np.ndarray | None
    attrs: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ReconFile:
    """What :func:`read_recon` finds in a recon.h5, as plain data.

    Attributes
    ----------
    result : Reconstruction
        With ``pupil``, ``positions_px`` and ``fit`` (the residuals per capture and over each set) as the
        file has them; ``calibration`` is not rebuilt (each capture's pupil is not kept): its parts are in
        ``calibration`` below.
    attrs : dict
        The attributes of /recon (``engine``, ``iterations``, ``seconds``, ``stopped_by``, the grid sizes,
        the residuals, ``dropped_captures``, …).
    calibration : dict or None
        Residuals per capture and over each set, pupils, Zernike coefficients, positions, brightness.
    tiles : dict or None
        /tiles of a tiled reconstruction.
    region_px : tuple or None
        ``(box on the recovery grid, box on the sensor grid, sensor grid side)`` of /recon/region_px.
    multiplex : MultiplexGeometry or None
        /multiplex of a multiplexed reconstruction.
    capture_summary : dict
        What ingest, hdr and register recorded (empty for simulations; :mod:`cca_cli.io.capture_info`).
    """

    result: Reconstruction
    attrs: dict
    calibration: dict | None
    tiles: dict | None
    region_px: tuple | None
    multiplex: object | None = None
    capture_summary: dict = field(default_factory=dict)


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


# ------------------------------------------------------------------------------------------------------------ write
def write_recon(path: Path, result: Reconstruction, provenance: Provenance, *, force: bool = False, extra=None,
                tiles: TilesRecord | None = None) -> None:
    """Write ``recon.h5`` atomically: the recovery, its history, the centre capture, truth, geometry and calibration.

    Parameters
    ----------
    path : Path
    result : Reconstruction
        ``object`` and ``observed`` are written as they are (the region, for a padded recovery);
        ``region`` places them on the grid.
    provenance : Provenance
    force : bool
        Replace an existing output (one cca wrote).
    extra : callable, optional
        ``extra(handle)`` writes further groups (registration records of the captures, /multiplex).
    tiles : TilesRecord, optional
        The tiles of a tiled reconstruction (/tiles).
    """
    units = result.units   # recorded captures: counts/s instead of the simulation's irradiance
    obj = result.object
    observed = result.observed if result.observed is not None else np.abs(obj) ** 2
    with atomic_h5(path, provenance, force=force) as handle:
        write_dataset(handle, SPECTRUM, result.spectrum, units=units and f"√({units}) · px")
        write_dataset(handle, OBJECT, obj, units=units and f"√({units})")
        write_dataset(handle, RECON_INTENSITY, (np.abs(obj) ** 2).astype(np.float32), units=units)
        columns = result.history.keys()
        for name in columns:
            described = {} if tiles is None else {"description": f"Median over the tiles of the {name} per "
                                                                 "iteration (seconds: the longest tile's); a tile "
                                                                 "that stopped earlier holds its last value."}
            write_dataset(handle, f"/history/{name}", result.history.array(name), **described)
        write_dataset(handle, OBSERVED, np.asarray(observed, np.float32), units=units)
        for name, data in result.truth.items():
            write_dataset(handle, f"/truth/{name}", data)
        write_geometry(handle, result.geometry)
        if result.region is not None:
            _write_region(handle, result.region, result.hires_size)
        if result.fit is not None:
            _write_fit(handle, result.fit)
        if result.calibration is not None:
            _write_calibration(handle, result.calibration, result.geometry)
        if tiles is not None:
            _write_tiles(handle, tiles)
        if extra is not None:
            extra(handle)
        recon = handle["recon"]
        recon.attrs["engine"] = result.engine
        recon.attrs["engine_options"] = json.dumps(result.options)
        recon.attrs["iterations"] = result.history.iterations
        recon.attrs["stopped_by"] = result.stopped_by
        recon.attrs["seconds"] = result.seconds
        recon.attrs["hires_size"] = result.hires_size
        recon.attrs["lowres_size"] = result.band_grid_px
        recon.attrs["pixel_pitch_object_m"] = result.pixel_size_m
        recon.attrs["fft_backend"] = fft.backend_name()
        recon.attrs["device"] = result.device
        if result.dropped:
            recon.attrs["dropped_captures"] = np.asarray(result.dropped, np.int32)
        if result.held_back:
            write_dataset(handle, "/recon/held_back_captures", np.asarray(result.held_back, np.int32))
            recon.attrs["residual_held_back"] = float(np.nanmin(result.history["held_back"]))
        if tiles is not None:
            for j, name in enumerate(_RESIDUALS):
                values = tiles.residual[:, j][np.isfinite(tiles.residual[:, j])]
                if values.size:
                    recon.attrs[f"residual_{name}_tile_median"] = float(np.median(values))


def _write_region(handle, region: RegionEmbedding, hires_size: int) -> None:
    y0, x0, hh, ww = region.hires_box(hires_size)
    oy, ox = region.offset_yx
    write_dataset(handle, REGION, np.array([[y0, x0, hh, ww], [oy, ox, *region.shape]], np.int32),
                  guard_px=region.guard_px, apodize_px=region.apodize_px, sensor_grid_px=region.size)


def _read_fit(handle) -> FitReport | None:
    """The residuals :func:`_write_fit` wrote (None where the file has none)."""
    recon = handle["recon"]
    if "/recon/residual_per_image" not in handle or "/calibration/bright_field" not in handle \
            or any(f"residual_{name}" not in recon.attrs for name in _RESIDUALS):
        return None
    values = {name: float(recon.attrs[f"residual_{name}"]) for name in _RESIDUALS}
    plain = {f"{name}_without_brightness": float(recon.attrs.get(f"residual_{name}_without_brightness", values[name]))
             for name in _RESIDUALS}
    return FitReport(per_image=np.asarray(handle["/recon/residual_per_image"], np.float64), **values, **plain,
                     bright_field_mask=np.asarray(handle["/calibration/bright_field"], bool))


def _write_fit(handle, fit: FitReport) -> None:
    """The residuals of the final model: per capture, and over all / bright-field / dark-field captures."""
    write_dataset(handle, "/recon/residual_per_image", fit.per_image)
    write_dataset(handle, "/calibration/bright_field", fit.bright_field_mask)
    recon = handle["recon"]
    for name in _RESIDUALS:
        recon.attrs[f"residual_{name}"] = getattr(fit, name)
        recon.attrs[f"residual_{name}_without_brightness"] = getattr(fit, f"{name}_without_brightness")


def _write_calibration(handle, calibration: Calibration, geometry: CaptureGeometry) -> None:
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
    if calibration.background is not None:
        write_dataset(handle, "/calibration/background", np.asarray(calibration.background, np.float64))
    if calibration.position_model is not None:
        group.attrs["position_model"] = calibration.position_model
        group.attrs["position_parameters"] = json.dumps(calibration.position_parameters)


def _write_tiles(handle, tiles: TilesRecord) -> None:
    """The /tiles group: boxes, residuals, iterations and times, pupils and Zernike coefficients per tile."""
    write_dataset(handle, "/tiles/box_px", np.asarray(tiles.box_px, np.int32))
    write_dataset(handle, "/tiles/grid_index", np.asarray(tiles.grid_index, np.int32))
    write_dataset(handle, "/tiles/residual", np.asarray(tiles.residual, np.float64))
    write_dataset(handle, "/tiles/iterations", np.asarray(tiles.iterations, np.int32))
    write_dataset(handle, "/tiles/seconds", np.asarray(tiles.seconds, np.float64))
    write_dataset(handle, "/tiles/shift_px", np.asarray(tiles.shift_px, np.float64))
    if tiles.pupil is not None:
        write_dataset(handle, "/tiles/pupil", np.asarray(tiles.pupil, np.complex64))
    if tiles.zernike_waves is not None:
        write_dataset(handle, "/tiles/zernike_waves", np.asarray(tiles.zernike_waves, np.float64))
        write_dataset(handle, "/tiles/zernike_modes", np.asarray(tiles.zernike_modes, np.int32))
    handle["tiles"].attrs.update(tiles.attrs)


# ------------------------------------------------------------------------------------------------------------- read
def read_recon(path: Path) -> ReconFile:
    """Read a recon.h5 (checked: finite arrays, the datasets and attributes every recon.h5 has).

    Raises
    ------
    InputError
        One line naming the file and what is missing or wrong.
    """
    with open_input(path, stage="reconstruct") as handle:
        geometry = read_geometry(handle)
        spectrum = read_finite(handle, SPECTRUM, ndim=2)
        obj = read_finite(handle, OBJECT, ndim=2)
        read_finite(handle, RECON_INTENSITY, ndim=2, dtype=np.float32)   # checked: what export and viewers read
        observed = read_finite(handle, OBSERVED, ndim=2, dtype=np.float32)
        columns = {name: np.asarray(require(handle, f"/history/{name}", ndim=1)) for name in History.COLUMNS}
        columns.update({name: np.asarray(handle[f"/history/{name}"]) for name in History.OPTIONAL
                        if f"/history/{name}" in handle})
        held_back = (tuple(int(i) for i in handle["/recon/held_back_captures"][()])
                     if "/recon/held_back_captures" in handle else ())
        recon = require(handle, SPECTRUM).parent
        attrs = dict(recon.attrs)
        attrs.update(engine=require_attr(recon, "engine", str), iterations=require_attr(recon, "iterations", int),
                     seconds=require_attr(recon, "seconds", float), hires_size=require_attr(recon, "hires_size", int),
                     lowres_size=require_attr(recon, "lowres_size", int))
        units = _text(handle[OBSERVED].attrs.get("units", ""))
        truth = {name: np.asarray(handle["truth"][name]) for name in handle["truth"]} if "truth" in handle else {}
        region_px = _read_region_px(handle)
        margins = dict(handle[REGION].attrs) if REGION in handle else {}
        calibration = _read_calibration(handle, geometry)
        tiles = _read_tiles(handle)
        multiplex = read_multiplex(handle) if "multiplex" in handle else None
        capture_summary = read_capture_summary(handle)
        fit = _read_fit(handle)
        pupil = np.asarray(handle["/calibration/pupil"]) if "/calibration/pupil" in handle else None
        positions = (np.asarray(handle["/calibration/spectrum_centres_yx_px"])
                     if "/calibration/spectrum_centres_yx_px" in handle else None)
    if spectrum.shape[0] != spectrum.shape[1]:
        raise InputError(f"{path}: {SPECTRUM} has shape {spectrum.shape}, expected a square image")
    region = None
    if region_px is not None and region_px[2]:
        (_, _, _, _), (oy, ox, rows, cols), size = region_px
        region = RegionEmbedding(size=size, offset_yx=(oy, ox), shape=(rows, cols),
                                 guard_px=int(margins.get("guard_px", 0)), apodize_px=int(margins.get("apodize_px", 0)))
    dropped = tuple(int(i) for i in np.atleast_1d(attrs.get("dropped_captures", ())))
    result = Reconstruction(
        object=obj, spectrum=spectrum, history=History.from_columns(columns), geometry=geometry,
        engine=str(attrs["engine"]), options=json.loads(_text(attrs.get("engine_options", "{}"))),
        seconds=float(attrs["seconds"]), stopped_by=_text(attrs.get("stopped_by", "")), observed=observed,
        truth=truth, units=None if units in ("", "irradiance") else units, band_grid_px=int(attrs["lowres_size"]),
        pupil=pupil, positions_px=positions, region=region, dropped=dropped, held_back=held_back,
        device=_text(attrs.get("device", "cpu")), fit=fit)
    return ReconFile(result=result, attrs=attrs, calibration=calibration, tiles=tiles, region_px=region_px,
                     multiplex=multiplex, capture_summary=capture_summary)


def read_spectrum(path: Path) -> tuple[np.ndarray, dict]:
    """/recon/spectrum of a recon.h5 and the attributes of /recon (a one-line InputError otherwise)."""
    with open_input(path) as handle:
        if SPECTRUM not in handle:
            raise InputError(f"{path}: has no {SPECTRUM}; give a recon.h5 written by cca reconstruct")
        spectrum = np.asarray(handle[SPECTRUM])
        attrs = dict(handle["recon"].attrs)
    if spectrum.ndim != 2 or spectrum.shape[0] != spectrum.shape[1] or not np.iscomplexobj(spectrum) \
            or not np.isfinite(spectrum).all():
        raise InputError(f"{path}: {SPECTRUM} is not a finite complex (M, M) array")
    return spectrum.astype(np.complex64), attrs


def _read_region_px(handle) -> tuple | None:
    """/recon/region_px: the recovered box on the recovery grid, the frames' box on the sensor grid, its size."""
    if REGION not in handle:
        return None
    dataset = handle[REGION]
    return (tuple(int(v) for v in dataset[0]), tuple(int(v) for v in dataset[1]),
            int(dataset.attrs.get("sensor_grid_px", 0)))


def _read_calibration(handle, geometry: CaptureGeometry) -> dict | None:
    """What recon.h5 says about the final model: residuals per capture, pupils, positions, brightness."""
    if "/recon/residual_per_image" not in handle:
        return None
    attrs = handle["recon"].attrs
    out = {
        "nominal_px": np.asarray(geometry.spectrum_centres_yx_px),
        "refined_px": (np.asarray(handle["/calibration/spectrum_centres_yx_px"])
                       if "/calibration/spectrum_centres_yx_px" in handle else np.asarray(geometry.spectrum_centres_yx_px)),
        "radius_px": geometry.pupil_radius_px,
        "bright_field": np.asarray(handle["/calibration/bright_field"]),
        "residual_per_image": np.asarray(handle["/recon/residual_per_image"]),
        "totals": {name: float(attrs[f"residual_{name}"]) for name in _RESIDUALS if f"residual_{name}" in attrs},
        "totals_without_brightness": {name: float(attrs[f"residual_{name}_without_brightness"])
                                      for name in _RESIDUALS if f"residual_{name}_without_brightness" in attrs},
        "brightness": np.asarray(handle["/calibration/brightness"]) if "/calibration/brightness" in handle else None,
        "pupil": np.asarray(handle["/calibration/pupil"]) if "/calibration/pupil" in handle else None,
        "pixels_per_sine": (geometry.field_width_m / geometry.wavelength_m) if geometry.kind == "led_array" else None,
    }
    if geometry.camera_index is not None:   # the lab's camera numbers, in the order of the pupils
        out["camera_ids"] = [int(v) for v in np.unique(np.asarray(geometry.camera_index))]
    group = handle["calibration"] if "calibration" in handle else None
    if group is not None and "/calibration/zernike_waves" in handle:
        waves = np.asarray(handle["/calibration/zernike_waves"])
        modes = [tuple(int(v) for v in mode) for mode in np.asarray(handle["/calibration/zernike_modes"])]
        out["zernike"] = {zernike_name(*mode): float(waves[0, j]) for j, mode in enumerate(modes)}
        out["zernike_per_pupil"] = waves
        out["pupil_model"] = _text(group.attrs.get("pupil_model", ""))
    if group is not None and "position_model" in group.attrs:
        out["position_model"] = _text(group.attrs["position_model"])
        out["position_parameters"] = json.loads(_text(group.attrs["position_parameters"]))
    return out


def _read_tiles(handle) -> dict | None:
    """/tiles of a tiled reconstruction: boxes, residuals and (first pupil's) Zernike coefficients per tile."""
    if "/tiles/box_px" not in handle:
        return None
    group = handle["tiles"]
    out = {"box_px": np.asarray(group["box_px"]), "residual": np.asarray(group["residual"])[:, 0],
           "iterations": np.asarray(group["iterations"]), "seconds": np.asarray(group["seconds"]),
           "attrs": {k: (v.item() if hasattr(v, "item") else _text(v)) for k, v in group.attrs.items()}}
    if "zernike_waves" in group:
        out["zernike_waves"] = np.asarray(group["zernike_waves"])[:, 0, :]
        out["zernike_names"] = [zernike_name(*(int(v) for v in mode)) for mode in np.asarray(group["zernike_modes"])]
    return out
