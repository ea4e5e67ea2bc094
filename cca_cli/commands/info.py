"""`cca info FILE.h5`: what a pipeline file holds, with units."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import h5py
import numpy as np
import typer

from cca_cli.commands.console import console, handle_errors
from cca_cli.errors import InputError
from cca_cli.io.h5 import check_input_file


def _text(value) -> str:
    """An attribute as text, whatever it holds (undecodable bytes are replaced, opaque data described)."""
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.void):
        return f"<{len(value.tobytes())} bytes of opaque data>"
    return str(value)


@handle_errors
def info_cli(path: Annotated[Path, typer.Argument(help="An HDF5 file written by cca.", show_default=False)]) -> None:
    """List the datasets of PATH with dtype, shape, units and meaning, and its provenance."""
    check_input_file(path)
    if not h5py.is_hdf5(path):
        raise InputError(f"{path}: not an HDF5 file")
    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: cannot open HDF5 file ({exc}); it may be truncated") from None
    out = lambda text="": console.print(text, markup=False, highlight=False, soft_wrap=True)  # noqa: E731
    try:
        with handle:
            _describe(handle, path, out)
    except (OSError, KeyError, RuntimeError) as exc:
        raise InputError(f"{path}: cannot read the file ({exc}); it may be truncated or damaged") from None


def _attrs(obj) -> dict[str, str]:
    out = {}
    for key in obj.attrs:
        try:
            out[key] = obj.attrs[key]
        except (OSError, TypeError, ValueError):
            out[key] = "<unreadable>"
    return out


def _describe(handle: h5py.File, path: Path, out) -> None:
    attrs = {k: _text(v) for k, v in _attrs(handle).items()}
    out(f"{path}: stage {attrs.get('stage', '?')}, cca {attrs.get('cca_version', '?')}, "
        f"schema {attrs.get('cca_schema', '?')}, created {attrs.get('created_utc', '?')}")
    out()

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            dataset_attrs = _attrs(obj)
            units = _text(dataset_attrs.get("units", ""))
            out(f"  /{name}  {obj.dtype}  {obj.shape}  [{units}]")
            if "description" in dataset_attrs:
                out(f"      {_text(dataset_attrs['description'])}")

    handle.visititems(visit)
    for group in ("geometry", "recon"):
        if group in handle and isinstance(handle[group], h5py.Group):
            items = [f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={_text(v)}"
                     for k, v in _attrs(handle[group]).items() if k != "units"]
            out()
            out(f"{group}: " + ", ".join(items))
    if attrs.get("inputs"):
        out()
        out(f"inputs: {attrs['inputs']}")
    if attrs.get("config"):
        out()
        out("config:")
        out(attrs["config"].rstrip())
