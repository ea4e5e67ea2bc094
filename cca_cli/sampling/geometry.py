"""Capture geometry: where every capture's pupil sits, in SI and in spectrum pixels."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from cca_cli.sampling.grid import square_scan
from cca_cli.sampling.overlap import step_m
from cca_cli.units import FourierScale, sensor_field_width_m, sensor_pixels_across

__all__ = ["CaptureGeometry", "camera_scan_geometry", "check_positive", "unit_slip"]


#: Longest wavelength taken as light (m): a larger value is a unit slip (nanometres typed as metres).
MAX_WAVELENGTH_M = 1e-3
#: The longest wavelength of light a camera images with (m): long-wave infrared ends near 15 µm.
MAX_LIGHT_WAVELENGTH_M = 30e-6

#: Lengths (m) no setup reaches, by the name's ending, with the unit a larger value was most likely typed in.
_LARGEST_M = {"pixel_pitch_m": (1e-3, "µm"), "pixel_pitch_object_m": (1e-3, "µm"), "focal_length_m": (10.0, "mm"),
              "aperture_diameter_m": (10.0, "mm"), "led_pitch_m": (0.1, "mm"), "led_distance_m": (10.0, "mm")}
_UNIT_POWER = {"nm": "e-9", "µm": "e-6", "mm": "e-3"}


def unit_slip(name: str, value: float) -> str | None:
    """Why ``value`` (m) for ``name`` reads as typed in nm, µm or mm, with the value to give; None if plausible.

    Examples
    --------
    >>> unit_slip("focal_length_m", 75)
    '75 m is not a plausible focal length: give it in metres (75e-3 for 75 mm)'
    """
    if name.endswith("wavelength_m"):
        largest, unit = MAX_WAVELENGTH_M, "nm" if value >= 100 else "µm"
    else:
        key = next((k for k in _LARGEST_M if name.endswith(k)), None)
        if key is None:
            return None
        largest, unit = _LARGEST_M[key]
        if unit == "µm" and value < 1:
            unit = "mm"   # 0.00345 (mm) rather than 3.45 (µm)
        name = key
    if value < largest:
        return None
    what = {"pixel_pitch_object_m": "object pixel pitch"}.get(name, name[:-2].replace("_", " ").replace("led ", "LED "))
    return f"{value:g} m is not a plausible {what}: give it in metres ({value:g}{_UNIT_POWER[unit]} for {value:g} {unit})"


def check_positive(**values) -> None:
    """Refuse any value that is not a positive, finite number: ``ValueError`` naming the argument.

    Examples
    --------
    >>> check_positive(wavelength_m=550e-9, distance_m=50)
    >>> check_positive(wavelength_m=-5e-7)
    Traceback (most recent call last):
    ...
    ValueError: wavelength_m must be a positive, finite number (SI units), got -5e-07
    """
    for name, value in values.items():
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = math.nan
        if isinstance(value, (str, bytes)):
            raise ValueError(f"{name} must be a positive, finite number (SI units), got the text {value!r}; write "
                             "it without quotes")
        if isinstance(value, (bool, np.bool_)) or not (math.isfinite(number) and number > 0):
            raise ValueError(f"{name} must be a positive, finite number (SI units), got {value!r}")
        if name.endswith("wavelength_m") and number >= MAX_WAVELENGTH_M:
            unit, power = ("nm", "e-9") if number >= 100 else ("µm", "e-6")
            raise ValueError(f"{name} is {number:g} m, not a wavelength of light (cca takes waves under 1 mm): give "
                             f"it in metres ({number:g}{power} for {number:g} {unit})")
        if name.endswith("wavelength_m") and number >= MAX_LIGHT_WAVELENGTH_M:   # 550e-6: µm typed for nm
            nm = number * 1e6
            raise ValueError(f"{name} is {number:g} m ({nm:g} µm), beyond the far infrared: give it in metres "
                             f"({nm:g}e-9 for {nm:g} nm)")
        slip = unit_slip(name, number)
        if slip is not None:
            raise ValueError(f"{name}: {slip}")


@dataclass(frozen=True)
class CaptureGeometry:
    """Optics and per-capture pupil positions of a capture set.

    Attributes
    ----------
    wavelength_m, focal_length_m, aperture_diameter_m, pixel_pitch_m, distance_m : float
        The camera (SI).
    field_width_m : float
        Object-plane width covered by the sensor images (m).
    aperture_centres_yx_m : ndarray, float64, (K, 2)
        Aperture centres in the aperture plane (m).
    spectrum_centres_yx_px : ndarray, float64, (K, 2)
        The same positions in spectrum pixels relative to DC.
    grid_indices : ndarray, int32, (K, 2)
        Grid [row, column] of each capture.
    pupil_radius_px : float
        Pupil radius in spectrum pixels.
    overlap : float
        Linear overlap of neighbouring apertures (nan when not a regular grid).
    kind : str
        ``camera_scan`` (a camera moved in the aperture plane) or ``led_array``
        (fixed objective, tilted illumination; then ``distance_m = focal_length_m = 1``
        so that aperture-plane "metres" are sin θ and ``aperture_diameter_m = 2 NA``).
    numerical_aperture : float
        Objective NA of an LED-array dataset (nan for camera scans).
    camera_index : ndarray, int32, (K,) or None
        Camera of each capture in a camera array (None: one camera, moved or fixed).
    defocus_m : float
        Known distance of the object from focus (LED arrays, m; nan when unknown).
    led_distance_m : float
        Distance of the LED plane from the sample (LED arrays, m; nan when unknown).
    """

    wavelength_m: float
    focal_length_m: float
    aperture_diameter_m: float
    pixel_pitch_m: float
    distance_m: float
    field_width_m: float
    aperture_centres_yx_m: np.ndarray
    spectrum_centres_yx_px: np.ndarray
    grid_indices: np.ndarray
    pupil_radius_px: float
    overlap: float = float("nan")
    kind: str = "camera_scan"
    numerical_aperture: float = float("nan")
    camera_index: np.ndarray | None = None
    defocus_m: float = float("nan")
    led_distance_m: float = float("nan")

    @property
    def n_images(self) -> int:
        """Number of captures K."""
        return int(self.spectrum_centres_yx_px.shape[0])

    @property
    def centre_index(self) -> int:
        """The capture whose pupil is nearest DC (what a single on-axis camera records)."""
        c = self.spectrum_centres_yx_px
        return int(np.argmin(np.hypot(c[:, 0], c[:, 1])))

    @property
    def synthetic_aperture_ratio(self) -> float:
        """Span of all pupils along the wider axis over one pupil diameter."""
        c = self.spectrum_centres_yx_px
        span = max(np.ptp(c[:, 0]), np.ptp(c[:, 1]))
        return float((span + 2.0 * self.pupil_radius_px) / (2.0 * self.pupil_radius_px))

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(rows, columns) of the capture grid."""
        return (int(self.grid_indices[:, 0].max()) + 1, int(self.grid_indices[:, 1].max()) + 1)

    def select(self, keep) -> "CaptureGeometry":
        """The same geometry for the captures ``keep`` only (indices or a boolean mask over K).

        Every per-capture array is indexed alike; :attr:`centre_index` then refers to the kept captures.
        """
        index = np.asarray(keep)
        return replace(self, aperture_centres_yx_m=np.asarray(self.aperture_centres_yx_m)[index],
                       spectrum_centres_yx_px=np.asarray(self.spectrum_centres_yx_px)[index],
                       grid_indices=np.asarray(self.grid_indices)[index],
                       camera_index=None if self.camera_index is None else np.asarray(self.camera_index)[index])


def check_lens(focal_length_m: float, aperture_diameter_m: float) -> None:
    """Refuse an aperture wider than twice the focal length (faster than f/0.5, which no lens is).

    Examples
    --------
    >>> check_lens(0.075, 2.5)
    Traceback (most recent call last):
    ...
    ValueError: aperture_diameter_m: 2.5 m behind a lens of focal_length_m 0.075 m is f/0.03: no lens has so wide a pupil (f/0.5 at most); check both, in metres
    """
    if aperture_diameter_m > 2 * focal_length_m:
        raise ValueError(f"aperture_diameter_m: {aperture_diameter_m:g} m behind a lens of focal_length_m "
                         f"{focal_length_m:g} m is f/{focal_length_m / aperture_diameter_m:.2g}: no lens has so wide a "
                         "pupil (f/0.5 at most); check both, in metres")


def camera_scan_geometry(*, wavelength_m: float, focal_length_m: float, aperture_diameter_m: float,
                         pixel_pitch_m: float, distance_m: float, field_width_m: float, grid: int,
                         overlap: float) -> tuple[CaptureGeometry, int]:
    """Geometry of an ``grid x grid`` aperture scan and the sensor pixels across the field.

    The sensor sees ``N = round(field_width / (pixel_pitch · z / f))`` pixels
    across the field of view; the field width is then taken as ``N`` object
    pixels exactly so that sensor pixels and object pixels coincide.

    Returns
    -------
    geometry : CaptureGeometry
    sensor_pixels : int
        N.

    Raises
    ------
    ValueError
        An optical quantity that is not a positive, finite number (named), a grid below 1, an
        overlap outside [0, 1), or a field of view under 8 sensor pixels.
    """
    check_positive(wavelength_m=wavelength_m, focal_length_m=focal_length_m, aperture_diameter_m=aperture_diameter_m,
                   pixel_pitch_m=pixel_pitch_m, distance_m=distance_m, field_width_m=field_width_m)
    check_lens(focal_length_m, aperture_diameter_m)
    sensor_pixels = sensor_pixels_across(field_width_m, pixel_pitch_m, focal_length_m, distance_m)
    if sensor_pixels < 8:
        raise ValueError(f"the field of view spans only {sensor_pixels} sensor pixels; widen the scene or use smaller pixels")
    field_width = sensor_field_width_m(sensor_pixels, pixel_pitch_m, focal_length_m, distance_m)
    scale = FourierScale.fraunhofer(wavelength_m, distance_m, field_width)
    scan = square_scan(grid, step_m(aperture_diameter_m, overlap))
    geometry = CaptureGeometry(
        wavelength_m=wavelength_m,
        focal_length_m=focal_length_m,
        aperture_diameter_m=aperture_diameter_m,
        pixel_pitch_m=pixel_pitch_m,
        distance_m=distance_m,
        field_width_m=field_width,
        aperture_centres_yx_m=scan.centres_yx_m,
        spectrum_centres_yx_px=scale.to_pixels(scan.centres_yx_m),
        grid_indices=scan.indices.astype(np.int32),
        pupil_radius_px=scale.pupil_radius_px(aperture_diameter_m),
        overlap=overlap,
    )
    return geometry, sensor_pixels
