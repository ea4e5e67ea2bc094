"""Stage `ingest`: a capture manifest and its image files → raw.h5.

Every image is read (OpenImageIO, or one MATLAB variable for LED-array
datasets), black-level subtracted and clipped at the sensor's white level
(linear float32 counts), and grouped by position into ``(K, E, H, W)``
exposure brackets. Positions become pupil centres in spectrum pixels in
:mod:`cca_cli.sampling.capture`. Single-exposure datasets also get
``/measurements`` so they can go straight to `reconstruct` (or `register`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from cca_cli.errors import InputError
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, describe, write_dataset
from cca_cli.io.images import read_image, to_linear
from cca_cli.io.manifest import CapturePlan, load_manifest, plan_captures
from cca_cli.sampling.capture import led_array_geometry, stage_scan_geometry
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent

__all__ = ["SECTIONS", "Ingested", "ingest", "write_raw", "run", "write_labels", "read_labels"]

SECTIONS = ("ingest",)


@dataclass(frozen=True)
class Ingested:
    """Linear frames of a capture set and their geometry."""

    plan: CapturePlan
    frames: np.ndarray          # (K, E, H, W) float32 counts, black subtracted
    exposure_s: np.ndarray      # (K, E)
    saturation_level: float
    geometry: CaptureGeometry


def _read_mat(plan: CapturePlan) -> np.ndarray:
    from scipy.io import loadmat

    source = plan.manifest.source
    if not source.mat.is_file():
        raise InputError(f"{source.mat}: file not found (manifest source.mat); check the path")
    try:
        data = loadmat(source.mat, variable_names=[source.variable])
    except Exception as exc:  # noqa: BLE001 - any decoder failure is an unreadable file
        raise InputError(f"{source.mat}: cannot read MATLAB file ({' '.join(str(exc).split())})") from None
    if source.variable not in data:
        raise InputError(f"{source.mat}: has no variable {source.variable!r} (manifest source.variable)")
    stack = np.asarray(data[source.variable])
    if stack.ndim != 3:
        raise InputError(f"{source.mat}: {source.variable} has shape {stack.shape}; expected (H, W, K)")
    stack = np.moveaxis(stack, -1, 0).astype(np.float32)
    if stack.shape[0] != len(plan.labels):
        raise InputError(f"{source.mat}: {stack.shape[0]} images but {source.illumination_csv.name} "
                         f"lists {len(plan.labels)} illuminations")
    bad = ~np.isfinite(stack).reshape(stack.shape[0], -1).all(axis=1)
    if bad.any():
        raise InputError(f"{source.mat}: {plan.labels[int(np.argmax(bad))]} contains NaN or infinite pixels; fix or drop it")
    return stack[:, None]


def _read_files(plan: CapturePlan, progress: ProgressFn) -> tuple[np.ndarray, float | None]:
    sensor = plan.manifest.sensor
    k, e = plan.exposure_s.shape
    frames = None
    first = None
    white_level = sensor.white_level
    if white_level is None and sensor.bit_depth is not None:
        white_level = float(2 ** sensor.bit_depth - 1)
    for i, row in enumerate(plan.files):
        for j, path in enumerate(row):
            raw = read_image(path)
            if frames is None:
                frames = np.empty((k, e) + raw.pixels.shape, np.float32)
                first = raw
                if white_level is None:
                    white_level = raw.white_level
            elif raw.pixels.shape != frames.shape[2:]:
                h0, w0 = frames.shape[2:]
                h1, w1 = raw.pixels.shape
                raise InputError(f"{path}: image is {w1}x{h1} px but {first.path} is {w0}x{h0}; "
                                 "all images of a capture set must have the same size")
            if white_level is not None and white_level <= sensor.black_level:
                raise InputError(f"{path}: white level {white_level:g} is not above the black level "
                                 f"{sensor.black_level:g} (manifest sensor)")
            frames[i, j] = to_linear(raw, black_level=sensor.black_level, white_level=white_level)
        progress(ProgressEvent("ingest", "images", i + 1, k))
    return frames, white_level


def ingest(manifest_path: Path, *, progress: ProgressFn = silent) -> Ingested:
    """Read a manifest and all its images (no file output)."""
    manifest = load_manifest(manifest_path)
    plan = plan_captures(manifest, manifest_path)
    if manifest.source is not None:
        frames, white_level = _read_mat(plan), None
    else:
        frames, white_level = _read_files(plan, progress)
    if white_level is not None:
        saturation = float(white_level - manifest.sensor.black_level)
    else:  # float data without a white level: nothing counts as clipped
        saturation = float(np.max(frames)) * 1.01 + 1e-30
    h, w = frames.shape[-2:]
    if manifest.optics is not None:
        o = manifest.optics
        field = w * o.pixel_pitch_m * o.distance_m / o.focal_length_m
        geometry = stage_scan_geometry(plan.positions, wavelength_m=o.wavelength_m, focal_length_m=o.focal_length_m,
                                       aperture_diameter_m=o.aperture_diameter_m, pixel_pitch_m=o.pixel_pitch_m,
                                       distance_m=o.distance_m, field_width_m=field, grid_indices=plan.grid_indices)
    else:
        il = manifest.illumination
        geometry = led_array_geometry(plan.positions, wavelength_m=il.wavelength_m,
                                      numerical_aperture=il.numerical_aperture,
                                      pixel_pitch_object_m=il.pixel_pitch_object_m,
                                      field_width_m=w * il.pixel_pitch_object_m, sign=il.sign,
                                      grid_indices=plan.grid_indices)
    return Ingested(plan=plan, frames=frames, exposure_s=plan.exposure_s, saturation_level=saturation,
                    geometry=geometry)


def write_labels(handle: h5py.File, labels: list[str]) -> None:
    """Store one readable name per position as /capture/labels."""
    describe(handle.create_dataset("/capture/labels", data=np.array(labels, dtype=h5py.string_dtype())))


def read_labels(handle: h5py.File, count: int) -> list[str]:
    """/capture/labels, or ``view k`` names when absent."""
    if "/capture/labels" in handle:
        return handle["/capture/labels"].asstr()[()].tolist()
    return [f"view {k}" for k in range(count)]


def write_raw(path: Path, data: Ingested, provenance: Provenance, *, force: bool = False) -> None:
    """Write ``raw.h5`` atomically."""
    manifest = data.plan.manifest
    with atomic_h5(path, provenance, force=force) as handle:
        frames = write_dataset(handle, "/raw/frames", data.frames)
        frames.attrs["saturation_level"] = data.saturation_level
        frames.attrs["black_level"] = manifest.sensor.black_level
        frames.attrs["values"] = manifest.values
        write_dataset(handle, "/raw/exposure_s", data.exposure_s)
        write_labels(handle, data.plan.labels)
        write_geometry(handle, data.geometry)
        if manifest.checkerboard is not None:
            board = handle.require_group("registration/board")
            board.attrs["pattern"] = np.asarray(manifest.checkerboard.pattern, np.int32)
            if manifest.checkerboard.square_m is not None:
                board.attrs["square_m"] = manifest.checkerboard.square_m
        k, e, h, w = data.frames.shape
        if e == 1:
            counts = data.frames[:, 0]
            intensity = counts / data.exposure_s[:, 0, None, None].astype(np.float32)
            if manifest.values == "amplitude":
                intensity = intensity * intensity
            weight = (counts < np.float32(data.saturation_level * 0.99)).astype(np.float32)
            write_dataset(handle, "/measurements/intensity", intensity.astype(np.float32), units="counts/s")
            write_dataset(handle, "/measurements/weight", weight)


def run(manifest_path: Path, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> Ingested:
    """Ingest ``manifest_path`` and write ``output``."""
    check_output(output, force=force)
    data = ingest(Path(manifest_path), progress=progress)
    write_raw(output, data, provenance, force=force)
    return data
