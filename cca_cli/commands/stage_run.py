"""What every one-stage command does around the stage: the output check, provenance and progress bars."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, TypeVar

from pydantic import BaseModel

from cca_cli.commands.console import progress_reporter
from cca_cli.io.h5 import check_output
from cca_cli.stages.runner import stage_provenance

__all__ = ["run_stage"]

T = TypeVar("T")


def run_stage(stage: str, run: Callable[..., T], *args, output: Path, sections: dict[str, BaseModel], inputs=(),
              force: bool, quiet: bool = False) -> T:
    """Call ``run(*args, output, provenance=…, force=…, progress=…)``, a stage's ``run`` function.

    Parameters
    ----------
    stage : str
        Stage name recorded in the provenance.
    run : callable
        The stage's ``run``; ``args`` are its arguments before ``output``.
    output : Path
        Refused before any input is hashed when it exists and ``force`` is not set.
    sections : dict
        The config sections the stage reads (hashed into the provenance).
    inputs : sequence of Path, or a callable returning one
        Input files (hashed into the provenance); a callable is called after the output check.
    force : bool
        Overwrite ``output``.
    quiet : bool
        No progress bars.
    """
    check_output(output, force=force)
    provenance = stage_provenance(stage, sections, inputs() if callable(inputs) else inputs)
    with progress_reporter(not quiet) as progress:
        return run(*args, output, provenance=provenance, force=force, progress=progress)
