"""Rich console, progress bars and the one-line error convention.

Both consoles print text as it is (``markup=False``): paths, keys and values
the user wrote may contain ``[`` and ``]``. Styled words go through
:func:`styled`, never through markup.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import statistics
import sys
from typing import Iterator

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

from cca_cli.errors import CcaError, check_interrupt, noting_interrupts
from cca_cli.io.outputs import disk_full
from cca_cli.stages.progress import ProgressEvent

__all__ = ["console", "err_console", "styled", "print_error", "print_warning", "handle_errors", "progress_reporter",
           "summary_table", "configure_logging", "EXIT_INTERNAL", "stop_note", "recovery_stop_note", "poor_fit_warning", "print_note", "length_text"]

#: Width of tables written to a file or a pipe (a log) when COLUMNS does not say: rich's 80 columns cut point ids
#: and parameter values; a terminal keeps its own width.
LOG_WIDTH = 160


def _width(stream) -> int | None:
    try:
        terminal = stream.isatty()
    except (AttributeError, ValueError):
        terminal = False
    return None if terminal or os.environ.get("COLUMNS") else LOG_WIDTH


console = Console(markup=False, soft_wrap=True, width=_width(sys.stdout))
err_console = Console(stderr=True, markup=False, soft_wrap=True, width=_width(sys.stderr))

#: Exit code of an unexpected failure (a bug): one line, the traceback with --verbose.
EXIT_INTERNAL = 70


def styled(label: str, style: str, rest: str = "") -> Text:
    """``label`` in ``style`` followed by ``rest`` as plain text (no markup is parsed)."""
    return Text.assemble((label, style), " " if rest else "", rest)


def print_error(message: str) -> None:
    """One red ``error:`` line on stderr."""
    err_console.print(styled("error:", "bold red", message), highlight=False, soft_wrap=True)


def print_warning(message: str) -> None:
    """One yellow ``warning:`` line on stderr."""
    err_console.print(styled("warning:", "bold yellow", message), highlight=False, soft_wrap=True)


class _LineHandler(logging.Handler):
    """Prints each library log record as one labelled line: ``note:``, ``warning:`` or ``error:``.

    A message the library starts with ``note:`` is information a user need not act on; other
    warnings ask for attention. With ``--verbose``, information records print as they are.
    """

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = " ".join(self.format(record).split())
            if record.levelno >= logging.ERROR:
                print_error(message)
            elif record.levelno >= logging.WARNING:
                if message.startswith("note:"):
                    print_note(message[len("note:"):].strip())
                else:
                    print_warning(message)
            else:
                err_console.print(message, highlight=False, soft_wrap=True)
        except Exception:  # noqa: BLE001 - logging must never stop a run
            self.handleError(record)


def configure_logging(verbose: bool = False) -> None:
    """Route library log records to one labelled line each on stderr (the only place logging is configured)."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(message)s",
                        handlers=[_LineHandler()], force=True)


def handle_errors(func):
    """Turn expected failures into one red line on stderr and a non-zero exit code."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            with noting_interrupts():
                result = func(*args, **kwargs)
                check_interrupt()  # a Ctrl-C that Python dropped on the way is not a success
            return result
        except typer.Exit:  # an exit code a command chose (a RuntimeError: not a bug)
            raise
        except CcaError as exc:
            print_error(" ".join(str(exc).split()))
            raise typer.Exit(exc.exit_code) from None
        except KeyboardInterrupt:
            err_console.print(styled("interrupted:", "bold red", "every output is whole or absent (a reconstruction "
                                     "keeps its last checkpoint); run the command again to go on from there"),
                              highlight=False, soft_wrap=True)
            raise typer.Exit(130) from None
        except MemoryError:
            print_error("out of memory: the run needs more than this machine has free; make it smaller "
                        "(fewer or smaller images) or free memory")
            raise typer.Exit(5) from None
        except OSError as exc:
            where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
            if disk_full(exc):
                print_error(f"{where}no space left on the device; free some space or write elsewhere")
                raise typer.Exit(5) from None
            print_error(f"{where}{exc.strerror or exc}")
            raise typer.Exit(1) from None
        except Exception as exc:  # a bug: one line for the user, the traceback with --verbose
            logging.getLogger("cca").info("the failure, for a bug report:", exc_info=True)
            first = (str(exc).strip().splitlines() or [""])[0][:200]
            print_error(f"internal error ({type(exc).__name__}: {first}); please report it with the command "
                        "line (-v shows where it happened)")
            raise typer.Exit(EXIT_INTERNAL) from None

    return wrapper


@contextlib.contextmanager
def progress_reporter(enabled: bool = True) -> Iterator:
    """A progress callback drawing one rich bar per (stage, task); a transient task's bar goes once it is complete."""
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("{task.fields[info]}"))
    # Started at the first event: a command that fails before any (a bad manifest) prints only its error line,
    # without the empty line a bar-less display leaves where the output is not a terminal.
    bars = Progress(*columns, console=err_console, disable=not enabled, transient=False)
    tasks: dict[tuple[str, str], int] = {}

    def report(event: ProgressEvent) -> None:
        if not bars.live.is_started:
            bars.start()
        key = (event.stage, event.task)
        if key not in tasks:
            tasks[key] = bars.add_task(f"{event.stage}: {event.task}", total=event.total, info="")
        info = "  ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in event.info.items())
        bars.update(tasks[key], completed=event.done, total=event.total, info=info)
        if event.transient and event.done >= event.total:
            bars.remove_task(tasks.pop(key))

    try:
        yield report
        shown = {task.id: task for task in bars.tasks}
        for task_id in tasks.values():
            task = shown.get(task_id)
            if task is not None and task.completed < (task.total or 0):
                bars.update(task_id, total=task.completed)
    finally:
        if bars.live.is_started:
            bars.stop()


def length_text(metres: float) -> str:
    """A length with a readable unit (nm, µm, mm, m)."""
    if not math.isfinite(metres):
        return f"{metres}"
    for scale, unit in ((1.0, "m"), (1e-3, "mm"), (1e-6, "µm"), (1e-9, "nm")):
        if abs(metres) >= scale:
            return f"{metres / scale:.3g} {unit}"
    return f"{metres / 1e-9:.3g} nm" if metres else "0 m"   # below a nanometre: still in nm, as its neighbours


def stop_note(stopped_by: str | None, iterations: int | None, change: float | None, tol: float | None,
              plateau: float | None = None, plateau_window: int | None = None,
              tiles: tuple[int, int] | None = None) -> str | None:
    """One line warning that the iteration cap ended a reconstruction before its stopping rules did (None otherwise).

    A run that also stops on a misfit plateau (``plateau`` > 0) is told that the plateau was not reached.
    ``tiles`` (capped, all) says how many tiles of a tiled run the cap stopped (``change`` is then not quoted:
    it differs from tile to tile).
    """
    if stopped_by != "cap":
        return None
    if tiles is not None:
        capped, total = tiles
        who, its = f"{capped} of {total} tiles stopped", "their"
        reached = ""
    else:
        who, its = "reconstruct stopped", "its"
        reached = f" (last change {change:.3g} > tol {tol:.3g})" if change is not None and tol is not None else ""
    if plateau:
        window = f" over {plateau_window} iterations" if plateau_window else ""
        return (f"{who} at the iteration cap ({iterations}) before {its} misfit plateau (less than "
                f"{100 * plateau:.3g}% better{window}) was reached; raise reconstruct.iterations (--iterations) "
                "to go on")
    return (f"{who} at the iteration cap ({iterations}) before the change reached "
            f"tol{reached}; raise reconstruct.iterations (--iterations) to go on")


def print_note(message: str) -> None:
    """One yellow ``note:`` line on stderr (the message is printed as it is, never as markup)."""
    err_console.print(styled("note:", "yellow", message), highlight=False, soft_wrap=True)


def recovery_stop_note(recovery) -> str | None:
    """:func:`stop_note` of a stage's :class:`~cca_cli.stages.reconstruct.Recovery`."""
    records = recovery.history.records
    results = getattr(recovery, "results", None)   # a tiled recovery: one result per tile
    tiles = None if results is None else (sum(r.stopped_by == "cap" for r in results), len(results))
    return stop_note(getattr(recovery, "stopped_by", None), recovery.history.iterations,
                     records[-1].change if records else None, recovery.options.get("tol"),
                     recovery.options.get("plateau"), recovery.options.get("plateau_window"), tiles=tiles)


#: A data residual over all images above this says the model, not the recovery, is off (recorded sets: 0.02–0.3).
POOR_FIT = 0.5
#: Above this data residual (over all images) the report's sharpness figures are marked as from a poor fit: on the
#: recorded corpus cca's own residual is 0.05-0.27; a swapped stage axis gave 0.33 (a flipped one 0.17).
DOUBTFUL_FIT = 0.3


def poor_fit_warning(recovery) -> str | None:
    """A warning when the recovered model explains the captures poorly (a data residual over all images above
    :data:`POOR_FIT`): the geometry (positions, their unit, the optics) rather than the recovery is to check."""
    fit = getattr(recovery, "fit", None)
    residual = getattr(fit, "all", None)
    if residual is None:
        results = getattr(recovery, "results", None)   # a tiled recovery: the median tile
        values = [float(r.residual["all"]) for r in results or () if r.residual.get("all") is not None]
        residual = statistics.median(values) if values else None
    if residual is None or not math.isfinite(residual) or residual <= POOR_FIT:
        return None
    return (f"the recovery explains the captures poorly (data residual {residual:.2f} over all images; recorded "
            "sets give 0.02–0.3): check the geometry the captures were ingested with (positions and their unit, "
            "the LEDs' distance or the stage pitch, NA, pixel size, wavelength)")


def summary_table(summary: dict, title: str = "Result") -> Table:
    """A two-column table of the headline numbers of a report."""
    table = Table(title=title, show_header=True, header_style="bold")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    rows = [
        ("synthetic aperture ratio", "sar", "{:.2f}"),
        ("images", "n_images", "{}"),
        ("recovered image (width x height)", "recovered_shape_px", "image"),
        ("engine / iterations", None, None),
        ("reconstruction time (s)", "seconds", "seconds"),
        # how well the recovery explains its captures first: gains read from a poor fit can be artefacts
        ("data residual, all images", "residual_all", "{:.4f}"),
        ("data residual, bright-field images", "residual_bright_field", "{:.4f}"),
        ("data residual, dark-field images", "residual_dark_field", "{:.4f}"),
        ("spot size at sensor", "spot_size_sensor_m", "length"),
        ("spot size at object", "spot_size_object_m", "length"),
        ("spot size at object, synthetic aperture", "spot_size_synthetic_object_m", "length"),
        ("MTF20 observed (px)", "mtf20_observed_px", "{}"),
        ("MTF20 recovered (px)", "mtf20_recovered_px", "{}"),
        ("resolution gain", "resolution_gain", "{:.2f}"),
        ("RMSE observed", "rmse_observed", "{:.4f}"),
        ("RMSE recovered", "rmse_recovered", "{:.4f}"),
        ("RMSE vs band-limited truth, observed", "rmse_observed_band", "{:.4f}"),
        ("RMSE vs band-limited truth, recovered", "rmse_recovered_band", "{:.4f}"),
        ("multiplexed images (P·T)", "multiplex_measurements", "{}"),
        ("spectrum holes (share of band)", "coverage_zero_fraction", "{:.1%}"),
        ("spectrum seen by one image only", "coverage_single_fraction", "{:.1%}"),
        ("images per spectrum px (mean)", "coverage_mean", "{:.2f}"),
        ("99% spectral reach observed (lp/mm)", "spectral_reach_observed_lp_per_mm", "{:.1f}"),
        ("99% spectral reach recovered (lp/mm)", "spectral_reach_recovered_lp_per_mm", "{:.1f}"),
        ("sharpness gain (reach)", "sharpness_gain", "{:.2f}"),
        ("RMS frequency gain", "rms_frequency_gain", "{:.2f}"),
        ("finest bar element at threshold contrast, observed", "bar_finest_resolved_observed", "{}"),
        ("finest bar element at threshold contrast, recovered", "bar_finest_resolved_recovered", "{}"),
        ("spectral energy beyond 1-camera cutoff, observed", "energy_beyond_cutoff_observed", "{:.2%}"),
        ("spectral energy beyond 1-camera cutoff, recovered", "energy_beyond_cutoff_recovered", "{:.2%}"),
        ("registration RMS max (px)", "registration_rms_px_max", "{:.3f}"),
        ("registration error over the object, RMS, worst view (px)", "registration_object_rms_px_max", "{:.3f}"),
        ("registration error over the object, max (px)", "registration_object_max_px", "{:.3f}"),
        ("HDR flux ratio, worst view (± its noise)", "hdr_flux_ratio_worst", "flux"),
        ("HDR dynamic-range gain (median)", "hdr_dynamic_range_gain_median", "{:.1f}"),
        ("data residual, all, brightness 1", "residual_all_without_brightness", "{:.4f}"),
        ("capture brightness min / median / max", "brightness_min_median_max", "triple"),
        ("pupil model", "pupil_model", "{}"),
        ("position change rms / max (spectrum px)", None, "positions"),
        ("defocus equivalent of the pupil", "defocus_m_equivalent", "length"),
    ]
    for label, key, fmt in rows:
        if key is None and fmt == "positions":
            if summary.get("position_change_px_max"):
                table.add_row(label, f"{summary['position_change_px_rms']:.3f} / {summary['position_change_px_max']:.3f}")
            continue
        if key is None:
            table.add_row(label, f"{summary.get('engine')} / {summary.get('iterations')}")
            continue
        if key not in summary:
            continue
        value = summary[key]
        if value is None or (isinstance(value, float) and math.isnan(value)):   # none to show (no dark field)
            text = "—"
        elif fmt == "length":
            text = length_text(value)
        elif fmt == "seconds":   # three digits below 100 s (0.04 s does not read 0.0), whole seconds above
            text = f"{value:.3g}" if value < 100 else f"{value:.0f}"
        elif fmt == "flux":
            sigma = summary.get("hdr_flux_ratio_worst_sigma")
            text = f"{value:.3f}" + (f" ± {sigma:.3f}" if sigma is not None else "")
        elif fmt == "triple":
            text = " / ".join(f"{v:.3g}" for v in value)
        elif fmt == "image":
            text = f"{value[1]} x {value[0]} px"
            if summary.get("recovered_field_m"):
                height, width = summary["recovered_field_m"]
                text += f", {length_text(width)} x {length_text(height)}"
        else:
            text = fmt.format(value)
        bound = summary.get("mtf20_at_finest_bar") or {}
        if value is not None and key in ("mtf20_observed_px", "mtf20_recovered_px") \
                and bound.get(key.split("_")[1]):
            text = f"≤ {text} (the chart's finest bar)"
        if value is not None and key == "resolution_gain" and bound.get("recovered"):
            text = f"≥ {text}"
        residual = summary.get("residual_all")
        if value is not None and key in ("sharpness_gain", "rms_frequency_gain", "energy_beyond_cutoff_recovered") \
                and residual is not None and residual > DOUBTFUL_FIT:
            text = f"{text} (from a poor fit: artefacts raise it)"
        table.add_row(label, text)
    for label, text in _nested_rows(summary):
        table.add_row(label, text)
    return table


def _nested_rows(summary: dict) -> list[tuple[str, str]]:
    """Rows for the report's nested entries: stop reason, USAF reading, baselines and speckle contrast."""
    rows = []
    if summary.get("stopped_by"):
        reasons = {"tol": "tol", "plateau": "misfit plateau", "cap": "iteration cap (before tol)",
                   "held_back": "held-back captures stopped improving", "callback": "the caller's callback"}
        rows.append(("stopped by", reasons.get(summary["stopped_by"], summary["stopped_by"])))
    if summary.get("held_back_captures"):
        rows.append(("held-back captures: residual (best, at iteration)",
                     f"{summary['residual_held_back']:.4f} ({summary['held_back_captures']} images, "
                     f"iteration {summary['held_back_best_iteration']})"))
    if summary.get("dropped_captures"):
        rows.append(("captures left out, dead or unlit (images)",
                     ", ".join(str(i) for i in summary["dropped_captures"])))
    zernike = summary.get("zernike_waves") or {}
    if zernike:
        largest = sorted(zernike.items(), key=lambda item: -abs(item[1]))[:3]
        whose = f", camera {summary['zernike_waves_camera']}" if "zernike_waves_camera" in summary else ""
        rows.append((f"largest pupil aberrations (waves RMS{whose})", ", ".join(f"{k} {v:+.3f}" for k, v in largest)))
    tiles = summary.get("tiles") or {}
    if tiles.get("residual_all_median_max"):
        rows.append(("tiles: data residual, median / max", " / ".join(f"{v:.4f}" for v in
                                                                     tiles["residual_all_median_max"])))
    for name, (low, middle, high) in list((tiles.get("zernike_waves_min_median_max") or {}).items())[:3]:
        rows.append((f"tiles: {name} (waves), min / median / max", f"{low:+.3f} / {middle:+.3f} / {high:+.3f}"))
    usaf = summary.get("usaf") or {}
    for name, reading in usaf.items():
        if not isinstance(reading, dict):
            continue
        text = "none resolved" if reading.get("group") is None else \
            f"G{reading['group']} E{reading['element']} ({reading['lp_per_mm']:.3g} lp/mm)"
        rows.append((f"USAF {name.replace('_', ' ')}", text))
    if usaf.get("gain") is not None:
        rows.append(("USAF gain (recovered / observed lp/mm)", f"{usaf['gain']:.2f}"))
    for name, entry in (summary.get("baselines") or {}).items():
        parts = []
        if entry.get("mtf20_px") is not None:
            parts.append(f"MTF20 {entry['mtf20_px']} px")
        if entry.get("rmse") is not None:
            parts.append(f"RMSE {entry['rmse']:.4f}")
        if entry.get("spot_size_object_m") is not None:
            parts.append(f"spot {length_text(entry['spot_size_object_m'])}")
        rows.append((f"baseline {name.replace('_', ' ')}", ", ".join(parts) or "—"))
    for name in ("observed", "recovered"):
        key = f"speckle_contrast_{name}"
        if summary.get(key) is not None:
            rows.append((f"speckle contrast {name}", f"{summary[key]:.3f}"))
    for name, value in (summary.get("speckle_contrast_baselines") or {}).items():
        rows.append((f"speckle contrast {name.replace('_', ' ')}", f"{value:.3f}"))
    return rows
