"""Stage `register`: align every view to the centre view with checkerboard homographies → registered.h5.

The board is found in each position's calibration view (the board
photographed at that position, stored by ingest) or, without calibration
views, in the captures themselves (a board beside the object). Each view's
homography to the centre view is fitted with RANSAC; views and validity
weights are warped onto the centre view's pixel grid and cut to the object
rectangle (any aspect; the whole frame by default). Pixels that the warp
could not fill get weight 0. The registration error is estimated where the
object is (:mod:`cca_cli.registration.accuracy`), not only at the corners.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.config.model import RegisterSection
from cca_cli.errors import CheckerboardNotFound, ConfigError, InputError
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, open_input, require, write_dataset
from cca_cli.registration.accuracy import object_error
from cca_cli.registration.checkerboard import find_checkerboard
from cca_cli.registration.homography import crop, estimate_homography, warp_views
from cca_cli.sampling.capture import object_pixel_m, with_field_width
from cca_cli.io.records import carry_capture_records
from cca_cli.io.captures import BOUNDARY_OPEN, read_frame_scale, read_labels, write_labels, write_strings
from cca_cli.library.orientation import recorded_orientation_advice
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent

__all__ = ["SECTIONS", "Registration", "register_views", "run"]

SECTIONS = ("registration",)

_log = logging.getLogger(__name__)
#: Estimated registration error (frame px) beyond which extrapolating outside the board is worth a warning:
#: about where it starts to blur what a recovery resolves.
EXTRAPOLATION_LIMIT_PX = 0.5


@dataclass(frozen=True)
class Registration:
    """Aligned, cropped views and how they were aligned."""

    intensity: np.ndarray      # (K', h, w)
    weight: np.ndarray         # (K', h, w)
    homographies: np.ndarray   # (K', 3, 3) view → reference
    rms_px: np.ndarray         # (K',)
    kept: np.ndarray           # (K',) indices into the input views
    dropped: list[str]         # labels of the lost views
    corners: np.ndarray        # (K', N, 2) detected corners in each view
    object_rms_px: np.ndarray | None = None      # (K',) estimated registration error over the object rectangle
    object_max_px: np.ndarray | None = None      # (K',)
    hull_fraction: np.ndarray | None = None      # (K',) share of the rectangle inside the board corners' hull


def register_views(intensity: np.ndarray, weight: np.ndarray | None, pattern: tuple[int, int], *, reference: int,
                   crop_xywh, labels: list[str], drop_missing: bool = False, ransac_threshold_px: float = 1.0,
                   interpolation: str = "cubic", board_views: np.ndarray | None = None, object_xywh=None,
                   board_files: list[str] | None = None, progress: ProgressFn = silent) -> Registration:
    """Register ``intensity`` views (K, H, W) to view ``reference`` and cut out ``crop_xywh``.

    Parameters
    ----------
    board_views : ndarray, (K, H, W), optional
        Calibration images of the board at each position; the board is
        looked for in ``intensity`` itself when None.
    board_files : list of str, optional
        The file(s) of each position's calibration image, for messages.
    object_xywh : tuple of int, optional
        Where the object is (reference px), for the registration error
        estimate; default ``crop_xywh``.

    Raises
    ------
    CheckerboardNotFound
        The board is missing in the reference view, or in any view when
        ``drop_missing`` is false.
    ConfigError
        The rectangle does not fit the frame.
    """
    k, h, w = intensity.shape
    x0, y0, cw, ch = (int(v) for v in crop_xywh)
    if x0 < 0 or y0 < 0 or x0 + cw > w or y0 + ch > h:
        raise ConfigError(f"registration.crop_xywh: ({x0}, {y0}, {cw}, {ch}) does not fit in the {w}x{h} px frames")
    search = intensity if board_views is None else board_views
    if search.shape != intensity.shape:
        raise InputError(f"calibration views are {search.shape[2]}x{search.shape[1]} px but the captures are "
                         f"{w}x{h} px; photograph the board with the same camera settings")
    def view_name(i: int) -> str:
        if board_views is None:
            return labels[i]
        if board_files is None:
            return f"{labels[i]} calibration view"
        position = labels[i][:labels[i].rindex(" (")] if labels[i].endswith(")") and " (" in labels[i] else labels[i]
        return f"{board_files[i]} (the board's view at {position})"

    try:   # first: without the reference's board no view can be registered
        ref = find_checkerboard(search[reference], pattern, source=view_name(reference))
    except CheckerboardNotFound:
        raise CheckerboardNotFound(view_name(reference), pattern, reference=True) from None
    corners, kept, dropped = [], [], []
    for i in range(k):
        try:
            corners.append(ref if i == reference else find_checkerboard(search[i], pattern, source=view_name(i)))
            kept.append(i)
        except CheckerboardNotFound:
            if not drop_missing:
                raise
            _log.warning("%s: no checkerboard found; view dropped", view_name(i))
            dropped.append(labels[i])
        progress(ProgressEvent("register", "checkerboards", i + 1, k))
    fits = []
    for i, pts in zip(kept, corners):
        try:
            fits.append(estimate_homography(pts, ref, ransac_threshold_px=ransac_threshold_px))
        except ValueError as exc:
            raise InputError(f"{labels[i]}: cannot fit a homography to the checkerboard ({exc})") from None
    mats = np.stack([f.matrix for f in fits])
    rect = (x0, y0, cw, ch)
    where = rect if object_xywh is None else tuple(int(v) for v in object_xywh)
    if where[0] + where[2] > w or where[1] + where[3] > h:
        raise ConfigError(f"registration.object_xywh: {where} does not fit in the {w}x{h} px frames")
    errors = [object_error(pts, ref, f.matrix, where, inliers=f.inlier_mask) for pts, f in zip(corners, fits)]
    hull = np.array([e.hull_fraction for e in errors])
    if (hull < 1).any():
        worst_px = max(e.max_px for e in errors)
        serious = worst_px > EXTRAPOLATION_LIMIT_PX
        region = ("the object region" if object_xywh is not None else
                  "the object region (the whole crop: registration.object_xywh says where the object is)")
        _log.warning("%s%s lies %.0f%% outside the board corners' hull (worst view %s): the "
                     "homographies extrapolate there (estimated error up to %.3f px%s)", "" if serious else "note: ",
                     region, 100 * (1 - hull.min()), labels[kept[int(np.argmin(hull))]], worst_px,
                     "; photograph the board over the object region" if serious else
                     f", below the {EXTRAPOLATION_LIMIT_PX} px that would matter")
    views, masks = warp_views(intensity[kept], mats, (h, w), interpolation=interpolation, with_mask=True)
    if weight is not None:
        warped_w = warp_views(weight[kept], mats, (h, w), interpolation="linear")
        # A weight-0 (invalid) source pixel spoils every output pixel its kernel touches.
        invalid = warp_views((weight[kept] <= 0).astype(np.float32), mats, (h, w), interpolation="linear") > 0
        w_out = np.where(masks & ~invalid, np.clip(warped_w, 0, 1), 0).astype(np.float32)
    else:
        w_out = masks.astype(np.float32)
    return Registration(intensity=crop(views, rect), weight=crop(w_out, rect), homographies=mats,
                        rms_px=np.array([f.rms_px for f in fits]), kept=np.asarray(kept, np.int32),
                        dropped=dropped, corners=np.stack(corners),
                        object_rms_px=np.array([e.rms_px for e in errors]),
                        object_max_px=np.array([e.max_px for e in errors]), hull_fraction=hull)


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
        frame_scale = read_frame_scale(src["/measurements/intensity"].attrs, captures_path)
        if "registration/board" not in src:
            raise InputError(f"{captures_path}: no checkerboard pattern recorded; add checkerboard: {{pattern: [9, 6]}} "
                             "to the manifest and re-run ingest")
        pattern = tuple(int(v) for v in src["registration/board"].attrs["pattern"])
        board_views, board_files = None, None
        if "/registration/board_views" in src:
            board_views = np.asarray(src["/registration/board_views"], np.float32)
            files = src["/registration/board_views"].attrs.get("files")
            board_files = None if files is None else [f.decode() if isinstance(f, bytes) else str(f) for f in files]
        k, h, w = intensity.shape
        rect = tuple(section.crop_xywh) if section.crop_xywh is not None else (0, 0, w, h)
        reg = register_views(intensity, weight, pattern, reference=geometry.centre_index, crop_xywh=rect,
                             labels=labels, drop_missing=section.drop_missing,
                             ransac_threshold_px=section.ransac_threshold_px, interpolation=section.interpolation,
                             board_views=board_views, object_xywh=section.object_xywh, board_files=board_files,
                             progress=progress)
        new_geometry = with_field_width(geometry, rect[2] * object_pixel_m(geometry), keep=reg.kept)
        warning = recorded_orientation_advice(reg.intensity, reg.weight, new_geometry, frame_scale)
        if warning is not None:
            _log.warning("%s: %s", captures_path, warning)
        with atomic_h5(output, provenance, force=force) as handle:
            units = src["/measurements/intensity"].attrs.get("units", "")
            ds = write_dataset(handle, "/measurements/intensity", reg.intensity, units=units)
            ds.attrs["boundary"] = BOUNDARY_OPEN
            ds.attrs["frame_scale"] = frame_scale
            write_dataset(handle, "/measurements/weight", reg.weight)
            write_dataset(handle, "/registration/homography", reg.homographies)
            write_dataset(handle, "/registration/rms_px", reg.rms_px)
            write_dataset(handle, "/registration/object_rms_px", reg.object_rms_px)
            write_dataset(handle, "/registration/object_max_px", reg.object_max_px)
            write_dataset(handle, "/registration/board_hull_fraction", reg.hull_fraction)
            write_dataset(handle, "/registration/kept_index", reg.kept)
            write_dataset(handle, "/registration/corners", reg.corners.astype(np.float32))
            write_strings(handle, "/registration/dropped", reg.dropped)
            handle["registration"].attrs["crop_xywh"] = np.asarray(rect, np.int32)
            handle["registration"].attrs["object_xywh"] = np.asarray(section.object_xywh or rect, np.int32)
            handle["registration"].attrs["reference_index"] = int(geometry.centre_index)
            handle["registration"].attrs["board_source"] = "calibration views" if board_views is not None else "captures"
            write_labels(handle, [labels[i] for i in reg.kept])
            write_geometry(handle, new_geometry)
            carry_capture_records(src, handle, keep=reg.kept)
            if "hdr" in src:
                for name in ("dynamic_range_gain", "dynamic_range", "valid_fraction", "flux_ratio", "flux_ratio_sigma"):
                    if name in src["hdr"]:
                        write_dataset(handle, f"/hdr/{name}", np.asarray(src["hdr"][name])[reg.kept])
    return reg
