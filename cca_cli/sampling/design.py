"""Plan a camera array for a target resolution: pure computation, no printing.

Given the optics (wavelength, focal length, aperture, pixel pitch), the object
distance and one target (a feature size at the object, a synthetic aperture
ratio, or a lens whose diffraction limit must be beaten), :func:`plan_array`
returns an :class:`ArrayPlan`: spot sizes, the SAR needed, the grid and step
at the chosen overlap, the image count, the grids the reconstruction runs on
and the memory it needs.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from cca_cli.sampling.grid import band_sizes
from cca_cli.sampling.overlap import grid_for_sar, step_m, synthetic_aperture_ratio
from cca_cli.units import (
    FourierScale,
    grid_pixel_m,
    object_pixel_pitch_m,
    sensor_field_width_m,
    sensor_pixels_across,
    spot_size_m,
)

__all__ = ["MIN_OVERLAP", "SUGGESTED_OVERLAP", "ArrayPlan", "plan_array", "iteration_seconds",
           "reconstruction_memory_bytes"]

#: Overlap below which the paper found recovery to fail (Holloway et al. 2016, Sec. 5).
MIN_OVERLAP = 0.5
#: Overlap suggested when the requested one is too small.
SUGGESTED_OVERLAP = 0.6

#: FFTs of the band grid per capture and iteration: the inverse to the sensor field and the forward back.
_FFTS_PER_CAPTURE = 2


@dataclass(frozen=True)
class ArrayPlan:
    """A planned camera array (all lengths in metres, sizes in pixels).

    Attributes
    ----------
    wavelength_m, focal_length_m, aperture_diameter_m, pixel_pitch_m, distance_m : float
        The optics.
    target : str
        ``feature``, ``sar`` or ``beat_lens``: what was asked for.
    target_value : float
        The feature size (m), SAR, or aperture of the lens to beat (m).
    overlap : float
        Linear overlap of neighbouring apertures.
    required_sar : float
        Synthetic aperture ratio the target needs.
    grid : int
        Positions per side (odd, so a centre image exists).
    sar : float
        SAR the grid reaches: ``(grid - 1)(1 - overlap) + 1``.
    synthetic_aperture_m, step_m : float
        Synthetic aperture diameter and camera spacing.
    n_images : int
        ``grid ** 2``.
    spot_lens_m, spot_synthetic_m : float
        Diffraction spot ``2.44 λ z / d`` at the object for one lens and for the synthetic aperture.
    spot_synthetic_px : float
        ``spot_synthetic_m`` in pixels of the recovered image: the recovery
        reaches the plan's resolution when its MTF20 bar width is at most this.
    spot_beat_m : float or None
        The same for the lens to beat (``beat_lens`` target only).
    spot_sensor_m : float
        Spot on the sensor of one lens, ``2.44 λ f / d``.
    object_pixel_m : float
        One sensor pixel projected on the object.
    field_width_m : float
        Object-plane width of the captured field.
    capture_px : int
        Sensor pixels across the field.
    sensor_px : int or None
        Pixels across the sensor, when given.
    fits_sensor : bool
        Whether the scene's angular extent fits the sensor (always true without ``sensor_px``).
    pupil_radius_px : float
        Pupil radius in spectrum pixels of the field.
    step_px : float
        Distance of neighbouring pupil centres in spectrum pixels.
    output_px : int
        Side of the recovered image (high-resolution grid M).
    lowres_px : int
        Side of the per-capture model grid m.
    output_pixel_m : float
        Object-plane pitch of the recovered image.
    capture_bytes : int
        Size of the capture stack (float32).
    memory_bytes : int
        Estimated peak memory of a reconstruction.
    fft_count_per_iteration : int
        m x m complex FFTs per iteration (an inverse and a forward one per capture).
    warnings : tuple of str
        Problems with the plan (low overlap, field larger than the sensor, target below one lens).
    """

    wavelength_m: float
    focal_length_m: float
    aperture_diameter_m: float
    pixel_pitch_m: float
    distance_m: float
    target: str
    target_value: float
    overlap: float
    required_sar: float
    grid: int
    sar: float
    synthetic_aperture_m: float
    step_m: float
    n_images: int
    spot_lens_m: float
    spot_synthetic_m: float
    spot_synthetic_px: float
    spot_beat_m: float | None
    spot_sensor_m: float
    object_pixel_m: float
    field_width_m: float
    capture_px: int
    sensor_px: int | None
    fits_sensor: bool
    pupil_radius_px: float
    step_px: float
    output_px: int
    lowres_px: int
    output_pixel_m: float
    capture_bytes: int
    memory_bytes: int
    fft_count_per_iteration: int
    warnings: tuple[str, ...]

    def to_dict(self) -> dict:
        """JSON-ready dictionary of every attribute."""
        out = asdict(self)
        out["warnings"] = list(self.warnings)
        return out


def iteration_seconds(plan: ArrayPlan, *, capture_seconds: float, pixel_seconds: float) -> float:
    """Estimated seconds per reconstruction iteration.

    Parameters
    ----------
    plan : ArrayPlan
    capture_seconds : float
        Wall time of one capture's share of a pass: its pupil box placed on the
        ``lowres_px`` band grid, the inverse and forward FFTs (pruned to the
        box's rows), the magnitude step and the adjoint, on the engine's threads.
    pixel_seconds : float
        Wall time per spectrum pixel of the steps that sweep the whole
        ``output_px`` x ``output_px`` spectrum once per iteration.

    Returns
    -------
    float
        ``n_images * capture_seconds + output_px**2 * pixel_seconds``.

    Notes
    -----
    Both engines visit every capture once per iteration; measure the rates with
    :func:`cca_cli.engines.timing.measure_iteration_cost`.
    """
    try:
        return float(plan.n_images) * capture_seconds + float(plan.output_px) ** 2 * pixel_seconds
    except OverflowError:  # more captures than a float holds
        return math.inf


def reconstruction_memory_bytes(k: float, capture_px: float, lowres: float, hires: float, box: float) -> float:
    """Estimated peak memory (bytes) of reconstructing ``k`` captures of ``capture_px``² on the given grids."""
    captures = k * capture_px * capture_px * 4
    amplitudes = k * lowres * lowres * 4
    pupils = 2 * k * box * box * 8
    spectra = 6 * hires * hires * 8            # spectrum, accumulator, normal diagonal, previous, object, intensity
    workspace = 2 * 16 * lowres * lowres * 8     # two threads' chunk buffers
    return captures + amplitudes + pupils + spectra + workspace


def plan_array(*, wavelength_m: float, focal_length_m: float, aperture_diameter_m: float, pixel_pitch_m: float,
               distance_m: float, feature_m: float | None = None, sar: float | None = None,
               beat_lens_m: float | None = None, overlap: float = 0.61, field_width_m: float | None = None,
               sensor_px: int | None = None) -> ArrayPlan:
    """Plan the array that reaches one target.

    Parameters
    ----------
    wavelength_m, focal_length_m, aperture_diameter_m, pixel_pitch_m, distance_m : float
        The camera and the object distance (SI).
    feature_m, sar, beat_lens_m : float, optional
        Exactly one target: the smallest feature to resolve at the object
        (its diffraction spot ``2.44 λ z / D`` must not exceed it), a
        synthetic aperture ratio, or the aperture of a lens whose spot must be beaten.
    overlap : float
        Linear overlap of neighbouring apertures, in [0, 1).
    field_width_m : float, optional
        Object-plane field to capture; default: the whole sensor (``sensor_px``) or 256 pixels.
    sensor_px : int, optional
        Pixels across the sensor.

    Returns
    -------
    ArrayPlan

    Raises
    ------
    ValueError
        If not exactly one target is given or a value is out of range.
    """
    targets = {"feature": feature_m, "sar": sar, "beat_lens": beat_lens_m}
    given = [k for k, v in targets.items() if v is not None]
    if len(given) != 1:
        raise ValueError("give exactly one target: a feature size, a SAR, or a lens aperture to beat")
    kind = given[0]
    value = float(targets[kind])
    if not (value > 0 and math.isfinite(value)):
        raise ValueError(f"the {kind} target must be a positive number, got {value}")
    for name, v in (("wavelength_m", wavelength_m), ("focal_length_m", focal_length_m),
                    ("aperture_diameter_m", aperture_diameter_m), ("pixel_pitch_m", pixel_pitch_m),
                    ("distance_m", distance_m), ("field_width_m", field_width_m)):
        if v is not None and not (v > 0 and math.isfinite(v)):
            raise ValueError(f"{name} must be a positive number, got {v}")
    if sensor_px is not None and not sensor_px >= 1:
        raise ValueError(f"sensor_px must be at least 1, got {sensor_px}")
    d = aperture_diameter_m
    spot_lens = spot_size_m(wavelength_m, distance_m, d)
    warnings = []
    if kind == "feature":
        required = spot_lens / value
    elif kind == "sar":
        required = value
    else:
        required = beat_lens_m / d
    if required < 1.0:
        warnings.append(f"one {d * 1e3:.1f} mm lens already reaches the target (SAR {required:.2f} < 1)")
        required_grid_sar = 1.0
    else:
        required_grid_sar = required
    if overlap < MIN_OVERLAP:
        warnings.append(f"overlap {overlap:.0%} is below the {MIN_OVERLAP:.0%} the paper needs for recovery; "
                        f"use about {SUGGESTED_OVERLAP:.0%}")
    grid = grid_for_sar(required_grid_sar, overlap)
    achieved = synthetic_aperture_ratio(grid, overlap)
    step = step_m(d, overlap)

    pixel = object_pixel_pitch_m(pixel_pitch_m, focal_length_m, distance_m)
    if field_width_m is None:
        capture_px = int(sensor_px) if sensor_px else 256
    else:
        capture_px = max(1, sensor_pixels_across(field_width_m, pixel_pitch_m, focal_length_m, distance_m))
    field = sensor_field_width_m(capture_px, pixel_pitch_m, focal_length_m, distance_m)
    fits = sensor_px is None or capture_px <= sensor_px
    if not fits:
        warnings.append(f"the {field * 1e3:.3g} mm field spans {capture_px} px but the sensor has {sensor_px}: "
                        f"the scene's angular extent ({field / distance_m * 1e3:.3g} mrad) does not fit")

    scale = FourierScale.fraunhofer(wavelength_m, distance_m, field)
    radius = scale.pupil_radius_px(d)
    reach = float(scale.to_pixels((grid - 1) / 2.0 * step))  # the outermost aperture centre (no arrays: grids may be huge)
    layout = band_sizes(reach, radius, sensor_size=max(capture_px, 2))
    k = grid * grid
    spot_synthetic = spot_size_m(wavelength_m, distance_m, achieved * d)
    output_pixel = grid_pixel_m(field, layout.hires_size)
    return ArrayPlan(
        wavelength_m=wavelength_m, focal_length_m=focal_length_m, aperture_diameter_m=d,
        pixel_pitch_m=pixel_pitch_m, distance_m=distance_m, target=kind, target_value=value, overlap=overlap,
        required_sar=required, grid=grid, sar=achieved, synthetic_aperture_m=achieved * d, step_m=step,
        n_images=k, spot_lens_m=spot_lens, spot_synthetic_m=spot_synthetic,
        spot_synthetic_px=spot_synthetic / output_pixel,
        spot_beat_m=spot_size_m(wavelength_m, distance_m, beat_lens_m) if kind == "beat_lens" else None,
        spot_sensor_m=spot_size_m(wavelength_m, focal_length_m, d), object_pixel_m=pixel, field_width_m=field,
        capture_px=capture_px, sensor_px=sensor_px, fits_sensor=fits, pupil_radius_px=radius,
        step_px=float(scale.to_pixels(step)),
        output_px=layout.hires_size, lowres_px=layout.lowres_size,
        output_pixel_m=output_pixel,
        capture_bytes=k * capture_px * capture_px * 4,
        memory_bytes=int(reconstruction_memory_bytes(k, capture_px, layout.lowres_size, layout.hires_size,
                                                     layout.box_size)),
        fft_count_per_iteration=_FFTS_PER_CAPTURE * k, warnings=tuple(warnings),
    )

