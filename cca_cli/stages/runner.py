"""Run the configured stages in order, skipping those whose output is up to date.

A stage's output is up to date when it exists, is complete (a report folder
still holds every file it lists) and records the same hash of the config
sections the stage reads and the same SHA-256 of its input files; a
reconstruction also records the engine and options its section resolved to
(cca's defaults included), and one that another cca's defaults made is
recomputed. Outputs
appear atomically, so an interrupted run resumes at the first stage without a
complete, matching output. One run at a time writes in a folder (a lock file);
temporaries that killed runs left are removed, and an output cca did not write
is never replaced.
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass
from pathlib import Path

from pydantic import BaseModel

from cca_cli.config.model import RunConfig
from cca_cli.errors import ConfigError, OutputError, OutputExistsError, check_interrupt
from cca_cli.io.h5 import file_sha256, read_provenance, unique_paths
from cca_cli.io.lock import folder_lock
from cca_cli.io.outputs import check_folder, folder_complete, foreign_part, prepare_folder, remove_stale_temporaries
from cca_cli.stages import hdr as hdr_stage
from cca_cli.stages import ingest as ingest_stage
from cca_cli.stages import reconstruct as reconstruct_stage
from cca_cli.stages import register as register_stage
from cca_cli.stages import report as report_stage
from cca_cli.stages import simulate as simulate_stage
from cca_cli.stages.progress import ProgressFn, silent
from cca_cli.stages.provenance import config_hash, pick_sections, section_yaml, stage_provenance

__all__ = ["StagePlan", "StageOutcome", "plan_stages", "config_hash", "section_yaml", "stage_provenance",
           "pick_sections", "is_up_to_date", "run_pipeline", "prepare_folder", "default_out_dir"]

OUTPUTS = {"simulate": "captures.h5", "ingest": "raw.h5", "hdr": "hdr.h5", "register": "registered.h5",
           "reconstruct": "recon.h5", "report": "report"}
#: Inputs of a stage that runs first in run.stages; otherwise its input is the previous stage's output.
INPUTS = {"simulate": (), "ingest": (), "hdr": ("raw.h5",), "register": ("hdr.h5",), "reconstruct": ("captures.h5",),
          "report": ("recon.h5",)}
SECTIONS = {"simulate": simulate_stage.SECTIONS, "ingest": ingest_stage.SECTIONS, "hdr": hdr_stage.SECTIONS,
            "register": register_stage.SECTIONS, "reconstruct": reconstruct_stage.SECTIONS,
            "report": report_stage.SECTIONS}
#: Each stage's ``run(*args, output, provenance=…, force=…, progress=…)``.
RUNS = {"simulate": simulate_stage.run, "ingest": ingest_stage.run, "hdr": hdr_stage.run,
        "register": register_stage.run, "reconstruct": reconstruct_stage.run, "report": report_stage.run}


@dataclass(frozen=True)
class StagePlan:
    """One stage of a run: its output, inputs and the config sections it reads."""

    name: str
    output: Path
    inputs: tuple[Path, ...]
    sections: tuple[str, ...]


@dataclass(frozen=True)
class StageOutcome:
    """What happened to a stage: ``ran`` or ``skipped`` (up to date)."""

    name: str
    status: str
    output: Path
    seconds: float
    result: object = None


def default_out_dir(config_path: Path | None) -> Path:
    """``./cca-runs/<config name>`` (``headline`` for the built-in default)."""
    return Path("cca-runs") / (config_path.stem if config_path else "headline")


def plan_stages(config: RunConfig, out_dir: Path) -> list[StagePlan]:
    """The stages of ``config.run.stages`` with their files under ``out_dir``."""
    plans = []
    for name in config.run.stages:
        if name == "ingest":
            inputs = tuple(_manifest_inputs(config))
        elif plans and name != "simulate":
            inputs = (plans[-1].output,)
        else:
            inputs = tuple(out_dir / f for f in INPUTS[name])
        plans.append(StagePlan(name, out_dir / OUTPUTS[name], inputs, SECTIONS[name]))
    return plans


def _manifest_inputs(config: RunConfig) -> list[Path]:
    """The manifest and the files it lists (hashed into the ingest stage's provenance)."""
    from cca_cli.io.manifest import manifest_files

    return manifest_files(config.ingest.manifest)


def _recorded_provenance(output: Path) -> dict:
    if output.is_dir():
        try:
            return json.loads((output / report_stage.REPORT_JSON).read_text()).get("provenance", {})
        except (OSError, ValueError):
            return {}
    return read_provenance(output) if output.exists() else {}


def is_up_to_date(plan: StagePlan, digest: str, section: BaseModel | None = None) -> bool:
    """Whether ``plan.output`` exists, complete, with the same config hash and input hashes (and, for a
    reconstruction given its ``section``, made with today's engine defaults: without it that is not checked,
    while :func:`run_pipeline` checks it)."""
    return _state(plan, digest, section) == "current"


@functools.lru_cache(maxsize=64)
def _cached_sha256(path: str, size: int, mtime_ns: int) -> str:
    return file_sha256(path)


def _sha256(path: Path) -> str:
    """SHA-256 of a file, computed once per version of it (the run checks each input twice)."""
    stat = Path(path).stat()
    return _cached_sha256(str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)


def _state(plan: StagePlan, digest: str, section: BaseModel | None = None) -> str:
    """``current``; ``incomplete`` (cca's, same config and inputs, files missing, or a report folder that lost
    report.json); ``outdated`` (a reconstruction of the same config and inputs whose engine and options, cca's
    defaults included, were others: made by another cca; checked when its ``section`` is given); ``other``
    (another config or inputs); ``foreign`` (not written by cca, or unreadable)."""
    part = foreign_part(plan.output)
    if part is not None:
        # a file of the user's in a folder cca wrote: the folder is never replaced, but where it is up to date
        # nothing needs replacing either
        inside = plan.output.is_dir() and Path(part) != plan.output
        return "current" if inside and _state_of_own(plan, digest, section) == "current" else "foreign"
    return _state_of_own(plan, digest, section)


def _state_of_own(plan: StagePlan, digest: str, section: BaseModel | None) -> str:
    """:func:`_state` of an output cca wrote."""
    if plan.output.is_dir() and not (plan.output / report_stage.REPORT_JSON).is_file():
        return "incomplete"  # cca's folder (its marker lists its files) without the file that records its provenance
    recorded = _recorded_provenance(plan.output)
    if plan.output.is_dir() and not recorded:
        return "incomplete"  # its report.json damaged: the report is made again
    if recorded.get("config_hash") != digest:
        return "other"
    try:
        inputs = json.loads(recorded.get("inputs", "[]"))
        # each file once on both sides (outputs of older versions may list a CSV manifest twice)
        recorded_once = unique_paths([i["path"] for i in inputs])
        hashes = {i["path"]: i["sha256"] for i in inputs}
        same_inputs = [hashes[p] for p in recorded_once] == [_sha256(p) for p in unique_paths(plan.inputs)]
    except (OSError, ValueError, KeyError, TypeError):
        same_inputs = False
    if not same_inputs:
        return "other"
    if plan.name == "reconstruct" and section is not None:
        from cca_cli.stages.reconstruct import engine_recipe

        if recorded.get("engine_recipe") != engine_recipe(plan.inputs[0], section):
            return "outdated"
    if plan.output.is_dir() and not folder_complete(plan.output):
        return "incomplete"
    return "current"


def run_pipeline(config: RunConfig, out_dir: Path, *, force: bool = False, progress: ProgressFn = silent,
                 on_stage=None, source: str | Path | None = None) -> list[StageOutcome]:
    """Run the configured stages; skip up-to-date ones unless ``force``.

    Parameters
    ----------
    config : RunConfig
    out_dir : Path
        Directory of the stage files.
    force : bool
        Recompute every stage and overwrite existing outputs.
    progress : callable
        Receives :class:`~cca_cli.stages.progress.ProgressEvent` objects.
    on_stage : callable, optional
        Called with ``(plan, "start" | "skipped")`` before each stage, and with ``(plan, "outdated")`` before
        a reconstruction of the same config and inputs that another cca's engine defaults made is recomputed.
    source : str or Path, optional
        The config file, named in messages about the run's size.

    Raises
    ------
    OutputExistsError
        If an output exists but was made from another config or inputs and ``force`` is not set.
    OutputError
        If an output exists that cca did not write (even with ``force``), or the folder cannot be written.
    ResourceError
        If a stage needs more memory or disk than the machine has (checked before it starts).
    RunLockedError
        If another run is writing in ``out_dir``.
    """
    out_dir = Path(out_dir)
    check_folder(out_dir)
    plans = plan_stages(config, out_dir)
    made = [folder for folder in (out_dir, *out_dir.parents) if not folder.exists()]   # deepest first
    if not made:   # another run writing here is said first: its outputs may look outdated meanwhile
        with folder_lock(out_dir):
            _check_before_running(config, plans, force=force, source=source)
            remove_stale_temporaries(out_dir)
            return _run_stages(config, plans, force=force, progress=progress, on_stage=on_stage, source=source)
    _check_before_running(config, plans, force=force, source=source)
    prepare_folder(out_dir)
    try:
        with folder_lock(out_dir):
            return _run_stages(config, plans, force=force, progress=progress, on_stage=on_stage, source=source)
    except BaseException:
        _remove_empty(made)   # the folders this run made, where a failure left nothing
        raise


def _remove_empty(folders: list[Path]) -> None:
    """Remove each of ``folders`` (deepest first) that nothing is left in: this run made them."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:   # something is in it, or it is gone: its parents stay too
            return


def _check_before_running(config: RunConfig, plans: list[StagePlan], *, force: bool, source) -> None:
    """Refuse, before anything runs or is created, what would stop the run later: an output cca did not write,
    one made from another config (without ``force``), a simulation the machine cannot hold."""
    from cca_cli.stages.footprint import check_footprint, simulate_footprint

    simulate = None
    rewritten: set[Path] = set()
    for plan in plans:  # the same decisions as _run_stages, without running anything
        exists = plan.output.exists() or plan.output.is_symlink()
        state = _state(plan, config_hash(pick_sections(config, plan.sections)), config.reconstruct) if exists else None
        if state == "foreign":
            _refuse_existing(plan, state)
        if exists and not force and not rewritten.intersection(plan.inputs):
            if state == "other" and not _resumes(plan, config.reconstruct):
                _refuse_existing(plan, state)
            if state == "current":
                continue
        if exists and foreign_part(plan.output) is not None:   # to be replaced, and a file of the user's is in it
            _refuse_existing(plan, "foreign")
        rewritten.add(plan.output)
        if plan.name == "simulate":
            simulate = plan
        if plan.name == "reconstruct":
            from cca_cli.workflows.recovery import check_device

            check_device(config.reconstruct)
    if simulate is not None:
        check_footprint(simulate_footprint(config), simulate.output, source=source)


def _resumes(plan: StagePlan, section) -> bool:
    """Whether an outdated recon.h5 has beside it the checkpoint of a reconstruction of these very captures and
    section: a run that began replacing it (with ``--force``, say) and was stopped goes on from there, without
    ``--force`` (the output was already being replaced when it stopped)."""
    if plan.name != "reconstruct" or section is None or not plan.inputs:
        return False
    from cca_cli.io.checkpoint import checkpoint_path, read_checkpoint
    from cca_cli.stages.reconstruct import checkpoint_fingerprint, engine_recipe

    path = checkpoint_path(plan.output)
    if not path.is_file():
        return False
    saved = read_checkpoint(path)
    if saved is None:
        return False
    try:   # what the stage's provenance will hold, from the run's cached hashes (no further read of the captures)
        inputs = [{"path": str(p), "sha256": _sha256(Path(p))} for p in unique_paths(plan.inputs)]
        provenance = {"inputs": json.dumps(inputs), "engine_recipe": engine_recipe(plan.inputs[0], section)}
        return saved.fingerprint == checkpoint_fingerprint(section, provenance, plan.inputs[0])
    except (OSError, ValueError, KeyError):
        return False


def _refuse_existing(plan: StagePlan, state: str) -> None:
    if state == "foreign":
        part = foreign_part(plan.output)
        if part is not None and Path(part) != plan.output:   # a folder cca wrote, holding a file it did not
            raise OutputError(
                f"{plan.output}: cca wrote this folder, but not {Path(part).relative_to(plan.output)} in it, so the "
                "folder is never replaced, not even with --force; move that file away, or choose another output "
                "folder")
        raise OutputError(
            f"{plan.output}: exists but cca did not write it (or cannot read it: a damaged file), so it is never "
            "replaced, not even with --force; move it away, or choose another output folder")
    raise OutputExistsError(f"{plan.output}: exists but was made from another config or inputs; "
                            "use --force to recompute it (--force recomputes every stage of the run), or choose "
                            "another output folder")


def _run_stages(config: RunConfig, plans: list[StagePlan], *, force: bool, progress: ProgressFn, on_stage,
                source) -> list[StageOutcome]:
    from cca_cli.stages.footprint import check_footprint, reconstruct_footprint, report_footprint, simulate_footprint

    outcomes = []
    rewritten: set[Path] = set()
    for plan in plans:
        check_interrupt()
        sections = pick_sections(config, plan.sections)
        digest = config_hash(sections)
        if plan.output.exists() or plan.output.is_symlink():
            state = _state(plan, digest, config.reconstruct)
            if state == "foreign":
                _refuse_existing(plan, state)
            if state == "outdated" and not force and on_stage:
                on_stage(plan, "outdated")
            # An output made from an input this run just rewrote is stale by construction: recompute it.
            if not force and not rewritten.intersection(plan.inputs):
                if state == "other" and not _resumes(plan, config.reconstruct):
                    _refuse_existing(plan, state)
                if state == "current":
                    if on_stage:
                        on_stage(plan, "skipped")
                    outcomes.append(StageOutcome(plan.name, "skipped", plan.output, 0.0))
                    _check_crop(config, plans, plan, source)
                    continue
        if on_stage:
            on_stage(plan, "start")
        start = time.perf_counter()
        provenance = stage_provenance(plan.name, sections, plan.inputs)
        if plan.name == "simulate":
            check_footprint(simulate_footprint(config), plan.output, source=source)
            args = (config,)
        elif plan.name == "ingest":
            args = (plan.inputs[0],)
        else:  # the input file and the stage's one section
            if plan.name == "reconstruct":
                check_footprint(reconstruct_footprint(plan.inputs[0], config.reconstruct), plan.output,
                                source=plan.inputs[0])
            elif plan.name == "report":
                check_footprint(report_footprint(plan.inputs[0]), plan.output, source=plan.inputs[0])
            args = (plan.inputs[0], getattr(config, plan.sections[0]))
        result = RUNS[plan.name](*args, plan.output, provenance=provenance, force=True, progress=progress)
        check_interrupt()
        outcomes.append(StageOutcome(plan.name, "ran", plan.output, time.perf_counter() - start, result))
        rewritten.add(plan.output)
        _check_crop(config, plans, plan, source)
    return outcomes


def _check_crop(config: RunConfig, plans: list[StagePlan], done: StagePlan, source) -> None:
    """Once ingest has written the frames: a ``registration.crop_xywh`` they cannot hold is refused before the later
    stages (hdr) spend their time, as register itself would refuse it."""
    crop = config.registration.crop_xywh if config.registration is not None else None
    if done.name != "ingest" or crop is None or "register" not in [p.name for p in plans]:
        return
    from cca_cli.io.h5 import open_input

    with open_input(done.output) as handle:
        if "/raw/frames" not in handle:
            return
        h, w = handle["/raw/frames"].shape[-2:]
    x0, y0, cw, ch = (int(v) for v in crop)
    if x0 < 0 or y0 < 0 or x0 + cw > w or y0 + ch > h:
        where = f"{source}: " if source else ""
        raise ConfigError(f"{where}registration.crop_xywh: ({x0}, {y0}, {cw}, {ch}) does not fit in the {w}x{h} px "
                          f"frames of {done.output}; fix it (hdr and register have not run)")
