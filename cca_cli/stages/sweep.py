"""Parameter sweeps: many simulate → reconstruct → report runs of one config, on Dask.

A sweep is a base :class:`RunConfig` and a :class:`SweepSection`: explicit
points (override dicts whose keys change together, like ``array.grid`` and
``array.overlap`` in the overlap study) crossed with the cartesian product of
``parameters``. Every point is a full run in ``<sweep dir>/points/<point id>``
with its own seed; the point id is a readable slug plus a hash of the point's
effective overrides, so the same parameters always land in the same directory.

Resumability comes in two layers: a point whose ``point.json`` records the
same full config is not resubmitted at all, and a point that was interrupted
resumes at its first incomplete stage (:func:`run_pipeline` skips up-to-date
stages). Every file appears atomically, the sweep table included.

A sweep run into the folder of an earlier sweep of the same base config and
study adds to it: the table and figures hold the complete points of both
(:func:`earlier_points`). A folder of another base config or study is refused
unless ``force``.
"""

from __future__ import annotations

import csv
import hashlib
import io
import itertools
import json
import math
import re
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import yaml

from cca_cli.config.load import apply_overrides, dump_config, parse_config
from cca_cli.config.messages import accepted_keys
from cca_cli.config.model import RunConfig, SweepSection
from cca_cli.engines.registry import ENGINES, resolve
from cca_cli.errors import CcaError, ConfigError, OutputExistsError
from cca_cli.io.h5 import Provenance, atomic_h5, atomic_path, remove_temporaries, write_dataset
from cca_cli.io.outputs import is_cca_hdf5, starts_with
from cca_cli.io.sweep_table import read_table, read_table_layout
from cca_cli.workflows.scenes import check_scene
from cca_cli.workflows.cluster import (SchedulerLost, check_scheduler, check_workers, open_client, scheduler_gone,
                                      scheduler_lost, scheduler_timeout)

__all__ = [
    "PAPER_STUDIES",
    "SchedulerLost",
    "METRICS",
    "SweepPoint",
    "PointCost",
    "parse_set",
    "study_spec",
    "check_key",
    "expand_points",
    "point_cost",
    "run_point",
    "cached_result",
    "earlier_points",
    "earlier_rows",
    "open_client",
    "check_scheduler",
    "check_workers",
    "scheduler_timeout",
    "run_sweep",
    "pending_row",
    "interrupted_row",
    "table_columns",
    "TABLE_COLUMNS",
    "write_table",
    "read_table",
    "default_axes",
    "write_sweep_figures",
]

POINT_JSON = "point.json"
#: How a point.json and a sweep.csv that cca wrote begin (so that --force and re-runs recognise them).
POINT_JSON_START = '{\n  "config_digest"'
CSV_START = "point_id,index,status,"

#: Report metrics copied into the sweep table.
METRICS = ("sar", "grid_n", "n_images", "iterations", "recon_seconds", "mtf20_observed_px", "mtf20_recovered_px",
           "resolution_gain", "rmse_observed", "rmse_recovered", "rmse_observed_band", "rmse_recovered_band")

_OVERLAPS = (0.0, 0.2, 0.41, 0.5, 0.61, 0.75, 0.77)


def _grid_near_sar(sar: float, overlap: float) -> int:
    """Odd grid whose SAR at ``overlap`` is nearest ``sar`` (so a centre image exists)."""
    step = 1.0 - overlap
    candidates = range(1, 200, 2)
    return min(candidates, key=lambda n: (abs((n - 1) * step + 1 - sar), n))


#: The paper's three studies (Holloway et al. 2016, Figs. 6-8), applied to any base config.
PAPER_STUDIES: dict[str, SweepSection] = {
    "overlap": SweepSection(
        study="overlap",
        points=[{"array.overlap": o, "array.grid": _grid_near_sar(10.0, o)} for o in _OVERLAPS],
        x="array.overlap", highlight=[0.0, 0.41, 0.5, 0.75]),
    "sar": SweepSection(study="sar", parameters={"array.grid": [1, 3, 7, 9, 13, 29]},
                        points=[{"array.overlap": 0.61}], x="sar"),
    "noise": SweepSection(study="noise", points=[{"array.overlap": 0.61}],
                          parameters={"array.grid": [1, 3, 7, 9, 13, 29], "noise.snr_db": [10, 20, 30]},
                          x="sar", group="noise.snr_db"),
    "grid": SweepSection(study="grid"),
}


@dataclass(frozen=True)
class SweepPoint:
    """One point of a sweep.

    Attributes
    ----------
    index : int
        Position in the sweep (also the seed offset).
    point_id : str
        Directory name: readable slug + short hash of ``overrides``.
    overrides : dict
        Effective dotted-key overrides of the base config (the seed included).
    out_dir : Path
        The point's run directory.
    config : RunConfig or None
        The point's config; None when its values are invalid (see ``error``).
    error : str or None
        Why the point cannot run (an invalid value), recorded in the table.
    """

    index: int
    point_id: str
    overrides: dict[str, Any]
    out_dir: Path
    config: RunConfig | None
    error: str | None = None


@dataclass(frozen=True)
class PointCost:
    """Size of one point: captures, per-capture grid m, object grid M and iteration cap."""

    images: int
    lowres_px: int
    hires_px: int
    iterations: int

    @property
    def work(self) -> float:
        """Captured pixels processed per iteration: images × m²."""
        return float(self.images) * self.lowres_px ** 2


def parse_set(text: str) -> tuple[str, list[Any]]:
    """``key=v1,v2,…`` → ``(key, [v1, v2, …])``, each value read as YAML (numbers stay numbers).

    Raises
    ------
    ConfigError
        If there is no ``=`` or no value.
    """
    key, sep, values = text.partition("=")
    key = key.strip()
    if not sep or not key or not values.strip():
        raise ConfigError(f"--set {text!r}: expected key=value[,value…], e.g. --set array.overlap=0,0.41,0.61")
    parsed = []
    for raw in values.split(","):
        try:
            parsed.append(yaml.safe_load(raw.strip()))
        except yaml.YAMLError:
            parsed.append(raw.strip())
    return key, parsed


def study_spec(config: RunConfig, study: str, *, sets: list[str] = (), source: str = "config") -> SweepSection:
    """The sweep spec that `cca sweep <study>` runs on ``config``.

    The config's own ``sweep:`` section when present (it must be of kind
    ``study``, except for ``grid`` which accepts any), else the paper's
    default for ``study``; ``--set`` values add to (or replace) its parameters.
    """
    if study not in PAPER_STUDIES:
        raise ConfigError(f"unknown study {study!r}; choose one of {', '.join(PAPER_STUDIES)}")
    spec = config.sweep
    if spec is None:
        spec = PAPER_STUDIES[study]
    elif study != "grid" and spec.study != study:
        raise ConfigError(f"{source}: sweep.study is {spec.study!r}, not {study!r}; "
                          f"run `cca sweep {spec.study} {source}` or change sweep.study")
    if sets:
        parameters = dict(spec.parameters)
        for text in sets:
            key, values = parse_set(text)
            parameters[key] = values
        spec = spec.model_copy(update={"parameters": parameters})
    if not spec.points and not spec.parameters:
        raise ConfigError(f"{source}: nothing to sweep; give sweep.parameters / sweep.points in the config "
                          "or --set key=v1,v2 on the command line")
    return spec


def check_key(dotted: str, *, source: str = "sweep") -> None:
    """Raise :class:`ConfigError` naming ``dotted`` unless it is a config key a sweep may change."""
    parts = dotted.split(".")
    fields = RunConfig.model_fields
    if len(parts) < 2 or parts[0] not in fields or parts[0] in ("sweep", "run"):
        sections = ", ".join(k for k in fields if k not in ("sweep", "run"))
        raise ConfigError(f"{source}: {dotted}: not a sweepable key; use section.key with a section of {sections}")
    keys = accepted_keys(RunConfig, (parts[0], parts[1]))
    if parts[1] not in keys:
        raise ConfigError(f"{source}: {dotted}: unknown key; accepted keys in {parts[0]}: {', '.join(sorted(keys))}")
    if len(parts) > 2 and dotted.rsplit(".", 1)[0] != "reconstruct.options":
        raise ConfigError(f"{source}: {dotted}: {parts[0]}.{parts[1]} has no sub-keys")


def _slug(overrides: dict[str, Any]) -> str:
    bits = []
    for key, value in overrides.items():
        if key == "noise.seed":
            continue
        name = key.rsplit(".", 1)[-1].replace("_", "")
        text = f"{value:g}" if isinstance(value, float) else str(value)
        bits.append(f"{name}{text}")
    slug = re.sub(r"[^A-Za-z0-9.+-]+", "_", "-".join(bits)) or "base"
    return slug[:48]


def _hash(data: Any) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


def config_digest(config: RunConfig) -> str:
    """Hash of a point's full config, the output directory left out."""
    data = config.model_dump(mode="json")
    data["run"]["out_dir"] = None
    data["sweep"] = None
    return _hash(data)


def expand_points(base: RunConfig, spec: SweepSection, sweep_dir: Path, *, source: str = "sweep") -> list[SweepPoint]:
    """Every point of ``spec`` on ``base``: explicit points × the cartesian product of parameters.

    Each point gets ``noise.seed = base seed + index`` unless the sweep sets
    ``noise.seed``, and ``reconstruct.options.threads = 1`` unless the config
    sets it (the sweep parallelises across points, not inside them). The index
    is the point's position in the sweep; in a folder where earlier sweeps ran
    points, a point one of them finished keeps its index, and a new one takes
    its position where no finished point holds it, else the next after the
    folder's last, so that the folder's table never holds one index (or
    derived seed) twice.

    Raises
    ------
    ConfigError
        If a key is not a config key. Invalid *values* do not raise: that
        point carries the error (``cca sweep`` then refuses the sweep before
        any point runs, and ``--dry-run`` lists it as invalid).
    """
    for key in list(spec.parameters) + [k for p in spec.points for k in p]:
        check_key(key, source=source)
    for key, values in spec.parameters.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{source}: {key}: give a non-empty list of values")
    explicit = spec.points or [{}]
    product = [dict(zip(spec.parameters, combo)) for combo in itertools.product(*spec.parameters.values())]
    seeded = "noise.seed" in spec.parameters or any("noise.seed" in p for p in spec.points)
    known = _indices_in_folder(Path(sweep_dir), seeded)
    taken = set(known.values())
    free = (i for i in itertools.count(max(taken, default=-1) + 1) if i not in taken)
    points = []
    for position, (fixed, varied) in enumerate(itertools.product(explicit, product)):
        overrides = {**fixed, **varied}
        # A point an earlier sweep in the folder finished keeps its index (and seed); another takes its position in
        # this sweep where no finished point holds it (an interrupted point resumes), else the next after the
        # folder's last: every row of the folder's table has its own index and noise draw.
        key = _values_key(overrides, seeded)
        index = known[key] if key in known else (position if position not in taken else next(free))
        taken.add(index)
        if "noise.seed" not in overrides:
            overrides["noise.seed"] = base.noise.seed + index
        point_id = f"{_slug(overrides)}-{_hash(overrides)[:8]}"
        points.append(_make_point(base, index, point_id, overrides, Path(sweep_dir) / "points" / point_id,
                                  source=source))
    return points


def _values_key(overrides: dict[str, Any], seeded: bool) -> str:
    """A point's swept values (its seed only where the sweep sets it, ``seeded``): what makes it the same point."""
    values = overrides if seeded else {k: v for k, v in overrides.items() if k != "noise.seed"}
    return json.dumps(values, sort_keys=True, default=str)


def _indices_in_folder(sweep_dir: Path, seeded: bool) -> dict[str, int]:
    """The index of each point earlier sweeps left in ``sweep_dir``, by :func:`_values_key` of its swept values
    (a point whose record names no index is left out)."""
    found = {}
    for directory in _point_dirs(sweep_dir):
        record = _point_record(directory)
        overrides = None if record is None else record.get("overrides")
        index = None if record is None else record.get("index")
        if isinstance(overrides, dict) and isinstance(index, int) and not isinstance(index, bool):
            found.setdefault(_values_key(overrides, seeded), index)
    return found


def _make_point(base: RunConfig, index: int, point_id: str, overrides: dict[str, Any], out_dir: Path, *,
                source: str) -> SweepPoint:
    """The point ``base`` + ``overrides`` run in ``out_dir`` (one thread per point unless the config says)."""
    base = base.model_copy(update={"sweep": None})
    candidates = ENGINES.values() if base.reconstruct.engine == "auto" else [ENGINES[base.reconstruct.engine]]
    takes_threads = all("threads" in entry.option_names() for entry in candidates)
    extra = {"run.out_dir": str(out_dir)}
    engine = overrides.get("reconstruct.engine", base.reconstruct.engine)
    explicit_threads = "threads" in base.reconstruct.options or "reconstruct.options.threads" in overrides
    if takes_threads and engine == base.reconstruct.engine and not explicit_threads:
        extra["reconstruct.options.threads"] = 1
    try:
        config = apply_overrides(base, {**overrides, **extra}, source=f"{source} point {point_id}")
        if "simulate" in config.run.stages:
            check_scene(config.scene)   # a chart that does not fit fails this point before any runs
        error = None
    except ConfigError as exc:
        config, error = None, str(exc)
    return SweepPoint(index, point_id, overrides, out_dir, config, error)


def point_cost(point: SweepPoint) -> PointCost | None:
    """Captures and grid sizes of a point, from its numbers alone (nothing is simulated or allocated)."""
    if point.config is None:
        return None
    from cca_cli.stages.footprint import simulation_sizes

    try:
        sizes = simulation_sizes(point.config)
        _, options = resolve(point.config.reconstruct.engine, "simulation", point.config.reconstruct.given())
        return PointCost(int(sizes.images), int(sizes.lowres_px), int(sizes.hires_px), options.max_iterations)
    except (CcaError, ValueError, OverflowError):
        return None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    message = text[0] if text else ""
    return message if isinstance(exc, CcaError) else f"{type(exc).__name__}: {message}"


def _metrics(summary: dict) -> dict[str, Any]:
    grid = summary.get("grid") or [None]
    return {
        "sar": summary.get("sar"), "grid_n": grid[0], "n_images": summary.get("n_images"),
        "iterations": summary.get("iterations"), "recon_seconds": summary.get("seconds"),
        "mtf20_observed_px": summary.get("mtf20_observed_px"), "mtf20_recovered_px": summary.get("mtf20_recovered_px"),
        "resolution_gain": summary.get("resolution_gain"), "rmse_observed": summary.get("rmse_observed"),
        "rmse_recovered": summary.get("rmse_recovered"),
        "rmse_observed_band": summary.get("rmse_observed_band"),
        "rmse_recovered_band": summary.get("rmse_recovered_band"),
    }


def run_point(config_data: dict, out_dir: str, *, force: bool = False, index: int | None = None,
              overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run one point's pipeline (a Dask task); never raises.

    Parameters
    ----------
    config_data : dict
        The point's config as JSON-ready data (``RunConfig.model_dump(mode="json")``).
    out_dir : str
        The point's directory.
    force : bool
        Recompute every stage.
    index, overrides : optional
        The point's place in its sweep and its overrides, kept in ``point.json``: a later sweep into the
        same folder puts the point in its table (:func:`earlier_points`).

    Returns
    -------
    dict
        ``status`` ("ok" or "failed"), ``error`` (one line), ``wall_s``, the
        stage outcomes and the report metrics (:data:`METRICS`).
    """
    from cca_cli.stages.report import REPORT_JSON
    from cca_cli.stages.runner import run_pipeline

    start = time.perf_counter()
    directory = Path(out_dir)
    try:
        config = parse_config(config_data, source=str(directory))
        directory.mkdir(parents=True, exist_ok=True)
        remove_temporaries(directory)
        outcomes = run_pipeline(config, directory, force=force)
        report = directory / "report" / REPORT_JSON
        summary = json.loads(report.read_text()) if report.exists() else {}
        result = {"status": "ok", "error": "", "wall_s": round(time.perf_counter() - start, 3),
                  "stages": {o.name: o.status for o in outcomes}, "worker": _worker_name(), **_metrics(summary)}
        record = {"config_digest": config_digest(config), "index": index, "overrides": overrides, "result": result}
        with atomic_path(directory / POINT_JSON, force=True, owned=starts_with(POINT_JSON_START)) as tmp:
            tmp.write_text(json.dumps(record, indent=2, default=str))
        return result
    except Exception as exc:  # a failed point is recorded, the others go on
        return {"status": "failed", "error": _one_line(exc), "wall_s": round(time.perf_counter() - start, 3),
                "traceback": traceback.format_exc(limit=4)}


def _worker_name() -> str:
    """Address of the Dask worker running this task (``local`` outside a worker)."""
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return "local"


def cached_result(point: SweepPoint) -> dict[str, Any] | None:
    """The recorded result of a point that already completed with the same config, else None."""
    if point.config is None:
        return None
    try:
        record = json.loads((point.out_dir / POINT_JSON).read_text())
    except (OSError, ValueError):
        return None
    from cca_cli.stages.report import REPORT_JSON

    if record.get("config_digest") != config_digest(point.config):
        return None
    if not (point.out_dir / "report" / REPORT_JSON).exists():
        return None
    result = dict(record.get("result", {}))
    return result if result.get("status") == "ok" else None


def earlier_points(base: RunConfig, spec: SweepSection, points: list[SweepPoint], sweep_dir: Path, *,
                   force: bool = False, source: str = "sweep") -> list[SweepPoint]:
    """Complete points that earlier sweeps of ``base`` left in ``sweep_dir``, other than ``points``.

    A sweep run into the folder of an earlier one adds its points to the table and figures rather than
    replacing them: these points' rows join the table (:func:`earlier_rows`). A point counts when its
    directory holds a complete run whose config is ``base`` with the point's overrides (kept in its
    ``point.json``, or in the folder's table for points of older cca versions).

    Raises
    ------
    OutputExistsError
        Without ``force``, when the folder's table is of another study, or a complete point in the folder
        (this sweep's own included) was made from another base config: one table cannot hold both. With
        ``force`` those points are left out of the table (their directories stay; this sweep's own points
        are recomputed), and a table of another study is replaced by this sweep's points.
    """
    sweep_dir = Path(sweep_dir)
    study, recorded, order = _recorded_points(sweep_dir)
    if study is not None and study != spec.study:
        if force:
            return []
        raise OutputExistsError(f"{sweep_dir / 'sweep.h5'}: holds a {study} study, not {spec.study}; use --force to "
                                "replace its table with this sweep's points, or choose another --out-dir")
    ours = {p.point_id: p for p in points}
    kept, other = [], None
    for directory in _point_dirs(sweep_dir):
        record = _point_record(directory)
        if record is None:
            continue
        point = ours.get(directory.name)
        if point is None:
            index, overrides = record.get("index"), record.get("overrides")
            if not isinstance(overrides, dict):
                index, overrides = recorded.get(directory.name, (None, None))
            if overrides is None:  # nothing says what the point is
                continue
            point = _make_point(base, index, directory.name, overrides, directory, source=source)
            same = point.config is not None and record.get("config_digest") == config_digest(point.config)
            if same and cached_result(point) is not None:
                kept.append(point)
        else:
            same = point.config is None or record.get("config_digest") == config_digest(point.config)
        if not same and other is None:
            other = directory
    if other is not None and not force:
        raise OutputExistsError(f"{sweep_dir}: holds points made from another base config than {source} "
                                f"({other.relative_to(sweep_dir)} …); use --force to recompute this sweep's points "
                                "and leave the others out of the table, or choose another --out-dir")
    # One table and its figures plot the keys this sweep varies: points that vary others cannot join them.
    key_sets = {frozenset(p.overrides) for p in points}   # explicit points may vary keys together
    foreign = [p for p in kept if frozenset(p.overrides) not in key_sets]
    if foreign and not force:
        theirs = ", ".join(sorted(foreign[0].overrides)) or "nothing"
        ours = ", ".join(sorted({key for p in points for key in p.overrides})) or "nothing"
        raise OutputExistsError(f"{sweep_dir}: holds points of a sweep over {theirs} ({foreign[0].point_id} …), and "
                                f"this one varies {ours}: one table and its figures cannot plot both; choose another "
                                "--out-dir, or use --force to leave those points out of the table")
    kept = [p for p in kept if frozenset(p.overrides) in key_sets]
    return sorted(kept, key=lambda p: (order.get(p.point_id, len(order)), p.index if p.index is not None else 0,
                                       p.point_id))


def earlier_rows(points: list[SweepPoint]) -> list[dict[str, Any]]:
    """Table rows (status ``cached``) of the points :func:`earlier_points` found."""
    return [_row(point, cached_result(point) or {}, "cached") for point in points]


def _recorded_points(sweep_dir: Path) -> tuple[str | None, dict[str, tuple[int | None, dict]], dict[str, int]]:
    """The study of the folder's sweep.h5, each of its rows' index and overrides by point id, and the row order."""
    path = sweep_dir / "sweep.h5"
    if not path.is_file() or not is_cca_hdf5(path):
        return None, {}, {}
    try:
        study, parameters = read_table_layout(path)
        rows = read_table(path)
    except (OSError, KeyError, ValueError, TypeError):
        return None, {}, {}
    recorded, order = {}, {}
    for position, row in enumerate(rows):
        overrides = {key: _table_value(row[key]) for key in parameters if row.get(key) not in (None, "")}
        recorded[str(row.get("point_id"))] = (row.get("index"), overrides)
        order[str(row.get("point_id"))] = position
    return study, recorded, order


def _table_value(value: Any) -> Any:
    """A parameter cell as the config reads it (text cells hold YAML: lists, numbers of mixed columns)."""
    if not isinstance(value, str):
        return value
    try:
        return yaml.safe_load(value)
    except yaml.YAMLError:
        return value


def _point_dirs(sweep_dir: Path) -> list[Path]:
    try:
        return sorted(d for d in (sweep_dir / "points").iterdir() if d.is_dir() and not d.is_symlink())
    except OSError:
        return []


def _point_record(directory: Path) -> dict | None:
    """The point.json cca wrote in ``directory`` (None when there is none or it cannot be read)."""
    path = directory / POINT_JSON
    if not starts_with(POINT_JSON_START)(path):
        return None
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _row(point: SweepPoint, result: dict[str, Any], status: str | None = None) -> dict[str, Any]:
    row = {"point_id": point.point_id, "index": point.index, "status": status or result.get("status", "failed"),
           "error": result.get("error", ""), "wall_s": result.get("wall_s"), "out_dir": str(point.out_dir)}
    row.update({f"param:{k}": v for k, v in point.overrides.items()})
    row.update({k: result.get(k) for k in METRICS})
    return row


def pending_row(point: SweepPoint) -> dict[str, Any]:
    """The table row of a point that had not finished when its sweep was interrupted (status ``pending``)."""
    return _row(point, {"status": "pending", "error": ""})


def interrupted_row(point: SweepPoint) -> dict[str, Any]:
    """A point's row after its sweep was interrupted: from its result on disk (``ok``) if it finished, else
    ``pending`` (a worker may finish a point just before the interrupt reaches the sweep)."""
    done = cached_result(point)
    return pending_row(point) if done is None else _row(point, done, "ok")


def run_sweep(points: list[SweepPoint], client, *, force: bool = False,
              on_row: Callable[[dict[str, Any], int, int], None] | None = None) -> list[dict[str, Any]]:
    """Run every point that is not already complete; return one table row per point, in point order.

    Parameters
    ----------
    points : list of SweepPoint
    client : distributed.Client
        Where the points run (one task each).
    force : bool
        Recompute points (and every stage) even when complete.
    on_row : callable, optional
        Called with ``(row, done, total)`` as each point finishes or is found complete.

    Raises
    ------
    CcaError
        The scheduler went away (one line: the finished points are kept, a re-run does the rest).

    Notes
    -----
    Rows carry ``status`` ``ok`` (ran now), ``cached`` (complete from an
    earlier run), ``failed`` (with ``error``) or ``pending`` (not finished
    when the sweep was interrupted).
    """
    from distributed import as_completed

    rows: dict[int, dict[str, Any]] = {}
    total = len(points)

    def finish(point: SweepPoint, row: dict[str, Any]) -> None:
        rows[point.index] = row
        if on_row:
            on_row(row, len(rows), total)

    futures = {}
    for point in points:
        if point.error is not None:
            finish(point, _row(point, {"status": "failed", "error": point.error}))
            continue
        cached = None if force else cached_result(point)
        if cached is not None:
            finish(point, _row(point, cached, "cached"))
            continue
        future = client.submit(run_point, point.config.model_dump(mode="json"), str(point.out_dir), force=force,
                               index=point.index, overrides=point.overrides, pure=False)
        futures[future] = point
    try:
        for future in as_completed(list(futures)):
            point = futures[future]
            try:
                result = future.result()
            except scheduler_gone():  # below
                raise
            except Exception as exc:  # the worker died or the task was lost
                result = {"status": "failed", "error": _one_line(exc)}
            finish(point, _row(point, result))
    except scheduler_gone():
        kept = sum(cached_result(point) is not None for point in points)
        where = points[0].out_dir.parent if points else "the sweep folder"
        raise scheduler_lost("sweep", f"the finished points are kept in {where} ({kept} of {total})") from None
    except BaseException:
        for future in futures:
            future.cancel()
        raise
    finally:
        for point in points:
            rows.setdefault(point.index, pending_row(point))
    return [rows[p.index] for p in points]


def table_columns(rows: list[dict[str, Any]]) -> list[str]:
    """Column order of the sweep table: identity, parameters, metrics."""
    head = ["point_id", "index", "status", "error", "wall_s"]
    params = []
    for row in rows:
        params += [k for k in row if k.startswith("param:") and k not in params]
    return head + params + list(METRICS) + ["out_dir"]


#: Units and meaning of the sweep table's columns (parameter columns are described by :func:`_column_info`).
TABLE_COLUMNS: dict[str, tuple[str, str]] = {
    "point_id": ("text", "Point directory name: a readable slug of its overrides plus a short hash of them."),
    "index": ("1", "The point's number in the folder's table: its position in the sweep that ran it, or the next "
                   "free number where an earlier sweep's point holds that (also its seed offset)."),
    "status": ("text", "ok (ran now), cached (complete from an earlier run), failed, or pending (interrupted)."),
    "error": ("text", "Why the point failed, in one line; empty otherwise."),
    "wall_s": ("s", "Wall time of the point's whole run (every stage)."),
    "sar": ("1", "Synthetic aperture ratio ((n - 1)·step + d)/d."),
    "grid_n": ("1", "Aperture positions along one side of the grid."),
    "n_images": ("1", "Number of captures."),
    "iterations": ("1", "Iterations the reconstruction ran."),
    "recon_seconds": ("s", "Reconstruction time."),
    "mtf20_observed_px": ("px", "Finest bar width of the observed centre image whose contrast (and every wider "
                                "one's) reaches the report's threshold, in truth-grid pixels."),
    "mtf20_recovered_px": ("px", "Finest bar width of the recovery whose contrast (and every wider one's) reaches "
                                 "the report's threshold, in truth-grid pixels."),
    "resolution_gain": ("1", "mtf20_observed_px / mtf20_recovered_px."),
    "rmse_observed": ("1", "RMSE of the observed centre intensity against the truth (least-squares scale, "
                           "normalised by the truth's maximum)."),
    "rmse_recovered": ("1", "RMSE of the recovered intensity against the truth (least-squares scale, "
                            "normalised by the truth's maximum)."),
    "rmse_observed_band": ("1", "RMSE of the observed centre intensity against the band-limited truth."),
    "rmse_recovered_band": ("1", "RMSE of the recovered intensity against the band-limited truth."),
    "out_dir": ("text", "The point's run directory."),
}

#: Units of a swept config key, from the suffix of its name (SI units appear in key names).
_KEY_UNITS = (("_lp_per_mm", "lp/mm"), ("_m", "m"), ("_s", "s"), ("_db", "dB"), ("_px", "px"), ("_rad", "rad"),
              ("_e", "electrons"))


def _column_info(column: str, kind: str) -> tuple[str, str]:
    """Units and description of a table column; ``kind`` is ``int``, ``float`` or ``text``."""
    if column.startswith("param:"):
        key = column.removeprefix("param:")
        units = "text" if kind == "text" else next((u for suffix, u in _KEY_UNITS if key.endswith(suffix)), "1")
        return units, f"Config value {key} of each point (a swept parameter or the point's seed)."
    return TABLE_COLUMNS.get(column, ("text" if kind == "text" else "1", f"Sweep table column {column}."))


#: Table columns that hold whole numbers (where some rows have them: int64 with ``missing_value``).
_INT_COLUMNS = ("index", "grid_n", "n_images", "iterations")


def _kind(values: list[Any]) -> str:
    """``int`` when every value present is an integer, ``float`` when every one is a number, else ``text``."""
    present = [v for v in values if v is not None]
    if not present or any(isinstance(v, bool) or not isinstance(v, (int, float, np.number)) for v in present):
        return "text"
    return "int" if all(isinstance(v, (int, np.integer)) for v in present) else "float"


def write_table(rows: list[dict[str, Any]], sweep_dir: Path, *, spec: SweepSection, base: RunConfig) -> tuple[Path, Path]:
    """Write ``sweep.csv`` and ``sweep.h5`` atomically into ``sweep_dir``.

    ``sweep.h5`` holds one dataset per column under ``/table``, each with
    ``units`` and ``description`` attributes: integers as int64 (a missing
    value is the ``missing_value`` attribute), other numbers as float64 with
    NaN for missing, text as UTF-8 strings. The root attributes hold the
    provenance with the base config and the sweep spec.
    """
    sweep_dir = Path(sweep_dir)
    columns = table_columns(rows)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([c.removeprefix("param:") for c in columns])
    for row in rows:
        writer.writerow(["" if row.get(c) is None else row.get(c) for c in columns])
    csv_path, h5_path = sweep_dir / "sweep.csv", sweep_dir / "sweep.h5"
    with atomic_path(csv_path, force=True, owned=starts_with(CSV_START)) as tmp:
        tmp.write_text(buffer.getvalue())
    spec_yaml = yaml.safe_dump(spec.model_dump(mode="json"), sort_keys=False)
    provenance = Provenance.make("sweep", dump_config(base.model_copy(update={"sweep": None})) + "sweep:\n"
                                 + "".join(f"  {line}\n" for line in spec_yaml.splitlines()), _hash(spec_yaml))
    with atomic_h5(h5_path, provenance, force=True) as handle:
        group = handle.create_group("table")
        for column in columns:
            values = [row.get(column) for row in rows]
            name = column.removeprefix("param:")
            kind = _kind(values)
            if kind == "text" and all(v is None for v in values) and TABLE_COLUMNS.get(column, ("text",))[0] != "text":
                # a number column missing in every row: as in a sweep where some rows have it
                kind = "int" if column in _INT_COLUMNS else "float"
            units, description = _column_info(column, kind)
            extra = {}
            if kind == "int":
                missing = -1 if all(v >= 0 for v in values if v is not None) else int(np.iinfo(np.int64).min)
                data = np.array([missing if v is None else int(v) for v in values], np.int64)
                if any(v is None for v in values):
                    extra["missing_value"] = missing
            elif kind == "float":
                data = np.array([np.nan if v is None else float(v) for v in values], np.float64)
            else:
                data = ["" if v is None else (json.dumps(v) if isinstance(v, (list, dict)) else str(v)) for v in values]
            write_dataset(group, name, data, units=units, description=description,
                          parameter=column.startswith("param:"), **extra)
        handle.attrs["study"] = spec.study
        handle.attrs["columns"] = json.dumps([c.removeprefix("param:") for c in columns])
    return csv_path, h5_path


def default_axes(spec: SweepSection, points: list[SweepPoint]) -> tuple[str, str | None]:
    """The x column and grouping column of the sweep's plots."""
    varying = []
    for point in points:
        for key in point.overrides:
            if key != "noise.seed" and key not in varying and len({json.dumps(p.overrides.get(key)) for p in points}) > 1:
                varying.append(key)
    study_x = {"overlap": "array.overlap", "sar": "sar", "noise": "sar"}.get(spec.study)
    x = spec.x or study_x or (varying[0] if varying else "index")
    group = spec.group
    if group is None and spec.study == "grid":
        rest = [k for k in varying if k != x]
        group = rest[0] if rest else None
    return x, group


def _value(row: dict[str, Any], column: str):
    value = row.get(f"param:{column}", row.get(column))
    return value


def write_sweep_figures(rows: list[dict[str, Any]], sweep_dir: Path, *, spec: SweepSection,
                        points: list[SweepPoint]) -> list[Path]:
    """Gather what the plots need (table, contrast curves, recovered crops) and draw them into ``sweep_dir/figures``."""
    from cca_cli.report.sweep_figures import SweepPlotData, plot_sweep

    x, group = default_axes(spec, points)
    ok = [r for r in rows if r["status"] in ("ok", "cached")]
    by_id = {p.point_id: p for p in points}
    series = []
    for row in ok:
        xv, gv = _value(row, x), (_value(row, group) if group else None)
        if xv is None:
            continue
        series.append({"x": float(xv), "group": gv, **{k: row.get(k) for k in METRICS}, "index": row["index"],
                       "point_id": row["point_id"]})
    highlight = _highlighted(series, spec.highlight)
    contrast, crops = [], []
    for item in highlight:
        point = by_id[item["point_id"]]
        contrast.append((item, _contrast(point.out_dir)))
        crops.append((item, _crops(point.out_dir)))
    data = SweepPlotData(study=spec.study, x=x, group=group, series=series, contrast=contrast, crops=crops)
    return plot_sweep(data, Path(sweep_dir) / "figures")


def _highlighted(series: list[dict], wanted: list[float] | None) -> list[dict]:
    if not series:
        return []
    if wanted is None:
        chosen = sorted(series, key=lambda s: (str(s["group"]), s["x"]))
        if len(chosen) > 8:
            keep = np.unique(np.linspace(0, len(chosen) - 1, 8).round().astype(int))
            chosen = [chosen[i] for i in keep]
        return chosen
    chosen = []
    for value in wanted:
        near = [s for s in series if math.isclose(s["x"], float(value), rel_tol=1e-6, abs_tol=1e-9)]
        chosen += [s for s in near if s not in chosen]
    return chosen


def _contrast(out_dir: Path) -> dict | None:
    try:
        summary = json.loads((out_dir / "report" / "report.json").read_text())
    except (OSError, ValueError):
        return None
    if "contrast_recovered" not in summary:
        return None
    return {"recovered": summary["contrast_recovered"], "observed": summary["contrast_observed"],
            "threshold": summary.get("mtf_threshold", 0.2)}


def _crops(out_dir: Path) -> dict | None:
    from cca_cli.io.recon import read_recon
    from cca_cli.optics import fft

    try:
        result = read_recon(out_dir / "recon.h5").result
    except (CcaError, OSError, KeyError):
        return None
    recovered, observed = result.intensity, result.observed
    truth = np.abs(result.truth["object"]) ** 2 if "object" in result.truth else None
    size = truth.shape[-1] if truth is not None else recovered.shape[-1]

    def fit(image):
        return image if image.shape[-1] == size else fft.fourier_resample(image[None], size)[0]

    return {"recovered": fit(recovered), "observed": fit(observed),
            "truth": None if truth is None else truth.astype(np.float32)}
