"""What recorded captures carry from stage to stage in their HDF5 files: sensor calibration and capture records."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from cca_cli.io.h5 import write_dataset

__all__ = ["write_sensor_records", "read_sensor_records", "carry_capture_records"]


def write_sensor_records(handle: h5py.File, *, white_level: float | None, black_level: float,
                         dark_exposure_s: np.ndarray | None = None, black_maps: np.ndarray | None = None,
                         gain_map: np.ndarray | None = None, read_noise: float | None = None,
                         electrons_per_count: float | None = None, noise_source: str = "") -> None:
    """Write the /sensor group: attributes for the scalars, datasets for the dark levels and the gain map."""
    group = handle.require_group("sensor")
    if white_level is not None:
        group.attrs["white_level"] = float(white_level)
    group.attrs["black_level"] = float(black_level)
    if read_noise is not None:
        group.attrs["read_noise"] = float(read_noise)
    if electrons_per_count is not None:
        group.attrs["electrons_per_count"] = float(electrons_per_count)
    group.attrs["noise_source"] = noise_source
    if black_maps is not None:
        write_dataset(handle, "/sensor/black_level", black_maps)
        write_dataset(handle, "/sensor/dark_exposure_s", dark_exposure_s)
    if gain_map is not None:
        write_dataset(handle, "/sensor/gain_map", gain_map)


def read_sensor_records(handle: h5py.File) -> dict | None:
    """The /sensor group as a dict (keys of :func:`write_sensor_records`), or None when absent."""
    if "sensor" not in handle:
        return None
    group = handle["sensor"]
    attrs = group.attrs
    source = attrs.get("noise_source", "")
    return {
        "white_level": float(attrs["white_level"]) if "white_level" in attrs else None,
        "black_level": float(attrs.get("black_level", 0.0)),
        "dark_exposure_s": np.asarray(group["dark_exposure_s"], np.float64) if "dark_exposure_s" in group else None,
        "black_maps": np.asarray(group["black_level"], np.float32) if "black_level" in group else None,
        "gain_map": np.asarray(group["gain_map"], np.float32) if "gain_map" in group else None,
        "read_noise": float(attrs["read_noise"]) if "read_noise" in attrs else None,
        "electrons_per_count": float(attrs["electrons_per_count"]) if "electrons_per_count" in attrs else None,
        "noise_source": source.decode() if isinstance(source, bytes) else str(source),
    }


def carry_capture_records(source: h5py.File, target: h5py.File, *, keep=None) -> None:
    """Copy the records later stages need from one capture file to the next.

    The known defocus and LED distance (/geometry attributes ``defocus_m``, ``led_distance_m``; write /geometry
    first), the initial pupil (/calibration), the board pattern and board
    views (/registration/board*, only the views ``keep`` when given) and the
    sensor calibration (/sensor).
    """
    for name in ("defocus_m", "led_distance_m"):
        if "geometry" in source and name in source["geometry"].attrs and "geometry" in target:
            target["geometry"].attrs[name] = source["geometry"].attrs[name]
    for name in ("/calibration/initial_pupil", "/sensor"):
        if name in source and name not in target:
            parent = target.require_group(str(Path(name).parent))
            source.copy(source[name], parent, name=Path(name).name)
    if "registration/board" in source:
        board = target.require_group("registration/board")
        for key, value in source["registration/board"].attrs.items():
            board.attrs[key] = value
    if "/registration/board_views" in source and "/registration/board_views" not in target:
        views = source["/registration/board_views"]
        data = views[()] if keep is None else views[()][np.asarray(keep)]
        copy = target.create_dataset("/registration/board_views", data=data)
        for key, value in views.attrs.items():
            if key == "files" and keep is not None:   # each view's file names, one entry a view
                value = [value[i] for i in np.asarray(keep)]
            copy.attrs[key] = value
