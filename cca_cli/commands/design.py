"""`cca design`: plan a camera array for a target resolution."""

from __future__ import annotations

import copy
import json
import math
from decimal import Decimal
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from cca_cli.commands.console import console, err_console, handle_errors, print_warning
from cca_cli.errors import ConfigError
from cca_cli.io.outputs import atomic_path, check_output, starts_with

#: First line of a config written by --write-config (how --force recognises one).
WRITTEN_BY = "# Written by `cca design`."
#: Engines the time estimate and the written config can use, and the reconstruct settings written for each.
#: ``momentum`` stops once the data misfit falls by less than 1% over 10 passes (a simulation's noise floor,
#: after tens of passes; on noisy captures its spectrum change often levels off above ``tol``), ``altmin``
#: after the paper's 1000 iterations at most.
WRITTEN_RECONSTRUCT = {
    "momentum": {"tau": 1e-3, "iterations": 200, "tol": 1e-5, "options": {"plateau": 0.01, "plateau_window": 10}},
    "altmin": {"tau": 1e-3, "iterations": 1000, "tol": 1e-5},
}

__all__ = ["WRITTEN_RECONSTRUCT", "design_cli", "plan_config"]


def _si(value: float | None, unit: str = "m") -> str:
    if value is None:
        return "—"
    for scale, prefix in ((1.0, ""), (1e-3, "m"), (1e-6, "µ"), (1e-9, "n")):
        if abs(value) >= scale:
            return f"{value / scale:.4g} {prefix}{unit}"
    return f"{value:.3g} {unit}"


def _count(n: int) -> str:
    """An integer, in scientific notation once it is too long to read."""
    return str(n) if n < 10 ** 7 else format(Decimal(n), ".3e")


def _option_names(exc: ValueError) -> str:
    """The message of a planning error with its keys spelled as the command's options (--wavelength-m …)."""
    text = str(exc)
    for key in ("wavelength_m", "focal_length_m", "aperture_diameter_m", "pixel_pitch_m", "distance_m",
                "field_width_m", "sensor_px", "overlap"):
        option = "--aperture-m" if key == "aperture_diameter_m" else "--" + key.replace("_", "-")
        text = text.replace(key, option) if text.startswith(key) or f" {key}" in text else text
    for kind, option in (("feature", "--feature-m"), ("sar", "--sar"), ("beat_lens", "--beat-lens-m")):
        text = text.replace(f"the {kind} target", f"the target {option}")
    return text


def _machine_warnings(plan) -> tuple[str, ...]:
    """Warnings when this machine cannot hold the plan's captures or its reconstruction."""
    from cca_cli.io.capacity import memory_available, size_text

    available = memory_available()
    if plan.memory_bytes > available:
        return (f"reconstructing this plan needs about {size_text(float(min(plan.memory_bytes, 1e300)))} of memory; "
                f"this machine has {size_text(available)} available",)
    return ()


def _measured_cost(plan, engine: str):
    """The engine's rates on ``plan``'s grids, measured on this machine now."""
    from cca_cli.engines.timing import measure_iteration_cost

    return measure_iteration_cost(engine, n_images=plan.n_images, pupil_radius_px=plan.pupil_radius_px,
                                  step_px=plan.step_px, lowres_size=plan.lowres_px, hires_size=plan.output_px)


def _time_text(seconds: float | None, cost) -> str:
    if seconds is None:
        return "—"
    threads = "1 thread" if cost.threads == 1 else f"{cost.threads} threads"
    return f"{seconds:.3g} s ({threads})"


def plan_config(plan, *, engine: str = "momentum", iterations: int | None = None) -> dict:
    """A `cca run` config (as a mapping) that simulates and reconstructs ``plan`` with a bar chart.

    Parameters
    ----------
    plan : ArrayPlan
    engine : {"momentum", "altmin"}
        Reconstruction engine.
    iterations : int, optional
        Iteration cap; default that of :data:`WRITTEN_RECONSTRUCT`, whose stopping rules may end the run sooner.

    Returns
    -------
    dict
        The config's sections: the chart fills the output grid, with the default bar widths
        and the synthetic spot's width (rounded down to whole pixels) that fit it, finest first
        to stay.
    """
    from cca_cli.targets import DEFAULT_WIDTHS, resolution_chart

    size = plan.output_px
    # Bars as wide as the synthetic spot (rounded down) show whether the recovery reaches it.
    predicted = math.floor(min(plan.spot_synthetic_px, 1e9))
    widths = sorted(set(DEFAULT_WIDTHS) | ({predicted} if predicted >= 1 else set()), reverse=True)
    while widths:
        try:
            resolution_chart(size, widths=tuple(widths))
            break
        except ValueError:
            widths.pop(0)
    if not widths:
        raise ConfigError(f"--write-config: no bar chart fits the {size} px output grid; widen the field")
    return {
        "optics": {"wavelength_m": plan.wavelength_m, "focal_length_m": plan.focal_length_m,
                   "aperture_diameter_m": plan.aperture_diameter_m, "pixel_pitch_m": plan.pixel_pitch_m,
                   "distance_m": plan.distance_m},
        "scene": {"kind": "resolution_chart", "size_px": size, "field_width_m": plan.field_width_m,
                  "widths_px": widths},
        "array": {"grid": plan.grid, "overlap": plan.overlap},
        "noise": {"model": "gaussian", "snr_db": 30.0, "seed": 0},
        "reconstruct": {"engine": engine, **copy.deepcopy(WRITTEN_RECONSTRUCT[engine]),
                        **({} if iterations is None else {"iterations": iterations})},
        "report": {"mtf_threshold": 0.2,
                   "baselines": [{"kind": "passive_incoherent"},
                                 {"kind": "lens", "aperture_diameter_m": plan.synthetic_aperture_m,
                                  "illumination": "incoherent"}]},
    }


def _tidy_floats(value):
    """``value`` with every float rounded to 12 significant digits (0.032, not 0.031999999999999994)."""
    if isinstance(value, float):
        return float(f"{value:.12g}")
    if isinstance(value, dict):
        return {key: _tidy_floats(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_tidy_floats(item) for item in value]
    return value


@handle_errors
def design_cli(
    wavelength_m: Annotated[float, typer.Option("--wavelength-m", help="Wavelength λ (m).")] = 550e-9,
    focal_length_m: Annotated[float, typer.Option("--focal-length-m", help="Lens focal length (m).")] = 0.8,
    aperture_m: Annotated[float, typer.Option("--aperture-m", help="Lens aperture diameter d (m).")] = 0.018,
    pixel_pitch_m: Annotated[float, typer.Option("--pixel-pitch-m", help="Sensor pixel pitch (m).")] = 2e-6,
    distance_m: Annotated[float, typer.Option("--distance-m", help="Object distance z (m).")] = 50.0,
    feature_m: Annotated[Optional[float], typer.Option("--feature-m", help="Target: smallest feature at the object (m).")] = None,
    sar: Annotated[Optional[float], typer.Option("--sar", help="Target: synthetic aperture ratio.")] = None,
    beat_lens_m: Annotated[Optional[float], typer.Option("--beat-lens-m", help="Target: aperture of a lens to out-resolve (m).")] = None,
    overlap: Annotated[float, typer.Option("--overlap", help="Linear overlap of neighbouring apertures.")] = 0.61,
    field_width_m: Annotated[Optional[float], typer.Option("--field-width-m", help="Object-plane field to capture (m).")] = None,
    sensor_px: Annotated[Optional[int], typer.Option("--sensor-px", help="Pixels across the sensor.")] = None,
    engine: Annotated[str, typer.Option("--engine", help="Engine of the time estimate and the written config: "
                                                         "momentum or altmin.")] = "momentum",
    iterations: Annotated[Optional[int], typer.Option("--iterations", help="Iteration cap in the written config "
                                                      "(default: 200 for momentum, 1000 for altmin).")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the plan as JSON.")] = False,
    write_config: Annotated[Optional[Path], typer.Option("--write-config", help="Write a `cca run` YAML of the plan.", dir_okay=False)] = None,
    force: Annotated[bool, typer.Option("--force", "-f", help="Overwrite --write-config's file.")] = False,
    measure: Annotated[bool, typer.Option("--measure/--no-measure", help="Time the engine's work on this machine for the per-iteration estimate.")] = True,
) -> None:
    """Plan an array: spot sizes, SAR, grid, step, images, data volume, output size, memory and time."""
    from cca_cli.sampling.design import iteration_seconds, plan_array

    if engine not in WRITTEN_RECONSTRUCT:
        raise ConfigError(f"--engine: choose {' or '.join(WRITTEN_RECONSTRUCT)}, got {engine!r}")
    if iterations is not None and iterations < 1:
        raise ConfigError(f"--iterations: must be at least 1, got {iterations}")
    if write_config is not None:
        check_output(write_config, force=force, owned=starts_with(WRITTEN_BY))
    try:
        plan = plan_array(wavelength_m=wavelength_m, focal_length_m=focal_length_m, aperture_diameter_m=aperture_m,
                          pixel_pitch_m=pixel_pitch_m, distance_m=distance_m, feature_m=feature_m, sar=sar,
                          beat_lens_m=beat_lens_m, overlap=overlap, field_width_m=field_width_m, sensor_px=sensor_px)
    except ValueError as exc:
        raise ConfigError(f"cca design: {_option_names(exc)}") from None
    cost = _measured_cost(plan, engine) if measure else None
    seconds = None if cost is None else iteration_seconds(plan, capture_seconds=cost.capture_seconds,
                                                            pixel_seconds=cost.pixel_seconds)
    if write_config is not None:
        import yaml

        config = _tidy_floats(plan_config(plan, engine=engine, iterations=iterations))
        text = WRITTEN_BY + "\n" + yaml.safe_dump(config, sort_keys=False)
        with atomic_path(write_config, force=force, owned=starts_with(WRITTEN_BY)) as tmp:
            tmp.write_text(text)
    if as_json:
        data = plan.to_dict()
        data["engine"] = engine
        data["threads"] = None if cost is None else cost.threads
        data["capture_seconds"] = None if cost is None else cost.capture_seconds
        data["pixel_seconds"] = None if cost is None else cost.pixel_seconds
        data["seconds_per_iteration"] = seconds
        console.print_json(json.dumps(data))
    else:
        from cca_cli.io.capacity import size_text

        table = Table(title="cca design", header_style="bold")
        table.add_column("quantity")
        table.add_column("value", justify="right")
        target = {"feature": f"feature {_si(plan.target_value)}", "sar": f"SAR {plan.target_value:g}",
                  "beat_lens": f"beat a {_si(plan.target_value)} lens"}[plan.target]
        rows = [
            ("target", target),
            ("spot at object, one lens (2.44 λz/d)", _si(plan.spot_lens_m)),
            ("spot at object, synthetic aperture", _si(plan.spot_synthetic_m)),
            ("spot on the output image, synthetic", f"{plan.spot_synthetic_px:.3g} px"),
            *([("spot at object, lens to beat", _si(plan.spot_beat_m))] if plan.spot_beat_m else []),
            ("spot at sensor, one lens", _si(plan.spot_sensor_m)),
            ("required SAR", f"{plan.required_sar:.4g}"),
            ("grid / SAR reached", f"{_count(plan.grid)} x {_count(plan.grid)} / {plan.sar:.4g}"),
            ("synthetic aperture", _si(plan.synthetic_aperture_m)),
            ("overlap / step", f"{plan.overlap:.0%} / {_si(plan.step_m)}"),
            ("images", _count(plan.n_images)),
            ("object pixel (sensor)", _si(plan.object_pixel_m)),
            ("field / pixels per capture", f"{_si(plan.field_width_m)} / {plan.capture_px} px"),
            ("capture data (float32)", size_text(plan.capture_bytes)),
            ("output image", f"{_count(plan.output_px)} x {_count(plan.output_px)} px at {_si(plan.output_pixel_m)}"),
            ("per-capture model grid", f"{plan.lowres_px} px (pupil radius {plan.pupil_radius_px:.1f} px)"),
            ("reconstruction memory (est.)", size_text(plan.memory_bytes)),
            (f"time per iteration, {engine} (est.)", _time_text(seconds, cost)),
            ("fits the sensor", ("yes" if plan.fits_sensor else "NO") if sensor_px is not None
             else "not checked (give --sensor-px)"),
        ]
        for label, value in rows:
            table.add_row(label, value)
        console.print(table)
    for warning in plan.warnings + _machine_warnings(plan):
        print_warning(warning)
    if write_config is not None:
        err_console.print(f"wrote {write_config}; run it with: cca run {write_config}", highlight=False)
