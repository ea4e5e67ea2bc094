"""The root `cca` command."""

from __future__ import annotations

import typer

from cca_cli import __version__
from cca_cli.commands.capture_cmds import hdr_cli, ingest_cli, register_cli
from cca_cli.commands.console import configure_logging
from cca_cli.commands.design import design_cli
from cca_cli.commands.export import export_cli
from cca_cli.commands.info import info_cli
from cca_cli.commands.run import run_cli
from cca_cli.commands.stage_cmds import reconstruct_cli, report_cli, simulate_cli
from cca_cli.commands.sweep import sweep_app

app = typer.Typer(
    name="cca",
    help="Coherent camera arrays: long-distance, sub-diffraction imaging by macroscopic Fourier ptychography.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"cca {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log informational messages."),
) -> None:
    """Coherent camera arrays: simulate, reconstruct and report sub-diffraction imaging."""
    configure_logging(verbose)


app.command("run")(run_cli)
app.command("simulate")(simulate_cli)
app.command("ingest")(ingest_cli)
app.command("hdr")(hdr_cli)
app.command("register")(register_cli)
app.command("reconstruct")(reconstruct_cli)
app.command("report")(report_cli)
app.command("info")(info_cli)
app.command("export")(export_cli)
app.command("design")(design_cli)
app.add_typer(sweep_app, name="sweep")
