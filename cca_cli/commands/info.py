"""`cca info FILE.h5`: what a pipeline file holds, with units."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import h5py
import typer

from cca_cli.commands.console import console, handle_errors
from cca_cli.errors import InputError


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


@handle_errors
def info_cli(path: Annotated[Path, typer.Argument(help="An HDF5 file written by cca.", show_default=False)]) -> None:
    """List the datasets of PATH with dtype, shape, units and meaning, and its provenance."""
    if not path.exists():
        raise InputError(f"{path}: file not found")
    if not h5py.is_hdf5(path):
        raise InputError(f"{path}: not an HDF5 file")
    out = lambda text="": console.print(text, markup=False, highlight=False, soft_wrap=True)  # noqa: E731
    with h5py.File(path, "r") as handle:
        attrs = {k: _text(v) for k, v in handle.attrs.items()}
        out(f"{path}: stage {attrs.get('stage', '?')}, cca {attrs.get('cca_version', '?')}, "
            f"schema {attrs.get('cca_schema', '?')}, created {attrs.get('created_utc', '?')}")
        out()

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                units = _text(obj.attrs.get("units", ""))
                out(f"  /{name}  {obj.dtype}  {obj.shape}  [{units}]")
                if "description" in obj.attrs:
                    out(f"      {_text(obj.attrs['description'])}")

        handle.visititems(visit)
        for group in ("geometry", "recon"):
            if group in handle:
                items = [f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={_text(v)}"
                         for k, v in handle[group].attrs.items() if k != "units"]
                out()
                out(f"{group}: " + ", ".join(items))
        if attrs.get("inputs"):
            out()
            out(f"inputs: {attrs['inputs']}")
        if attrs.get("config"):
            out()
            out("config:")
            out(attrs["config"].rstrip())
