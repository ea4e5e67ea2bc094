"""Shared command-line option types, defined once."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

__all__ = ["ConfigArg", "OptionalConfigArg", "Force", "Output", "Quiet"]

ConfigArg = Annotated[Path, typer.Argument(help="YAML config file.", dir_okay=False, show_default=False)]
OptionalConfigArg = Annotated[Optional[Path], typer.Argument(
    help="YAML config file; omit for the built-in default (the paper's Fig. 5 case).", dir_okay=False,
    show_default=False)]
Force = Annotated[bool, typer.Option("--force", "-f", help="Overwrite existing outputs (and recompute).")]
Output = Annotated[Path, typer.Option("--output", "-o", help="Output path.", dir_okay=True, show_default=False)]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.")]
