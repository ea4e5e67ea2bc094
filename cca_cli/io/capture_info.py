"""Carry what ingest, hdr and register learned about recorded captures into recon.h5 for the report."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from cca_cli.io.h5 import describe

__all__ = ["capture_extras", "read_capture_summary"]

_COPIED = ("/registration/rms_px", "/registration/dropped", "/registration/object_rms_px",
           "/registration/object_max_px", "/registration/board_hull_fraction", "/hdr/dynamic_range_gain",
           "/hdr/dynamic_range", "/hdr/valid_fraction", "/hdr/flux_ratio", "/hdr/flux_ratio_sigma")


def capture_extras(captures_path: Path):
    """A ``write_recon`` ``extra`` callback copying registration/HDR records, or None when there are none."""
    with h5py.File(captures_path, "r") as src:
        present = {name: (src[name][()], src[name].dtype, dict(src[name].attrs)) for name in _COPIED if name in src}
    if not present:
        return None

    def extra(handle: h5py.File) -> None:
        for name, (data, dtype, attrs) in present.items():
            copy = handle.create_dataset(name, data=data, dtype=dtype)
            copy.attrs.update(attrs)
            describe(copy, units=_text(attrs["units"]) if "units" in attrs else None,
                     description=_text(attrs["description"]) if "description" in attrs else None)

    return extra


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def read_capture_summary(handle: h5py.File) -> dict:
    """Report entries from the records copied by :func:`capture_extras` (empty for simulations)."""
    out = {}
    if "/registration/dropped" in handle:
        out["lost_positions"] = handle["/registration/dropped"].asstr()[()].tolist()
    if "/registration/rms_px" in handle:
        rms = np.asarray(handle["/registration/rms_px"])
        out["registration_rms_px_max"] = round(float(rms.max()), 4)
        out["registration_rms_px_mean"] = round(float(rms.mean()), 4)
    if "/registration/object_rms_px" in handle:
        obj = np.asarray(handle["/registration/object_rms_px"])
        out["registration_object_rms_px_mean"] = round(float(obj.mean()), 4)
        out["registration_object_rms_px_max"] = round(float(obj.max()), 4)
    if "/registration/object_max_px" in handle:
        out["registration_object_max_px"] = round(float(np.max(handle["/registration/object_max_px"])), 4)
    if "/registration/board_hull_fraction" in handle:
        out["registration_object_in_board_hull"] = round(float(np.min(handle["/registration/board_hull_fraction"])), 4)
    if "/hdr/dynamic_range_gain" in handle:
        out["hdr_dynamic_range_gain_median"] = round(float(np.median(handle["/hdr/dynamic_range_gain"])), 3)
    if "/hdr/dynamic_range" in handle:
        out["hdr_dynamic_range_median"] = round(float(np.median(handle["/hdr/dynamic_range"])), 1)
    if "/hdr/valid_fraction" in handle:
        out["hdr_valid_fraction_mean"] = round(float(np.mean(handle["/hdr/valid_fraction"])), 4)
    if "/hdr/flux_ratio" in handle:
        ratio = np.asarray(handle["/hdr/flux_ratio"], np.float64)
        finite = np.isfinite(ratio)
        if finite.any():
            worst = np.unravel_index(np.argmax(np.where(finite, np.abs(ratio - 1), -1)), ratio.shape)
            out["hdr_flux_ratio_worst"] = round(float(ratio[worst]), 4)
            if "/hdr/flux_ratio_sigma" in handle:   # its noise: a dim exposure's ratio may stray by chance
                sigma = float(np.asarray(handle["/hdr/flux_ratio_sigma"], np.float64)[worst])
                if np.isfinite(sigma):
                    out["hdr_flux_ratio_worst_sigma"] = round(sigma, 4)
    return out
