"""What every one-stage command does around the stage: output and resource checks, provenance, progress bars."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, TypeVar

from pydantic import BaseModel

from cca_cli.commands.console import progress_reporter
from cca_cli.io.h5 import check_input_file
from cca_cli.io.lock import output_lock
from cca_cli.io.outputs import check_output
from cca_cli.stages.footprint import Footprint, check_footprint
from cca_cli.stages.provenance import stage_provenance

__all__ = ["run_stage"]

T = TypeVar("T")


def run_stage(stage: str, run: Callable[..., T], *args, output: Path, sections: dict[str, BaseModel], inputs=(),
              force: bool, quiet: bool = False, protect=(), footprint: Callable[[], Footprint] | None = None,
              kind: str = "file") -> T:
    """Call ``run(*args, output, provenance=…, force=…, progress=…)``, a stage's ``run`` function.

    Everything that can be checked before the work starts is checked first, in
    this order: the output path (:func:`~cca_cli.io.outputs.check_output`), the
    inputs, the memory and disk the stage needs. The stage then runs holding the
    output's lock (:func:`~cca_cli.io.lock.output_lock`): the same command started
    again meanwhile is refused in one line.

    Parameters
    ----------
    stage : str
        Stage name recorded in the provenance.
    run : callable
        The stage's ``run``; ``args`` are its arguments before ``output``.
    output : Path
        Refused when it exists without ``force``, is an input, is not cca's, or cannot be written.
    sections : dict
        The config sections the stage reads (hashed into the provenance).
    inputs : sequence of Path, or a callable returning one
        Input files (hashed into the provenance; a callable such as a manifest's file list is called first).
    force : bool
        Overwrite ``output`` (when cca wrote it).
    quiet : bool
        No progress bars.
    protect : sequence of Path
        Further files the output must not replace (the config file).
    footprint : callable, optional
        The stage's :class:`~cca_cli.stages.footprint.Footprint`, checked against the machine.
    kind : {"file", "folder"}
        What the output is.
    """
    files = list(inputs() if callable(inputs) else inputs)
    check_output(output, force=force, kind=kind, inputs=[*files, *protect])
    for index, path in enumerate(files):
        check_input_file(path, listed_in=files[0] if callable(inputs) and index else None)
    if footprint is not None:
        check_footprint(footprint(), output, source=files[0] if files else (protect[0] if protect else None))
    provenance = stage_provenance(stage, sections, files)
    with output_lock(output), progress_reporter(not quiet) as progress:
        return run(*args, output, provenance=provenance, force=force, progress=progress)
