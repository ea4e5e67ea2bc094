"""`cca ingest`, `cca hdr`, `cca register`: recorded captures → measurements the recovery reads.

Each command imports its stage when it runs, so that starting one does not load the others' modules.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer

from cca_cli.commands.console import console, handle_errors
from cca_cli.commands.options import Force, Quiet, section_from_options
from cca_cli.commands.stage_run import run_stage
from cca_cli.config.model import HdrSection, RegisterSection
from cca_cli.errors import ConfigError

__all__ = ["ingest_cli", "hdr_cli", "register_cli"]


@handle_errors
def ingest_cli(
    manifest: Annotated[Path, typer.Argument(help="Capture manifest (YAML, or CSV with a YAML sidecar), or a "
                                                  "PtyLab FPM dataset (.hdf5).", show_default=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="raw file to write.")] = Path("raw.h5"),
    force: Force = False,
    quiet: Quiet = False,
) -> None:
    """Read the images MANIFEST lists (linear counts, grouped by position) → raw.h5."""
    from cca_cli.config.model import IngestSection
    from cca_cli.io.manifest import manifest_files
    from cca_cli.stages import ingest as ingest_stage

    data = run_stage("ingest", ingest_stage.run, manifest, output=output,
                     sections={"ingest": IngestSection(manifest=manifest)}, inputs=lambda: manifest_files(manifest),
                     force=force, quiet=quiet)
    k, e, h, w = data.frames.shape
    g = data.geometry
    console.print(f"{output}: {k} positions x {e} exposure(s) of {w}x{h} px ({g.kind}), "
                  f"pupil radius {g.pupil_radius_px:.2f} spectrum px, SAR {g.synthetic_aperture_ratio:.2f}")


@handle_errors
def hdr_cli(
    raw: Annotated[Path, typer.Argument(help="raw.h5 from ingest.", show_default=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="hdr file to write.")] = Path("hdr.h5"),
    saturation_level: Annotated[Optional[float], typer.Option(help="Clipping level (black-subtracted counts).")] = None,
    read_noise: Annotated[Optional[float], typer.Option(help="Read noise, counts RMS (default: measured).")] = None,
    force: Force = False,
    quiet: Quiet = False,
) -> None:
    """Merge each position's exposure bracket into linear radiance + validity weights → hdr.h5."""
    from cca_cli.stages import hdr as hdr_stage

    section = section_from_options(HdrSection, saturation_level=saturation_level, read_noise=read_noise)
    out = run_stage("hdr", hdr_stage.run, raw, section, output=output, sections={"hdr": section}, inputs=[raw],
                    force=force, quiet=quiet)
    noise = f", read noise {out.noise.read_noise:.2f} counts, {out.noise.electrons_per_count:.2f} e/count " \
            f"({out.noise.source})" if out.noise is not None else ""
    flagged = f", flux ratios off in {len(out.flagged)} view(s)" if out.flagged else ""
    console.print(f"{output}: {out.n_positions} positions merged from {out.n_exposures} exposures "
                  f"(ratio {out.exposure_ratio:.0f}), dynamic range gain median {np.median(out.dynamic_range_gain):.1f}x, "
                  f"valid pixels {np.mean(out.valid_fraction):.1%}{noise}{flagged}")


@handle_errors
def register_cli(
    captures: Annotated[Path, typer.Argument(help="hdr.h5 (or a single-exposure raw.h5).", show_default=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="registered file to write.")] = Path("registered.h5"),
    crop: Annotated[Optional[str], typer.Option(help="Rectangle to keep x0,y0,width,height (reference px; "
                                                     "default: the whole frame).")] = None,
    drop_missing: Annotated[bool, typer.Option("--drop-missing", help="Drop views without a board (warning).")] = False,
    ransac_threshold_px: Annotated[Optional[float], typer.Option(help="RANSAC inlier threshold (px).")] = None,
    force: Force = False,
    quiet: Quiet = False,
) -> None:
    """Align every view to the centre view with the checkerboard and crop the object → registered.h5."""
    from cca_cli.stages import register as register_stage

    rect = None
    if crop is not None:
        try:
            rect = [int(v) for v in crop.split(",")]
        except ValueError:
            raise ConfigError(f"--crop: {crop!r} is not four integers x0,y0,width,height") from None
        if len(rect) != 4:
            raise ConfigError(f"--crop: {crop!r} is not four integers x0,y0,width,height")
    section = section_from_options(RegisterSection, names={"crop_xywh": "--crop"}, crop_xywh=rect,
                                   drop_missing=drop_missing or None, ransac_threshold_px=ransac_threshold_px)
    reg = run_stage("register", register_stage.run, captures, section, output=output,
                    sections={"registration": section}, inputs=[captures], force=force, quiet=quiet)
    lost = f", lost: {'; '.join(reg.dropped)}" if reg.dropped else ""
    console.print(f"{output}: {len(reg.kept)} views registered, reprojection RMS max {reg.rms_px.max():.3f} px, "
                  f"estimated error over the object {reg.object_rms_px.mean():.3f} px RMS (max "
                  f"{reg.object_max_px.max():.3f} px), region {reg.intensity.shape[-1]}x{reg.intensity.shape[-2]} px{lost}")
