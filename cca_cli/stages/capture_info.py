"""Carry what ingest, hdr and register learned about recorded captures into recon.h5 for the report."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from cca_cli.io.h5 import describe

__all__ = ["capture_extras", "read_capture_summary"]

_COPIED = ("/registration/rms_px", "/registration/dropped", "/hdr/dynamic_range_gain", "/hdr/valid_fraction")


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
    if "/hdr/dynamic_range_gain" in handle:
        out["hdr_dynamic_range_gain_median"] = round(float(np.median(handle["/hdr/dynamic_range_gain"])), 3)
    if "/hdr/valid_fraction" in handle:
        out["hdr_valid_fraction_mean"] = round(float(np.mean(handle["/hdr/valid_fraction"])), 4)
    return out
