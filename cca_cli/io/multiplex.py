"""Read and write :class:`~cca_cli.optics.multiplex.MultiplexGeometry` as the /multiplex group."""

from __future__ import annotations

import h5py
import numpy as np

from cca_cli.errors import InputError
from cca_cli.io.h5 import open_input, write_dataset
from cca_cli.optics.multiplex import MultiplexGeometry

__all__ = ["write_multiplex", "read_multiplex", "is_multiplexed_file"]


def write_multiplex(handle: h5py.File, geometry: MultiplexGeometry) -> None:
    """Write cameras, sources, patterns and the per-virtual-capture indices under /multiplex."""
    group = handle.require_group("multiplex")
    group.attrs["pupil_radius_px"] = float(geometry.pupil_radius_px)
    group.attrs["camera_shape"] = np.asarray(geometry.camera_shape, np.int32)
    group.attrs["source_shape"] = np.asarray(geometry.source_shape, np.int32)
    write_dataset(group, "camera_centres_px", geometry.camera_centres_px)
    write_dataset(group, "source_shifts_px", geometry.source_shifts_px)
    write_dataset(group, "pattern_sources", np.concatenate([np.asarray(p, np.int32) for p in geometry.patterns]))
    write_dataset(group, "pattern_offsets",
                  np.concatenate([[0], np.cumsum([len(p) for p in geometry.patterns])]).astype(np.int64))
    write_dataset(group, "group_offsets", geometry.group_offsets)
    for name in ("virtual_camera", "virtual_source", "virtual_pattern", "virtual_group",
                 "measurement_camera", "measurement_pattern"):
        write_dataset(group, name, getattr(geometry, name))
    write_dataset(group, "virtual_centres_px", geometry.virtual_centres_px)


def read_multiplex(handle: h5py.File) -> MultiplexGeometry:
    """Read /multiplex; a malformed group raises a one-line InputError."""
    if "multiplex" not in handle:
        raise InputError(f"{handle.filename}: no /multiplex group; these are not multiplexed captures")
    group = handle["multiplex"]
    try:
        sources = np.asarray(group["pattern_sources"])
        offsets = np.asarray(group["pattern_offsets"])
        patterns = tuple(tuple(int(q) for q in sources[offsets[t]:offsets[t + 1]]) for t in range(len(offsets) - 1))
        geometry = MultiplexGeometry(
            camera_centres_px=np.asarray(group["camera_centres_px"], np.float64),
            source_shifts_px=np.asarray(group["source_shifts_px"], np.float64),
            patterns=patterns,
            pupil_radius_px=float(group.attrs["pupil_radius_px"]),
            camera_shape=tuple(int(v) for v in group.attrs["camera_shape"]),
            source_shape=tuple(int(v) for v in group.attrs["source_shape"]),
        )
    except KeyError as exc:
        raise InputError(f"{handle.filename}: /multiplex lacks {exc.args[0]}; the file is incomplete") from None
    except ValueError as exc:
        raise InputError(f"{handle.filename}: /multiplex: {exc}") from None
    return geometry


def is_multiplexed_file(path) -> bool:
    """Whether ``path`` holds multiplexed captures (has a /multiplex group)."""
    with open_input(path) as handle:
        return "multiplex" in handle
