"""Stage `hdr`: raw.h5 exposure brackets → hdr.h5 linear radiance and validity weights."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.config.model import HdrSection
from cca_cli.errors import ConfigError, InputError
from cca_cli.hdr.merge import merge_exposures
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, open_input, require, write_dataset
from cca_cli.stages.ingest import read_labels, write_labels
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent

__all__ = ["SECTIONS", "HdrOutcome", "run", "copy_board"]

SECTIONS = ("hdr",)


@dataclass(frozen=True)
class HdrOutcome:
    """Summary of a merge."""

    n_positions: int
    n_exposures: int
    dynamic_range_gain: np.ndarray   # (K,)
    valid_fraction: np.ndarray       # (K,)
    exposure_ratio: float


def copy_board(source, handle) -> None:
    """Copy the /registration/board attributes (checkerboard pattern) from ``source`` to ``handle``."""
    if "registration/board" in source:
        board = handle.require_group("registration/board")
        for key, value in source["registration/board"].attrs.items():
            board.attrs[key] = value


def run(raw_path: Path, section: HdrSection | None, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> HdrOutcome:
    """Merge every position's exposures of ``raw_path`` and write ``output``."""
    section = section or HdrSection()
    check_output(output, force=force)
    with open_input(raw_path, stage="ingest") as src:
        frames_ds = require(src, "/raw/frames", ndim=4)
        frames = np.asarray(frames_ds, np.float32)
        exposure = np.asarray(require(src, "/raw/exposure_s", ndim=2), np.float64)
        saturation = section.saturation_level or float(frames_ds.attrs["saturation_level"])
        values = str(frames_ds.attrs.get("values", "intensity"))
        geometry = read_geometry(src)
        labels = read_labels(src, frames.shape[0])
        k, e = frames.shape[:2]
        radiance = np.empty((k,) + frames.shape[2:], np.float32)
        weight = np.empty_like(radiance)
        gain = np.empty(k)
        valid = np.empty(k)
        ratio = 1.0
        for i in range(k):
            try:
                res = merge_exposures(frames[i], exposure[i], saturation_level=saturation,
                                      noise_floor=section.noise_floor, min_weight=section.min_weight,
                                      saturation_margin=section.saturation_margin)
            except ValueError as exc:
                if "noise_floor" in str(exc) or "saturation" in str(exc):
                    raise ConfigError(f"hdr: {exc}") from None
                raise InputError(f"{raw_path}: {labels[i]}: {exc}") from None
            radiance[i], weight[i] = res.radiance, res.weight
            gain[i], valid[i] = res.dynamic_range_gain, float(res.valid.mean())
            ratio = max(ratio, res.exposure_ratio)
            progress(ProgressEvent("hdr", "positions", i + 1, k))
        if values == "amplitude":
            radiance = radiance * radiance
        with atomic_h5(output, provenance, force=force) as handle:
            write_dataset(handle, "/measurements/intensity", radiance, units="counts/s")
            write_dataset(handle, "/measurements/weight", weight)
            write_dataset(handle, "/hdr/dynamic_range_gain", gain)
            write_dataset(handle, "/hdr/valid_fraction", valid)
            handle["hdr"].attrs["exposures"] = e
            handle["hdr"].attrs["exposure_ratio"] = ratio
            handle["hdr"].attrs["saturation_level"] = saturation
            write_labels(handle, labels)
            write_geometry(handle, geometry)
            copy_board(src, handle)
    return HdrOutcome(n_positions=k, n_exposures=e, dynamic_range_gain=gain, valid_fraction=valid,
                      exposure_ratio=ratio)
