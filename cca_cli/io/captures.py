"""Captures files: measurements, geometry and truth read back; per-position labels and sensor records."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError
from cca_cli.hdr.calibration import DarkModel
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import atomic_h5, describe, open_input, write_dataset
from cca_cli.io.measurements import INTENSITY, WEIGHT, read_intensity, read_weight
from cca_cli.io.records import read_sensor_records
from cca_cli.io.schema import spec_for
from cca_cli.library.data import FRAME_SCALES, CaptureSet

__all__ = ["BOUNDARY_OPEN", "read_frame_scale", "read_measurements", "read_captures", "write_capture_set", "SensorCalibration",
           "read_sensor", "write_labels", "read_labels", "write_strings"]

#: /measurements attribute ``boundary`` of recorded images: a window on a larger scene (not periodic).
BOUNDARY_OPEN = "open"


def read_frame_scale(attrs, path: Path, dataset: str = INTENSITY) -> str:
    """How the images of a file were scaled: the ``frame_scale`` attribute of ``dataset``, checked.

    Parameters
    ----------
    attrs : h5py AttributeManager or mapping
        The dataset's attributes.
    path : Path
        The file (named in the error).
    dataset : str
        The dataset's name in the file (named in the error).

    Returns
    -------
    str
        ``shared`` (also when the attribute is absent) or ``per_frame``.

    Raises
    ------
    InputError
        Any other value; one line naming the file, the dataset and the fix.
    """
    value = attrs.get("frame_scale", "shared")
    value = value.decode() if isinstance(value, bytes) else str(value)
    if value not in FRAME_SCALES:
        raise InputError(f"{path}: {dataset} says frame_scale {value!r}; it must be 'shared' or 'per_frame': "
                         "set the attribute so (or re-run ingest, for a file it wrote)")
    return value


def read_measurements(handle, path: Path) -> CaptureSet:
    """/measurements, /geometry and /truth of an open captures file, checked except for the image count."""
    intensity = read_intensity(handle, path)
    units = handle["/measurements/intensity"].attrs.get("units")
    units = units.decode() if isinstance(units, bytes) else units
    units = None if units in (None, "", spec_for("/measurements/intensity").units) else str(units)
    geometry = read_geometry(handle)
    weight = read_weight(handle, path, intensity.shape)
    truth = {name: np.asarray(handle["truth"][name]) for name in handle["truth"]} if "truth" in handle else {}
    k, h, w = intensity.shape
    # Recorded frames say "open"; a file without the attribute is a window on a larger scene unless square.
    boundary = handle["/measurements/intensity"].attrs.get("boundary", "periodic" if h == w else "open")
    pupil = np.asarray(handle["/calibration/initial_pupil"]) if "/calibration/initial_pupil" in handle else None
    frame_scale = read_frame_scale(handle["/measurements/intensity"].attrs, path)
    return CaptureSet(intensity=intensity, weight=weight, geometry=geometry, truth=truth, units=units,
                      boundary=boundary.decode() if isinstance(boundary, bytes) else str(boundary), initial_pupil=pupil,
                      frame_scale=frame_scale)


def read_captures(path: Path) -> CaptureSet:
    """Read /measurements, /geometry and (if present) /truth of a captures file, checking shapes and values."""
    with open_input(path) as handle:
        captures = read_measurements(handle, Path(path))
    k = captures.intensity.shape[0]
    if k != captures.geometry.n_images:
        raise InputError(f"{path}: {k} images but /geometry describes {captures.geometry.n_images} positions")
    return captures


def write_capture_set(path: Path, captures: CaptureSet, provenance, *, force: bool = False) -> None:
    """Write ``captures`` as a captures file ``cca reconstruct`` reads (atomically)."""
    with atomic_h5(path, provenance, force=force) as handle:
        images = write_dataset(handle, INTENSITY, np.asarray(captures.intensity, np.float32), units=captures.units)
        images.attrs["boundary"] = captures.boundary
        if captures.frame_scale != "shared":
            images.attrs["frame_scale"] = captures.frame_scale
        if captures.initial_pupil is not None:
            write_dataset(handle, "/calibration/initial_pupil", np.asarray(captures.initial_pupil, np.complex64))
        if captures.weight is not None:
            write_dataset(handle, WEIGHT, np.asarray(captures.weight, np.float32))
        write_geometry(handle, captures.geometry)
        for name, value in captures.truth.items():
            write_dataset(handle, f"/truth/{name}", value)


@dataclass(frozen=True)
class SensorCalibration:
    """What the dark and flat frames (or the manifest) say about the sensor."""

    white_level: float | None          # clipping level of the decoded values (counts); None: float data
    black_level: float                 # scalar black level used where there are no dark frames (counts)
    darks: DarkModel | None = None
    gain: np.ndarray | None = None     # (H, W) relative gain, mean 1
    read_noise: float | None = None    # counts RMS
    electrons_per_count: float | None = None
    noise_source: str = ""

    def black_at(self, exposure_s: float) -> tuple[np.ndarray | float, str | None]:
        """Black level (per pixel with dark frames, else the scalar) at an exposure, and a note."""
        if self.darks is None:
            return self.black_level, None
        return self.darks.at(exposure_s)

    def saturation_at(self, exposure_s: float) -> np.ndarray | float | None:
        """Clipping level of a linearised frame at an exposure: ``(white − black) / gain`` (None: float data)."""
        if self.white_level is None:
            return None
        black, _ = self.black_at(exposure_s)
        level = np.float32(self.white_level) - np.asarray(black, np.float32)
        return level if self.gain is None else level / self.gain


def read_sensor(handle) -> SensorCalibration | None:
    """The sensor calibration stored by :func:`cca_cli.stages.ingest.write_raw` (None when the file has none)."""
    records = read_sensor_records(handle)
    if records is None:
        return None
    darks = None
    if records["black_maps"] is not None:
        darks = DarkModel(exposure_s=records["dark_exposure_s"], black=records["black_maps"])
    return SensorCalibration(white_level=records["white_level"], black_level=records["black_level"], darks=darks,
                             gain=records["gain_map"], read_noise=records["read_noise"],
                             electrons_per_count=records["electrons_per_count"],
                             noise_source=records["noise_source"])


def write_strings(handle: h5py.File, path: str, values: list[str]) -> h5py.Dataset:
    """Store a list of texts as a variable-length string dataset at ``path`` (described from the schema)."""
    return describe(handle.create_dataset(path, data=np.array(values, dtype=h5py.string_dtype())))


def write_labels(handle: h5py.File, labels: list[str]) -> None:
    """Store one readable name per position as /capture/labels."""
    write_strings(handle, "/capture/labels", labels)


def read_labels(handle: h5py.File, count: int) -> list[str]:
    """/capture/labels, or ``view k`` names when absent."""
    if "/capture/labels" in handle:
        return handle["/capture/labels"].asstr()[()].tolist()
    return [f"view {k}" for k in range(count)]
