"""Stage `register`: align every view to the centre view with checkerboard homographies → registered.h5.

The board is found in each view (OpenCV, sub-pixel), each view's homography
to the centre view is fitted with RANSAC, views and validity weights are
warped onto the centre view's pixel grid and cropped to the object
rectangle. Pixels that the warp could not fill get weight 0.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from cca_cli.config.model import RegisterSection
from cca_cli.errors import CheckerboardNotFound, ConfigError, InputError
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, describe, open_input, require, write_dataset
from cca_cli.registration.checkerboard import find_checkerboard
from cca_cli.registration.homography import crop, estimate_homography, warp_views
from cca_cli.sampling.capture import object_pixel_m, with_field_width
from cca_cli.stages.hdr import copy_board
from cca_cli.stages.ingest import read_labels, write_labels
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent

__all__ = ["SECTIONS", "Registration", "register_views", "run"]

SECTIONS = ("registration",)

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Registration:
    """Aligned, cropped views and how they were aligned."""

    intensity: np.ndarray      # (K', h, h)
    weight: np.ndarray         # (K', h, h)
    homographies: np.ndarray   # (K', 3, 3) view → reference
    rms_px: np.ndarray         # (K',)
    kept: np.ndarray           # (K',) indices into the input views
    dropped: list[str]         # labels of the lost views
    corners: np.ndarray        # (K', N, 2) detected corners in each view


def register_views(intensity: np.ndarray, weight: np.ndarray | None, pattern: tuple[int, int], *, reference: int,
                   crop_xywh, labels: list[str], drop_missing: bool = False, ransac_threshold_px: float = 1.0,
                   interpolation: str = "cubic", progress: ProgressFn = silent) -> Registration:
    """Register ``intensity`` views (K, H, W) to view ``reference`` and crop them.

    Raises
    ------
    CheckerboardNotFound
        The board is missing in the reference view, or in any view when
        ``drop_missing`` is false.
    ConfigError
        The crop rectangle is not square or does not fit the frame.
    """
    k, h, w = intensity.shape
    x0, y0, cw, ch = (int(v) for v in crop_xywh)
    if cw != ch:
        raise ConfigError(f"registration.crop_xywh: the object rectangle must be square, got {cw}x{ch} px")
    if x0 < 0 or y0 < 0 or x0 + cw > w or y0 + ch > h:
        raise ConfigError(f"registration.crop_xywh: ({x0}, {y0}, {cw}, {ch}) does not fit in the {w}x{h} px frames")
    corners, kept, dropped = [], [], []
    for i in range(k):
        try:
            corners.append(find_checkerboard(intensity[i], pattern, source=labels[i]))
            kept.append(i)
        except CheckerboardNotFound:
            if not drop_missing or i == reference:
                raise
            _log.warning("%s: no checkerboard found; view dropped", labels[i])
            dropped.append(labels[i])
        progress(ProgressEvent("register", "checkerboards", i + 1, k))
    ref = corners[kept.index(reference)]
    fits = []
    for i, pts in zip(kept, corners):
        try:
            fits.append(estimate_homography(pts, ref, ransac_threshold_px=ransac_threshold_px))
        except ValueError as exc:
            raise InputError(f"{labels[i]}: cannot fit a homography to the checkerboard ({exc})") from None
    mats = np.stack([f.matrix for f in fits])
    views, masks = warp_views(intensity[kept], mats, (h, w), interpolation=interpolation, with_mask=True)
    np.clip(views, 0, None, out=views)
    if weight is not None:
        warped_w = warp_views(weight[kept], mats, (h, w), interpolation="linear")
        # A weight-0 (invalid) source pixel spoils every output pixel its kernel touches.
        invalid = warp_views((weight[kept] <= 0).astype(np.float32), mats, (h, w), interpolation="linear") > 0
        w_out = np.where(masks & ~invalid, np.clip(warped_w, 0, 1), 0).astype(np.float32)
    else:
        w_out = masks.astype(np.float32)
    rect = (x0, y0, cw, ch)
    return Registration(intensity=crop(views, rect), weight=crop(w_out, rect), homographies=mats,
                        rms_px=np.array([f.rms_px for f in fits]), kept=np.asarray(kept, np.int32),
                        dropped=dropped, corners=np.stack(corners))


def run(captures_path: Path, section: RegisterSection | None, output: Path, *, provenance: Provenance,
        force: bool = False, progress: ProgressFn = silent) -> Registration:
    """Register the views of ``captures_path`` (hdr.h5, or raw.h5 of single exposures) and write ``output``."""
    section = section or RegisterSection()
    check_output(output, force=force)
    with open_input(captures_path) as src:
        intensity = np.asarray(require(src, "/measurements/intensity", ndim=3), np.float32)
        weight = np.asarray(src["/measurements/weight"], np.float32) if "/measurements/weight" in src else None
        geometry = read_geometry(src)
        labels = read_labels(src, intensity.shape[0])
        if "registration/board" not in src:
            raise InputError(f"{captures_path}: no checkerboard pattern recorded; add checkerboard: {{pattern: [9, 6]}} "
                             "to the manifest and re-run ingest")
        pattern = tuple(int(v) for v in src["registration/board"].attrs["pattern"])
        k, h, w = intensity.shape
        rect = section.crop_xywh
        if rect is None:
            if h != w:
                raise ConfigError(f"registration.crop_xywh: the {w}x{h} px frames are not square; give the object "
                                  "rectangle [x0, y0, width, height] in reference pixels")
            rect = (0, 0, w, h)
        reg = register_views(intensity, weight, pattern, reference=geometry.centre_index, crop_xywh=rect,
                             labels=labels, drop_missing=section.drop_missing,
                             ransac_threshold_px=section.ransac_threshold_px, interpolation=section.interpolation,
                             progress=progress)
        new_geometry = with_field_width(geometry, rect[2] * object_pixel_m(geometry), keep=reg.kept)
        with atomic_h5(output, provenance, force=force) as handle:
            write_dataset(handle, "/measurements/intensity", reg.intensity, units=src["/measurements/intensity"].attrs.get("units", ""))
            write_dataset(handle, "/measurements/weight", reg.weight)
            write_dataset(handle, "/registration/homography", reg.homographies)
            write_dataset(handle, "/registration/rms_px", reg.rms_px)
            write_dataset(handle, "/registration/kept_index", reg.kept)
            write_dataset(handle, "/registration/corners", reg.corners.astype(np.float32))
            describe(handle.create_dataset("/registration/dropped", data=np.array(reg.dropped, dtype=h5py.string_dtype())))
            handle["registration"].attrs["crop_xywh"] = np.asarray(rect, np.int32)
            handle["registration"].attrs["reference_index"] = int(geometry.centre_index)
            write_labels(handle, [labels[i] for i in reg.kept])
            write_geometry(handle, new_geometry)
            copy_board(src, handle)
            if "hdr" in src:
                for name in ("dynamic_range_gain", "valid_fraction"):
                    write_dataset(handle, f"/hdr/{name}", np.asarray(src["hdr"][name])[reg.kept])
    return reg
