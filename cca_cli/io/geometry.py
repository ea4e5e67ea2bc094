"""Read and write :class:`~cca_cli.sampling.geometry.CaptureGeometry` as the /geometry group."""

from __future__ import annotations

import h5py
import numpy as np

from cca_cli.errors import InputError, short
from cca_cli.io.h5 import write_dataset
from cca_cli.io.schema import GEOMETRY_ATTRS
from cca_cli.sampling.geometry import CaptureGeometry

__all__ = ["write_geometry", "read_geometry"]

_SCALARS = ("wavelength_m", "focal_length_m", "aperture_diameter_m", "pixel_pitch_m", "distance_m",
            "field_width_m", "pupil_radius_px", "overlap")
_ARRAYS = ("aperture_centres_yx_m", "spectrum_centres_yx_px", "grid_indices")


def write_geometry(handle: h5py.File, geometry: CaptureGeometry) -> None:
    """Write ``geometry`` under /geometry with SI units as attributes."""
    group = handle.require_group("geometry")
    for name in _SCALARS:
        group.attrs[name] = float(getattr(geometry, name))
    group.attrs["centre_index"] = geometry.centre_index
    group.attrs["synthetic_aperture_ratio"] = geometry.synthetic_aperture_ratio
    group.attrs["kind"] = geometry.kind
    group.attrs["numerical_aperture"] = float(geometry.numerical_aperture)
    group.attrs["units"] = ", ".join(f"{k}: {v}" for k, v in GEOMETRY_ATTRS.items())
    for name in _ARRAYS:
        write_dataset(group, name, getattr(geometry, name))
    if geometry.camera_index is not None:
        write_dataset(group, "camera_index", np.asarray(geometry.camera_index, np.int32))
    if np.isfinite(geometry.defocus_m):
        group.attrs["defocus_m"] = float(geometry.defocus_m)
    if np.isfinite(geometry.led_distance_m):
        group.attrs["led_distance_m"] = float(geometry.led_distance_m)


def read_geometry(handle: h5py.File) -> CaptureGeometry:
    """Read /geometry; a missing or malformed group raises a one-line InputError."""
    if "geometry" not in handle:
        raise InputError(f"{handle.filename}: no /geometry group; the file was not written by cca simulate/ingest")
    group = handle["geometry"]
    if not isinstance(group, h5py.Group):
        raise InputError(f"{handle.filename}: /geometry is not a group; the file was not written by cca")
    values = {}
    for name in _SCALARS:
        if name not in group.attrs:
            raise InputError(f"{handle.filename}: /geometry lacks {name}; the file is incomplete")
        try:
            values[name] = float(group.attrs[name])
        except (TypeError, ValueError):
            raise InputError(f"{handle.filename}: /geometry attribute {name} is {short(group.attrs[name])}, "
                             "expected a number") from None
        if name != "overlap" and not (values[name] > 0 and np.isfinite(values[name])):
            raise InputError(f"{handle.filename}: /geometry attribute {name} is {values[name]}, expected a "
                             "positive number (pupil radius, optics)")
    arrays = {}
    for name in _ARRAYS:
        if name not in group or not isinstance(group[name], h5py.Dataset):
            raise InputError(f"{handle.filename}: /geometry lacks {name}; the file is incomplete")
        arrays[name] = np.asarray(group[name])
        if arrays[name].dtype.kind not in "biuf" or not np.isfinite(arrays[name]).all():
            raise InputError(f"{handle.filename}: /geometry/{name} holds NaN, Inf or non-numbers; the file is "
                             "damaged — re-run the stage that wrote it")
    kind = group.attrs.get("kind", "camera_scan")
    values["kind"] = kind.decode(errors="replace") if isinstance(kind, bytes) else str(kind)
    try:
        values["numerical_aperture"] = float(group.attrs.get("numerical_aperture", float("nan")))
    except (TypeError, ValueError):
        values["numerical_aperture"] = float("nan")
    k = arrays["spectrum_centres_yx_px"].shape[0]
    for name, arr in arrays.items():
        if arr.shape != (k, 2):
            raise InputError(f"{handle.filename}: /geometry/{name} has shape {arr.shape}, expected ({k}, 2)")
    values["defocus_m"] = float(group.attrs.get("defocus_m", float("nan")))
    values["led_distance_m"] = float(group.attrs.get("led_distance_m", float("nan")))
    if not (np.isnan(values["led_distance_m"]) or values["led_distance_m"] > 0):
        raise InputError(f"{handle.filename}: /geometry attribute led_distance_m is {values['led_distance_m']}, "
                         "expected a positive distance (m)")
    if "camera_index" in group:
        cameras = np.asarray(group["camera_index"])
        if cameras.shape != (k,) or cameras.dtype.kind not in "iu" or (k and cameras.min() < 0):
            raise InputError(f"{handle.filename}: /geometry/camera_index must hold one camera number ≥ 0 per capture")
        arrays["camera_index"] = cameras.astype(np.int32)
    return CaptureGeometry(**values, **arrays)
