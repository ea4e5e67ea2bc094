"""`cca simulate`, `cca reconstruct`, `cca report`: one stage each.

Each command imports its stage when it runs, so that starting one does not load the others' modules.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from cca_cli.commands.console import (console, handle_errors, poor_fit_warning, print_note, print_warning,
                                      recovery_stop_note, summary_table)
from cca_cli.commands.info import derived_lines
from cca_cli.commands.options import (ConfigArg, Device, Force, Quiet, Scheduler, Workers, cluster_options,
                                     section_from_options)
from cca_cli.commands.stage_run import run_stage
from cca_cli.config.load import load_config
from cca_cli.engines.registry import engine_help
from cca_cli.config.model import ReconstructSection, ReportSection
from cca_cli.stages.footprint import reconstruct_footprint, report_footprint, simulate_footprint
from cca_cli.stages.provenance import pick_sections


@handle_errors
def simulate_cli(
    config: ConfigArg,
    output: Annotated[Path, typer.Option("--output", "-o", help="captures file to write.")] = Path("captures.h5"),
    force: Force = False,
    quiet: Quiet = False,
) -> None:
    """Simulate the captures of CONFIG's array and scene → captures.h5."""
    from cca_cli.stages import simulate as simulate_stage

    cfg = load_config(config)
    sim = run_stage("simulate", simulate_stage.run, cfg, output=output,
                    sections=pick_sections(cfg, simulate_stage.SECTIONS), force=force, quiet=quiet, protect=[config],
                    footprint=lambda: simulate_footprint(cfg))
    g = sim.geometry
    if cfg.multiplex is not None:
        mux = sim.multiplex
        console.print(f"{output}: {mux.n_measurements} multiplexed images ({mux.n_cameras} cameras x "
                      f"{mux.n_patterns} patterns) of {sim.intensity.shape[-1]}² px summing {g.n_images} regions, "
                      f"SAR {g.synthetic_aperture_ratio:.2f}, pupil radius {g.pupil_radius_px:.2f} spectrum px")
        return
    console.print(f"{output}: {g.n_images} captures of {sim.intensity.shape[-1]}² px", highlight=False)
    from cca_cli.report.summary import derived_quantities

    derived = derived_quantities(g, hires_size=sim.layout.hires_size, lowres_size=sim.layout.lowres_size)
    for line in derived_lines(derived):
        console.print(line, highlight=False, markup=False)


@handle_errors
def reconstruct_cli(
    captures: Annotated[Path, typer.Argument(help="captures.h5 (from simulate, ingest, hdr or register).", show_default=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="recon file to write.")] = Path("recon.h5"),
    config: Annotated[Optional[Path], typer.Option("--config", "-c", help="Take the reconstruct section from this YAML.")] = None,
    engine: Annotated[Optional[str], typer.Option(help=f"Engine: {engine_help()}.")] = None,
    tau: Annotated[Optional[float], typer.Option(help="Tikhonov weight τ.")] = None,
    iterations: Annotated[Optional[int], typer.Option(help="Maximum iterations.")] = None,
    tol: Annotated[Optional[float], typer.Option(help="Relative-change stopping tolerance.")] = None,
    init: Annotated[Optional[Path], typer.Option(help="Start from the spectrum of this recon.h5 (same grid).")] = None,
    device: Device = None,
    checkpoint_every: Annotated[Optional[int], typer.Option(help="Iterations between checkpoints "
                                                            "(<output>.checkpoint; 0: none) [default: 50].")] = None,
    workers: Workers = None,
    scheduler: Scheduler = None,
    force: Force = False,
    quiet: Quiet = False,
) -> None:
    """Recover the high-resolution object from CAPTURES → recon.h5.

    An interrupted run resumes from its checkpoint when run again with the same captures and options. With
    reconstruct.tiles (from --config) the frame is recovered in tiles on Dask: --workers local processes, or
    the workers of --scheduler; a run started again redoes only the unfinished tiles.
    """
    from cca_cli.stages import reconstruct as reconstruct_stage

    base = load_config(config).reconstruct if config else None
    section = section_from_options(ReconstructSection, base, engine=engine, tau=tau, iterations=iterations, tol=tol,
                                   init=init, checkpoint_every=checkpoint_every, device=device)
    inputs = [captures] + ([section.init] if section.init is not None else [])
    with cluster_options(workers, scheduler, used=section.tiles is not None):
        recovery = run_stage("reconstruct", reconstruct_stage.run, captures, section, output=output,
                             sections={"reconstruct": section}, inputs=inputs, force=force, quiet=quiet,
                             protect=[config] if config else [],
                             footprint=lambda: reconstruct_footprint(captures, section))
    tiles = f"{len(recovery.results)} tiles, " if hasattr(recovery, "results") else ""
    on_gpu = " on the GPU" if getattr(recovery, "device", "cpu") == "cuda" else ""
    console.print(f"{output}: {recovery.engine}{on_gpu}, {tiles}{recovery.history.iterations} iterations in "
                  f"{recovery.seconds:.1f} s, {recovery.hires_size}² output")
    note = recovery_stop_note(recovery)
    if note:
        print_note(note)
    warning = poor_fit_warning(recovery)
    if warning:
        print_warning(warning)


@handle_errors
def report_cli(
    recon: Annotated[Path, typer.Argument(help="recon.h5 from reconstruct.", show_default=False)],
    output: Annotated[Path, typer.Option("--output", "-o", help="Report directory.")] = Path("report"),
    config: Annotated[Optional[Path], typer.Option("--config", "-c", help="Take the report section from this YAML "
                                                   "(bar_elements, baselines, …).")] = None,
    threshold: Annotated[Optional[float], typer.Option(help="Contrast threshold of the resolution limit "
                                                       "\\[default: 0.2].")] = None,
    figures: Annotated[Optional[bool], typer.Option("--figures/--no-figures", help="Write the PNG figures "
                                                    "\\[default: figures].")] = None,
    force: Force = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print where the report went, not its table.")] = False,
) -> None:
    """Metrics (report.json) and figures (PNG) of RECON → a report directory."""
    from cca_cli.stages import report as report_stage

    base = load_config(config).report if config else None
    section = section_from_options(ReportSection, base, names={"mtf_threshold": "--threshold"},
                                   mtf_threshold=threshold, figures=figures)
    summary = run_stage("report", report_stage.run, recon, section, output=output, sections={"report": section},
                        inputs=[recon], force=force, quiet=True, kind="folder", protect=[config] if config else [],
                        footprint=lambda: report_footprint(recon))
    if quiet:
        console.print(f"{output}: report.json and {len(summary.get('figures', []))} figure(s)", highlight=False)
    else:
        console.print(summary_table(summary, title=f"cca report → {output}"))
