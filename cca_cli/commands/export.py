"""`cca export RECON -o FILE`: the recovery as a float32 TIFF, 16-bit PNG or .npy file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from cca_cli.commands.console import console, handle_errors
from cca_cli.commands.options import Force

__all__ = ["export_cli"]


@handle_errors
def export_cli(
    recon: Annotated[Path, typer.Argument(help="recon.h5 from reconstruct.", show_default=False)],
    output: Annotated[Path, typer.Option("--output", "-o", show_default=False,
                                         help="Image file: .tif/.tiff (float32), .png (16-bit) or .npy.")],
    quantity: Annotated[str, typer.Option(help="amplitude, intensity or phase (rad).")] = "amplitude",
    format: Annotated[Optional[str], typer.Option("--format", help="tiff, png or npy (default: from the suffix).")] = None,
    force: Force = False,
) -> None:
    """Export the recovered amplitude, intensity or phase of RECON at full resolution, with its pixel size."""
    from cca_cli.io.export import export_recon, read_exported

    path = export_recon(recon, output, quantity=quantity, format=format, force=force)
    written = read_exported(path)
    h, w = written.values.shape
    pixel = f", {written.pixel_size_m * 1e6:.4g} µm pixels" if written.pixel_size_m else ""
    console.print(f"{path}: {quantity} {w}x{h} px{pixel}", highlight=False)
