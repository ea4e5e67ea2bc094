"""`cca run [CONFIG]`: every configured stage, resuming where a previous run stopped."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from cca_cli.commands.console import (console, err_console, handle_errors, print_note, progress_reporter,
                                     poor_fit_warning, print_warning, recovery_stop_note, stop_note,
                                     summary_table)
from cca_cli.commands.options import Device, Force, OptionalConfigArg, Quiet, Scheduler, Workers, cluster_options
from cca_cli.config.load import load_config
from cca_cli.config.model import ReconstructSection
from cca_cli.io.outputs import disk_usage
from cca_cli.stages.footprint import size_text


@handle_errors
def run_cli(
    config: OptionalConfigArg = None,
    out_dir: Annotated[Optional[Path], typer.Option("--out-dir", help="Override run.out_dir.")] = None,
    workers: Workers = None,
    scheduler: Scheduler = None,
    device: Device = None,
    force: Force = False,
    quiet: Quiet = False,
) -> None:
    """Run the pipeline of CONFIG (default: the paper's headline simulation) into ./cca-runs/.

    --workers / --scheduler say where a tiled reconstruction (reconstruct.tiles) runs its tiles; --device where
    the engine runs (reconstruct.device). Outputs a run already made stay current whichever device made them.
    """
    from cca_cli.stages.runner import default_out_dir, run_pipeline  # every stage's modules: only when a run starts

    cfg = load_config(config)
    if device is not None:
        cfg = with_device(cfg, device)
    directory = out_dir or cfg.run.out_dir or default_out_dir(config)

    def on_stage(plan, status):
        if status == "skipped":
            err_console.print(f"{plan.name}: {plan.output} is up to date, skipped", style="dim", highlight=False,
                              soft_wrap=True)
        elif status == "outdated":
            err_console.print(f"{plan.name}: {plan.output} was made with other engine defaults (another cca), "
                              "recomputing", style="dim", highlight=False, soft_wrap=True)

    tiled = cfg.reconstruct is not None and cfg.reconstruct.tiles is not None
    with cluster_options(workers, scheduler, used=tiled), progress_reporter(not quiet) as progress:
        outcomes = run_pipeline(cfg, Path(directory), force=force, progress=progress, on_stage=on_stage,
                                source=config if config is not None else "the built-in default")
    report = next((o for o in outcomes if o.name == "report"), None)
    if report is not None:
        summary = report.result
        if summary is None:
            import json

            summary = json.loads((report.output / "report.json").read_text())
        console.print(summary_table(summary, title=f"cca run → {directory}"))
    for outcome in outcomes:
        console.print(f"{outcome.name:12s} {outcome.status:8s} {outcome.output}  ({outcome.seconds:.1f} s, "
                      f"{size_text(disk_usage(outcome.output))})")
    recon = next((o for o in outcomes if o.name == "reconstruct"), None)
    warning = None
    if recon is not None and recon.result is not None:
        note = recovery_stop_note(recon.result)
        warning = poor_fit_warning(recon.result)
    elif report is not None:
        note = stop_note(summary.get("stopped_by"), summary.get("iterations"), summary.get("final_change"),
                         summary.get("tol"))
    else:
        note = None
    if note:
        print_note(note)
    if warning:
        print_warning(warning)


def with_device(cfg, device: str):
    """``cfg`` with ``reconstruct.device`` set from ``--device`` (one line naming the option when it is not one)."""
    from cca_cli.commands.options import section_from_options

    section = section_from_options(ReconstructSection, cfg.reconstruct, device=device)
    return cfg.model_copy(update={"reconstruct": section})
