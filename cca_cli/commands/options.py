"""Shared command-line option types, defined once, and config sections built from option values."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional, TypeVar

import typer
from pydantic import BaseModel, ValidationError

from cca_cli.config.messages import error_message
from cca_cli.errors import ConfigError, short

__all__ = ["ConfigArg", "OptionalConfigArg", "Force", "Output", "Quiet", "Workers", "Scheduler", "Device",
           "check_cluster_options", "cluster_options", "section_from_options"]

SectionT = TypeVar("SectionT", bound=BaseModel)

ConfigArg = Annotated[Path, typer.Argument(help="YAML config file.", dir_okay=False, show_default=False)]
OptionalConfigArg = Annotated[Optional[Path], typer.Argument(
    help="YAML config file; omit for the built-in default (the paper's Fig. 5 case).", dir_okay=False,
    show_default=False)]
Force = Annotated[bool, typer.Option("--force", "-f", help="Overwrite existing outputs (and recompute).")]
Output = Annotated[Path, typer.Option("--output", "-o", help="Output path.", dir_okay=True, show_default=False)]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars.")]
Workers = Annotated[Optional[int], typer.Option("--workers", "-w", help="Local Dask worker processes (default: one "
                                                                        "per core).")]
Scheduler = Annotated[Optional[str], typer.Option("--scheduler", help="Address of an existing Dask scheduler, e.g. "
                                                                      "tcp://host:8786.")]
Device = Annotated[Optional[str], typer.Option(
    "--device", help="Where the engine runs: cpu, cuda (a GPU through CuPy: pip install 'cca\\[gpu]') or auto "
                     "(cuda when a GPU can run it, else cpu); overrides reconstruct.device \\[default: cpu].",
    show_default=False)]


def check_cluster_options(workers: int | None, scheduler: str | None) -> None:
    """Refuse ``--workers`` given with ``--scheduler`` (they exclude each other), and a bad worker count.

    Parameters
    ----------
    workers : int, optional
        ``--workers``: local Dask worker processes.
    scheduler : str, optional
        ``--scheduler``: address of an existing Dask scheduler.

    Raises
    ------
    ConfigError
        One line naming both options when both are given, or ``--workers`` when its count is refused.
    """
    from cca_cli.workflows.cluster import check_workers

    if workers is not None and scheduler:
        raise ConfigError(f"--workers {workers} and --scheduler {scheduler} exclude each other: give --workers for "
                          "local worker processes or --scheduler for an existing cluster (its workers are its own)")
    check_workers(workers)


def cluster_options(workers: int | None, scheduler: str | None, *, used: bool):
    """Context in which tiled reconstructions run on ``--workers`` or ``--scheduler`` (checked first).

    ``used`` says whether anything will run on Dask (a config with ``reconstruct.tiles``); when not,
    the options are only noted as unused.
    """
    import contextlib

    from cca_cli.workflows.cluster import check_scheduler, scheduler_timeout, use_cluster

    check_cluster_options(workers, scheduler)
    if not used:
        if workers is not None or scheduler:
            import logging

            logging.getLogger("cca").warning("--workers/--scheduler apply to tiled reconstructions "
                                             "(reconstruct.tiles); this run has none, so they are unused")
        return contextlib.nullcontext()
    if scheduler:
        check_scheduler(scheduler, scheduler_timeout())
    return use_cluster(workers, scheduler)


def section_from_options(model: type[SectionT], base: BaseModel | None = None, *, names: dict[str, str] | None = None,
                         **values) -> SectionT:
    """A config section from ``base`` (or the defaults) with the option values that were given on top.

    Parameters
    ----------
    model : type
        The section's model (``HdrSection`` …).
    base : BaseModel, optional
        Section whose values the options override (e.g. from ``--config``).
    names : dict, optional
        Option spelling of keys whose option is not ``--<key-with-dashes>`` (``{"mtf_threshold": "--threshold"}``).
    **values
        Option values by key; None means the option was not given.

    Raises
    ------
    ConfigError
        One line naming the option (``--noise-floor: …``) when a value is invalid.
    """
    data = base.model_dump() if base is not None else {}
    data.update({k: v for k, v in values.items() if v is not None})
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = str(err["loc"][0]) if err["loc"] else ""
        option = (names or {}).get(key, "--" + key.replace("_", "-"))
        shown = "input" in err and not isinstance(err["input"], dict) and err["type"] != "value_error"
        got = f" (got {short(err['input'])})" if shown else ""
        raise ConfigError(f"{option}: {error_message(err)}{got}") from None
