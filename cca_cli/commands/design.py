"""`cca design`: plan a camera array for a target resolution."""

from __future__ import annotations

import json
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

__all__ = ["design_cli", "plan_config"]


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


def _bytes(n: int) -> str:
    if n >= 1024 ** 5:
        return f"{_count(n)} B"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{n} B"
        n /= 1024
    return f"{n} B"


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
    from cca_cli.stages.footprint import memory_available, size_text

    available = memory_available()
    if plan.memory_bytes > available:
        return (f"reconstructing this plan needs about {size_text(float(min(plan.memory_bytes, 1e300)))} of memory; "
                f"this machine has {size_text(available)} available",)
    return ()


def plan_config(plan, *, iterations: int = 300) -> dict:
    """A `cca run` config (as a mapping) that simulates and reconstructs ``plan`` with a bar chart."""
    from cca_cli.targets import DEFAULT_WIDTHS, resolution_chart

    size = plan.output_px
    widths = [w for w in DEFAULT_WIDTHS]
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
        "reconstruct": {"engine": "altmin", "tau": 1e-3, "iterations": iterations, "tol": 1e-5},
        "report": {"mtf_threshold": 0.2,
                   "baselines": [{"kind": "passive_incoherent"},
                                 {"kind": "lens", "aperture_diameter_m": plan.synthetic_aperture_m,
                                  "illumination": "incoherent"}]},
    }


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
    iterations: Annotated[int, typer.Option("--iterations", help="Iterations in the written config.")] = 300,
    as_json: Annotated[bool, typer.Option("--json", help="Print the plan as JSON.")] = False,
    write_config: Annotated[Optional[Path], typer.Option("--write-config", help="Write a `cca run` YAML of the plan.", dir_okay=False)] = None,
    force: Annotated[bool, typer.Option("--force", "-f", help="Overwrite --write-config's file.")] = False,
    measure: Annotated[bool, typer.Option("--measure/--no-measure", help="Time FFTs on this machine for the per-iteration estimate.")] = True,
) -> None:
    """Plan an array: spot sizes, SAR, grid, step, images, data volume, output size, memory and time."""
    from cca_cli.sampling.design import iteration_seconds, plan_array

    if iterations < 1:
        raise ConfigError(f"--iterations: must be at least 1, got {iterations}")
    if write_config is not None:
        check_output(write_config, force=force, owned=starts_with(WRITTEN_BY))
    try:
        plan = plan_array(wavelength_m=wavelength_m, focal_length_m=focal_length_m, aperture_diameter_m=aperture_m,
                          pixel_pitch_m=pixel_pitch_m, distance_m=distance_m, feature_m=feature_m, sar=sar,
                          beat_lens_m=beat_lens_m, overlap=overlap, field_width_m=field_width_m, sensor_px=sensor_px)
    except ValueError as exc:
        raise ConfigError(f"cca design: {_option_names(exc)}") from None
    seconds = None
    fft_s = None
    if measure:
        from cca_cli.optics.timing import fft_seconds

        fft_s = fft_seconds(plan.lowres_px)
        seconds = iteration_seconds(plan, fft_s)
    if write_config is not None:
        import yaml

        text = WRITTEN_BY + "\n" + yaml.safe_dump(plan_config(plan, iterations=iterations), sort_keys=False)
        with atomic_path(write_config, force=force, owned=starts_with(WRITTEN_BY)) as tmp:
            tmp.write_text(text)
    if as_json:
        data = plan.to_dict()
        data["fft_seconds"] = fft_s
        data["seconds_per_iteration"] = seconds
        console.print_json(json.dumps(data))
    else:
        table = Table(title="cca design", header_style="bold")
        table.add_column("quantity")
        table.add_column("value", justify="right")
        target = {"feature": f"feature {_si(plan.target_value)}", "sar": f"SAR {plan.target_value:g}",
                  "beat_lens": f"beat a {_si(plan.target_value)} lens"}[plan.target]
        rows = [
            ("target", target),
            ("spot at object, one lens (2.44 λz/d)", _si(plan.spot_lens_m)),
            ("spot at object, synthetic aperture", _si(plan.spot_synthetic_m)),
            *([("spot at object, lens to beat", _si(plan.spot_beat_m))] if plan.spot_beat_m else []),
            ("spot at sensor, one lens", _si(plan.spot_sensor_m)),
            ("required SAR", f"{plan.required_sar:.4g}"),
            ("grid / SAR reached", f"{_count(plan.grid)} x {_count(plan.grid)} / {plan.sar:.4g}"),
            ("synthetic aperture", _si(plan.synthetic_aperture_m)),
            ("overlap / step", f"{plan.overlap:.0%} / {_si(plan.step_m)}"),
            ("images", _count(plan.n_images)),
            ("object pixel (sensor)", _si(plan.object_pixel_m)),
            ("field / pixels per capture", f"{_si(plan.field_width_m)} / {plan.capture_px} px"),
            ("capture data (float32)", _bytes(plan.capture_bytes)),
            ("output image", f"{_count(plan.output_px)} x {_count(plan.output_px)} px at {_si(plan.output_pixel_m)}"),
            ("per-capture model grid", f"{plan.lowres_px} px (pupil radius {plan.pupil_radius_px:.1f} px)"),
            ("reconstruction memory (est.)", _bytes(plan.memory_bytes)),
            ("time per iteration (est.)", "—" if seconds is None else f"{seconds:.3g} s"),
            ("fits the sensor", "yes" if plan.fits_sensor else "NO"),
        ]
        for label, value in rows:
            table.add_row(label, value)
        console.print(table)
    for warning in plan.warnings + _machine_warnings(plan):
        print_warning(warning)
    if write_config is not None:
        err_console.print(f"wrote {write_config}; run it with: cca run {write_config}", highlight=False)
