"""The root `cca` command."""

from __future__ import annotations

import sys

import typer
from typer.core import TyperGroup

try:  # recent typer vendors click
    from typer._click import exceptions as click_errors
except ImportError:  # pragma: no cover - typer that uses click itself
    from click import exceptions as click_errors

from cca_cli.version import __version__
from cca_cli.commands.capture_cmds import hdr_cli, ingest_cli, register_cli
from cca_cli.commands.console import configure_logging, err_console, print_error, styled
from cca_cli.commands.design import design_cli
from cca_cli.commands.export import export_cli
from cca_cli.commands.info import info_cli
from cca_cli.commands.run import run_cli
from cca_cli.commands.stage_cmds import reconstruct_cli, report_cli, simulate_cli
from cca_cli.commands.sweep import sweep_app

class OneLineErrors(TyperGroup):
    """The root command group: a wrong command line is one line on stderr too (exit 2)."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click_errors.NoArgsIsHelpError as exc:
            exc.show()
            sys.exit(exc.exit_code)
        except click_errors.ClickException as exc:
            command = exc.ctx.command_path if getattr(exc, "ctx", None) is not None else "cca"
            print_error(f"{command}: {' '.join(exc.format_message().split())} (see {command} --help)")
            sys.exit(exc.exit_code)
        except typer.Abort:
            err_console.print(styled("interrupted:", "bold red", "nothing was written"), soft_wrap=True)
            sys.exit(130)
        sys.exit(code if isinstance(code, int) else 0)


app = typer.Typer(
    name="cca",
    cls=OneLineErrors,
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
