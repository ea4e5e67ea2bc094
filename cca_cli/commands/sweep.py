"""`cca sweep overlap|sar|noise|grid CONFIG`: parameter studies as resumable, parallel runs on Dask."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

from cca_cli.commands.console import console, err_console, handle_errors, styled
from cca_cli.commands.options import ConfigArg, Force, Quiet, Scheduler, Workers, check_cluster_options
from cca_cli.errors import CcaError, ConfigError, keeping_what_finished
from cca_cli.io.lock import folder_lock
from cca_cli.io.outputs import check_folder, prepare_folder

__all__ = ["sweep_app"]

sweep_app = typer.Typer(
    help="Parameter studies: every point a full simulate → reconstruct → report run, in parallel on Dask.",
    no_args_is_help=True,
)

DryRun = Annotated[bool, typer.Option("--dry-run", help="List the points and their cost; run nothing.")]
OutDir = Annotated[Optional[Path], typer.Option("--out-dir", help="Sweep directory (default: run.out_dir or ./cca-runs/<config>-<study>).")]
Sets = Annotated[Optional[list[str]], typer.Option(
    "--set", help="key=v1,v2,… : sweep a config key over values (repeatable; the cartesian product is taken).")]


def _sweep(study: str, config: Path, sets: list[str] | None, workers: int | None, scheduler: str | None,
           dry_run: bool, force: bool, out_dir: Path | None, quiet: bool) -> None:
    from cca_cli.config.load import load_config
    from cca_cli.stages import sweep as sw

    check_cluster_options(workers, scheduler)
    cfg = load_config(config)
    spec = sw.study_spec(cfg, study, sets=list(sets or []), source=str(config))
    sweep_dir = Path(out_dir or cfg.run.out_dir or Path("cca-runs") / f"{config.stem}-{study}")
    check_folder(sweep_dir)
    points = sw.expand_points(cfg, spec, sweep_dir, source=str(config))
    invalid = [p for p in points if p.error]
    if invalid and (len(invalid) == len(points) or not dry_run):   # before any runs; a dry run lists them
        first = invalid[0]
        where = ", ".join(f"{k}={v}" for k, v in first.overrides.items()) or first.point_id
        raise ConfigError(f"{len(invalid)} of {len(points)} points of the sweep are invalid, so none ran; the first "
                          f"({where}): {first.error}; fix or drop that value")
    earlier = sw.earlier_points(cfg, spec, points, sweep_dir, force=force, source=str(config))
    if scheduler and not dry_run:
        sw.check_scheduler(scheduler, sw.scheduler_timeout())
    costs = {p.index: sw.point_cost(p) for p in points}
    images = sum(c.images for c in costs.values() if c)
    work = sum(c.work * c.iterations for c in costs.values() if c)
    kept = f"; the table keeps {len(earlier)} complete points of earlier sweeps" if earlier else ""
    if not quiet or dry_run:
        err_console.print(styled(f"{len(points)} points", "bold",
                                 f"({spec.study} study) → {sweep_dir}: {images} images in all; work ≤ "
                                 f"{work / 1e9:.2f} G pixel-iterations (Σ images × m² × iteration cap){kept}"),
                          highlight=False, soft_wrap=True)
    if dry_run:
        table = Table(title=f"cca sweep {study} --dry-run", header_style="bold")
        for name in ("#", "point id", "overrides", "images", "m", "M", "iterations ≤", "status"):
            is_id = name == "point id"   # an id is what a user copies: keep it whole
            table.add_column(name, no_wrap=is_id,
                             min_width=max((len(p.point_id) for p in points), default=0) if is_id else None)
        for p in points:
            cost = costs[p.index]
            done = sw.cached_result(p) is not None
            table.add_row(str(p.index), p.point_id, ", ".join(f"{k}={v}" for k, v in p.overrides.items()),
                          *(map(str, (cost.images, cost.lowres_px, cost.hires_px, cost.iterations)) if cost else ["—"] * 4),
                          "invalid: " + p.error if p.error else ("complete" if done else "to run"))
        console.print(table)
        return

    columns = (TextColumn("[bold]points"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TimeRemainingColumn(), TextColumn("{task.fields[info]}"))
    counts = {"ok": 0, "cached": 0, "failed": 0}
    prepare_folder(sweep_dir)
    with folder_lock(sweep_dir):
        with Progress(*columns, console=err_console, disable=quiet) as bars:
            task = bars.add_task("points", total=len(points), info="")
            finished = {}

            def on_row(row, done, total):
                finished[row["index"]] = row
                counts[row["status"]] = counts.get(row["status"], 0) + 1
                if row["status"] == "failed" and not quiet:
                    bars.console.print(styled(f"point {row['point_id']} failed:", "red", str(row["error"])),
                                       highlight=False, soft_wrap=True)
                bars.update(task, completed=done,
                            info=f"ran {counts['ok']}  cached {counts['cached']}  failed {counts['failed']}")

            try:
                with sw.open_client(workers=workers, scheduler=scheduler) as client:
                    rows = sw.run_sweep(points, client, force=force, on_row=on_row)
            except KeyboardInterrupt:
                with keeping_what_finished():
                    _write_partial_table(sw, points, finished, earlier, sweep_dir, spec, cfg)
                raise
            except sw.SchedulerLost:   # its scheduler went away: the finished points' table, as after Ctrl-C
                _write_partial_table(sw, points, finished, earlier, sweep_dir, spec, cfg)
                raise
        rows = sw.earlier_rows(earlier) + rows
        everything = earlier + points
        csv_path, h5_path = sw.write_table(rows, sweep_dir, spec=spec, base=cfg)
        figures = sw.write_sweep_figures(rows, sweep_dir, spec=spec, points=everything) if spec.figures else []
    _print_rows(rows, spec, everything)
    console.print(f"table: {csv_path}  {h5_path}")
    for path in figures:
        console.print(f"figure: {path}")
    if counts["failed"]:
        raise CcaError(f"{counts['failed']} of {len(points)} points failed; each one's error is in the error column "
                       f"of {csv_path} (the other points' results are kept)")


def _write_partial_table(sw, points, finished: dict, earlier, sweep_dir: Path, spec, cfg) -> None:
    """After Ctrl-C (or a lost scheduler): the table of the points finished so far (the others ``pending``), before
    cca stops.

    Nothing is written when no point, of this sweep or an earlier one in the folder, has finished; a second
    Ctrl-C while it is written leaves the earlier table (or none): the table is written whole or not at all.
    """
    rows = [finished.get(p.index) or sw.interrupted_row(p) for p in points]
    done = sum(row["status"] != "pending" for row in rows)
    if not done and not earlier:
        return
    csv_path, _ = sw.write_table(sw.earlier_rows(earlier) + rows, sweep_dir, spec=spec, base=cfg)
    err_console.print(f"note: {csv_path} holds the {done} of {len(points)} points finished so far (the others "
                      "pending); run the command again to finish them", highlight=False, soft_wrap=True)


def _print_rows(rows, spec, points) -> None:
    from cca_cli.stages.sweep import default_axes

    x, group = default_axes(spec, points)
    table = Table(title="sweep", header_style="bold")
    params = []
    for row in rows:
        params += [k for k in row if k.startswith("param:") and k != "param:noise.seed" and k not in params]
    for name in ["point", "status"] + [p.removeprefix("param:") for p in params] + ["SAR", "images", "RMSE obs",
                                                                                    "RMSE rec", "MTF20 rec (px)"]:
        table.add_column(name)

    def f(v, fmt="{:.4g}"):
        return "—" if v is None else (fmt.format(v) if isinstance(v, (int, float)) else str(v))

    for row in rows:
        table.add_row(row["point_id"], row["status"] if row["status"] != "failed" else Text("failed", style="red"),
                      *(f(row.get(p)) for p in params), f(row.get("sar"), "{:.2f}"), f(row.get("n_images")),
                      f(row.get("rmse_observed")), f(row.get("rmse_recovered")), f(row.get("mtf20_recovered_px")))
    console.print(table)


def _command(study: str, doc: str):
    @handle_errors
    def command(config: ConfigArg, set_: Sets = None, workers: Workers = None, scheduler: Scheduler = None,
                dry_run: DryRun = False, force: Force = False, out_dir: OutDir = None, quiet: Quiet = False) -> None:
        _sweep(study, config, set_, workers, scheduler, dry_run, force, out_dir, quiet)

    command.__doc__ = doc
    command.__name__ = f"sweep_{study}"
    return command


sweep_app.command("overlap")(_command("overlap", "The paper's overlap study (Fig. 6): RMSE vs overlap at SAR ≈ 10.\n\n"
                                      "Uses CONFIG's sweep: section (study: overlap) or, without one, the paper's points."))
sweep_app.command("sar")(_command("sar", "The paper's SAR study (Fig. 7): contrast and MTF20 vs SAR at 61% overlap."))
sweep_app.command("noise")(_command("noise", "The paper's noise study (Fig. 8): RMSE vs SAR at SNR 10, 20, 30 dB."))
sweep_app.command("grid")(_command("grid", "Any keys: the cartesian product of --set key=v1,v2 (and CONFIG's sweep: section)."))
