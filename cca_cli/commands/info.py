"""`cca info FILE.h5`: what a pipeline file holds, with units, and the quantities its geometry implies.

`cca info` without a file: what this machine computes with (cca's version, the FFT backend and threads, and
the devices ``reconstruct.device`` can use).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer

from cca_cli.commands.console import console, handle_errors, length_text
from cca_cli.errors import InputError
from cca_cli.io.browse import is_group, open_hdf5, visit_datasets
from cca_cli.io.h5 import check_input_file

__all__ = ["info_cli", "derived_lines", "machine_lines"]


def _text(value) -> str:
    """An attribute as text, whatever it holds (undecodable bytes are replaced, opaque data described)."""
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.void):
        return f"<{len(value.tobytes())} bytes of opaque data>"
    return str(value)


def derived_lines(derived: dict) -> list[str]:
    """The lines `cca info` and `cca simulate` print for :func:`cca_cli.report.summary.derived_quantities`."""
    rows, cols = derived["grid"]
    led = derived.get("kind") == "led_array"
    lines = [f"  images          {derived['n_images']} ({rows} x {cols} grid)",
             f"  SAR             {derived['sar']:.2f}"]
    if derived.get("step_m") is not None:
        step = f"{derived['step_m']:.4g} (sin θ)" if led else length_text(derived["step_m"])
        overlap = f", overlap {derived['overlap']:.0%}" if derived.get("overlap") is not None else ""
        lines.append(f"  step            {step}{overlap}")
    lines.append(f"  pupil radius    {derived['pupil_radius_px']:.2f} spectrum px")
    if not led:
        lines.append(f"  spot at sensor  {length_text(derived['spot_size_sensor_m'])} (2.44·λ·f/d)")
    formula = "1.22·λ/NA" if led else "2.44·λ·z/d"
    lines.append(f"  spot at object  {length_text(derived['spot_size_object_m'])} ({formula}); synthetic aperture "
                 f"{length_text(derived['spot_size_synthetic_object_m'])}")
    if "guard_band" in derived:   # what reconstruct recovers recorded frames on: only that grid is said
        g = derived["guard_band"]
        pixel = f" of {length_text(g['object_pixel_m'])}" if g.get("object_pixel_m") else ""
        band = f", {g['lowres_grid_px']} px band grid per capture" if g.get("lowres_grid_px") else ""
        lines.append(f"  reconstruct     recorded {g['frame'][1]} x {g['frame'][0]} px frames on a {g['grid_px']} px "
                     f"grid with a guard band (pupil radius {g['pupil_radius_px']:.2f} px there), output grid "
                     f"{g['output_grid_px']} x {g['output_grid_px']} px{pixel}{band}")
    elif "output_grid_px" in derived:
        band = f", {derived['lowres_grid_px']} px band grid per capture" if "lowres_grid_px" in derived else ""
        lines.append(f"  output grid     {derived['output_grid_px']} x {derived['output_grid_px']} px of "
                     f"{length_text(derived['object_pixel_m'])}{band}")
    if "recovered_shape_px" in derived and "object_pixel_m" in derived:
        rows, cols = derived["recovered_shape_px"]
        pixel = derived["object_pixel_m"]
        lines.append(f"  recovered       {cols} x {rows} px region of it, {length_text(cols * pixel)} x "
                     f"{length_text(rows * pixel)} (the rest is guard band)")
    return lines


def _derived(handle) -> dict | None:
    """Derived quantities of a file with /geometry (None without one, or when it is malformed)."""
    if "geometry" not in handle:
        return None
    from cca_cli.io.geometry import read_geometry
    from cca_cli.report.summary import derived_quantities

    try:
        geometry = read_geometry(handle)
    except InputError:
        return None
    recon = handle["recon"].attrs if "recon" in handle else {}
    if "hires_size" in recon:
        derived = derived_quantities(geometry, hires_size=int(recon["hires_size"]),
                                     lowres_size=int(recon["lowres_size"]) if "lowres_size" in recon else None)
        if "/recon/region_px" in handle:
            derived["recovered_shape_px"] = [int(v) for v in handle["/recon/region_px"][0, 2:]]
        return derived
    images = handle.get("/measurements/intensity")
    sensor = images.shape[-1] if images is not None and images.ndim == 3 and images.shape[-1] == images.shape[-2] \
        else None
    derived = derived_quantities(geometry, sensor_pixels=sensor)
    if images is not None and images.ndim == 3 and str(images.attrs.get(
            "boundary", "periodic" if images.shape[1] == images.shape[2] else "open")) == "open":
        # what reconstruct (default padding) recovers these frames on: a guard band widens field and pupil
        from cca_cli.sampling.capture import with_field_width
        from cca_cli.sampling.region import plan_embedding

        h, w = images.shape[1:]
        try:
            region = plan_embedding((h, w), geometry.pupil_radius_px)
            padded = with_field_width(geometry, geometry.field_width_m * region.size / w)
            grid = derived_quantities(padded, sensor_pixels=region.size)
        except (ValueError, KeyError):
            return derived
        derived["guard_band"] = {"frame": [int(h), int(w)], "grid_px": int(region.size),
                                 "pupil_radius_px": float(padded.pupil_radius_px),
                                 "output_grid_px": grid.get("output_grid_px"),
                                 "object_pixel_m": grid.get("object_pixel_m"),
                                 "lowres_grid_px": grid.get("lowres_grid_px")}
    return derived


def machine_lines() -> list[str]:
    """What `cca info` prints without a file: version, FFT backend and threads, and the compute devices."""
    from cca_cli.optics import fft
    from cca_cli.optics.backend import device_status
    from cca_cli.version import __version__

    status = device_status()
    devices = f"cpu, cuda ({status.summary})" if status.cuda else status.summary
    return [f"cca {__version__}",
            f"  FFT backend     {fft.backend_name()}, {fft.default_threads()} threads",
            f"  devices         {devices}"]


@handle_errors
def info_cli(path: Annotated[Optional[Path], typer.Argument(
        help="An HDF5 file written by cca; omit it for this machine's FFT backend and devices (CPU, GPU).",
        show_default=False)] = None) -> None:
    """List the datasets of PATH with dtype, shape, units and meaning, its provenance and derived quantities.

    Without PATH: cca's version, the FFT backend and the devices reconstructions can run on (reconstruct.device).
    """
    if path is None:
        for line in machine_lines():
            console.print(line, markup=False, highlight=False, soft_wrap=True)
        return
    check_input_file(path)
    handle = open_hdf5(path)
    out = lambda text="": console.print(text, markup=False, highlight=False, soft_wrap=True)  # noqa: E731
    try:
        with handle:
            _describe(handle, path, out)
    except (OSError, KeyError, RuntimeError) as exc:
        raise InputError(f"{path}: cannot read the file ({exc}); it may be truncated or damaged") from None


def _attrs(obj) -> dict[str, str]:
    out = {}
    for key in obj.attrs:
        try:
            out[key] = obj.attrs[key]
        except (OSError, TypeError, ValueError):
            out[key] = "<unreadable>"
    return out


#: /geometry attributes an LED array's geometry holds as stand-ins (it is stored as a camera array whose
#: "aperture" is the objective's NA disc); `cca info` leaves them out for LED arrays.
_LED_STAND_INS = ("aperture_diameter_m", "distance_m", "focal_length_m", "overlap")


def _describe(handle, path: Path, out) -> None:
    attrs = {k: _text(v) for k, v in _attrs(handle).items()}
    out(f"{path}: stage {attrs.get('stage', '?')}, cca {attrs.get('cca_version', '?')}, "
        f"schema {attrs.get('cca_schema', '?')}, created {attrs.get('created_utc', '?')}")
    out()

    def visit(name, obj):
        dataset_attrs = _attrs(obj)
        units = _text(dataset_attrs.get("units", ""))
        out(f"  /{name}  {obj.dtype}  {obj.shape}  [{units}]")
        if "description" in dataset_attrs:
            out(f"      {_text(dataset_attrs['description'])}")

    visit_datasets(handle, visit)
    for group in ("geometry", "recon"):
        if group in handle and is_group(handle[group]):
            group_attrs = _attrs(handle[group])
            # an LED array's geometry is stored as a camera array's; those stand-ins are no facts of the setup
            hidden = _LED_STAND_INS if _text(group_attrs.get("kind", "")) == "led_array" else ()
            # a quantity that does not apply (a camera scan's NA, measured positions' overlap) is stored as NaN
            unset = {k for k, v in group_attrs.items() if group == "geometry" and isinstance(v, float) and v != v}
            items = [f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={_text(v)}"
                     for k, v in group_attrs.items() if k != "units" and k not in hidden and k not in unset]
            out()
            out(f"{group}: " + ", ".join(items))
    derived = _derived(handle)
    if derived is not None:
        out()
        out("derived quantities:")
        for line in derived_lines(derived):
            out(line)
    if attrs.get("inputs"):
        out()
        out(f"inputs: {_inputs_text(attrs['inputs'])}")
    if attrs.get("config"):
        out()
        out("config:")
        out(attrs["config"].rstrip())


def _inputs_text(inputs: str) -> str:
    """The provenance's input files: all of them when few, else the count and the first three."""
    import json

    try:
        files = json.loads(inputs)
    except ValueError:
        return inputs
    if not isinstance(files, list) or len(files) <= 5:
        return inputs
    first = ", ".join(str(f.get("path")) for f in files[:3] if isinstance(f, dict))
    return f"{len(files)} files with SHA-256 (first: {first}, …)"
