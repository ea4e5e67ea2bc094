"""The one place where SI quantities become pixels and back.

Two planes matter. The *object plane* is sampled on the simulation or
reconstruction grid: a field of view ``field_width_m`` wide cut into ``n``
pixels. The *Fourier plane* holds the object's spectrum; in the Fraunhofer
regime it is the aperture plane of the cameras, where spatial frequency ``f``
(cycles/m at the object) sits at position ``u = wavelength * distance * f``.

One pixel of a discrete spectrum of the field of view is ``1 / field_width_m``
cycles/m, so one *spectrum pixel* is ``wavelength * distance / field_width_m``
metres of aperture plane, whatever the number of object pixels. Every
aperture diameter, camera position and illumination angle enters the numeric
core through the functions below.

References
----------
J. Holloway, M. S. Asif, M. K. Sharma, N. Matsuda, R. Horstmeyer, O. Cossairt,
A. Veeraraghavan, "Toward long-distance subdiffraction imaging using coherent
camera arrays," IEEE Trans. Comput. Imaging 2(3), 251-265 (2016).
:DOI:`10.1109/TCI.2016.2557067`
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "AIRY_SPOT_FACTOR",
    "FourierScale",
    "grid_pixel_m",
    "object_pixel_pitch_m",
    "sensor_field_width_m",
    "sensor_pixels_across",
    "spot_size_m",
    "led_fourier_scale",
]

#: Diameter of the Airy disc's first dark ring in units of wavelength * distance / aperture.
AIRY_SPOT_FACTOR = 2.44


def object_pixel_pitch_m(pixel_pitch_m: float, focal_length_m: float, distance_m: float) -> float:
    """Size of one sensor pixel projected onto the object.

    Parameters
    ----------
    pixel_pitch_m : float
        Sensor pixel pitch (m).
    focal_length_m : float
        Lens focal length (m).
    distance_m : float
        Object distance (m).

    Returns
    -------
    float
        Object-plane pixel pitch ``pixel_pitch_m * distance_m / focal_length_m`` (m).
    """
    return pixel_pitch_m * distance_m / focal_length_m


def sensor_field_width_m(n_pixels: int, pixel_pitch_m: float, focal_length_m: float, distance_m: float) -> float:
    """Object-plane width seen by ``n_pixels`` sensor pixels (m)."""
    return n_pixels * object_pixel_pitch_m(pixel_pitch_m, focal_length_m, distance_m)


def sensor_pixels_across(field_width_m: float, pixel_pitch_m: float, focal_length_m: float, distance_m: float) -> int:
    """Whole sensor pixels across an object-plane field (the inverse of :func:`sensor_field_width_m`, rounded).

    Parameters
    ----------
    field_width_m : float
        Object-plane width (m).
    pixel_pitch_m, focal_length_m, distance_m : float
        Sensor pixel pitch, focal length and object distance (m).

    Returns
    -------
    int
        ``round(field_width_m / object_pixel_pitch_m(...))``.
    """
    return int(round(field_width_m / object_pixel_pitch_m(pixel_pitch_m, focal_length_m, distance_m)))


def grid_pixel_m(field_width_m: float, n_pixels: int) -> float:
    """Object-plane size of one pixel of an ``n_pixels`` grid spanning ``field_width_m``.

    Parameters
    ----------
    field_width_m : float
        Object-plane width of the grid (m).
    n_pixels : int
        Pixels across the grid (e.g. the recovered image's side M).

    Returns
    -------
    float
        Pixel pitch at the object (m).
    """
    return field_width_m / n_pixels


def spot_size_m(wavelength_m: float, distance_m: float, aperture_diameter_m: float) -> float:
    """Diffraction spot (Airy disc) diameter ``2.44 * wavelength * distance / aperture``.

    With ``distance_m`` the focal length this is the spot on the sensor; with
    the object distance it is the smallest resolvable feature at the object.

    Parameters
    ----------
    wavelength_m, distance_m, aperture_diameter_m : float
        Wavelength, propagation distance and aperture diameter (m).

    Returns
    -------
    float
        Spot diameter (m).
    """
    return AIRY_SPOT_FACTOR * wavelength_m * distance_m / aperture_diameter_m


@dataclass(frozen=True)
class FourierScale:
    """Conversion between aperture-plane metres and spectrum pixels.

    Parameters
    ----------
    metres_per_pixel : float
        Aperture-plane distance spanned by one spectrum pixel (m/px).

    Notes
    -----
    For a camera at distance ``z`` from an object of field of view ``W`` under
    wavelength ``λ`` (Fraunhofer), ``metres_per_pixel = λ z / W``. Build it with
    :meth:`fraunhofer`. LED-array microscopes use :func:`led_fourier_scale`.
    """

    metres_per_pixel: float

    @classmethod
    def fraunhofer(cls, wavelength_m: float, distance_m: float, field_width_m: float) -> "FourierScale":
        """Scale of the aperture plane for an object ``field_width_m`` wide at ``distance_m``."""
        return cls(wavelength_m * distance_m / field_width_m)

    def to_pixels(self, aperture_plane_m):
        """Aperture-plane length or position (m) → spectrum pixels (float)."""
        return np.asarray(aperture_plane_m, dtype=np.float64) / self.metres_per_pixel

    def to_metres(self, pixels):
        """Spectrum pixels → aperture-plane length or position (m)."""
        return np.asarray(pixels, dtype=np.float64) * self.metres_per_pixel

    def pupil_radius_px(self, aperture_diameter_m: float) -> float:
        """Radius (spectrum pixels) of a circular aperture of the given diameter."""
        return float(self.to_pixels(aperture_diameter_m / 2.0))

    def illumination_shift_px(self, source_offset_m, source_distance_m: float, object_distance_m: float):
        """Spectrum shift (pixels) made by a point source off the optical axis.

        A source ``x_s`` metres off axis at ``z_s`` metres from the object tilts
        the illuminating plane wave by ``x_s / z_s`` radians, which moves the
        object's spectrum by ``(x_s / z_s) / λ`` cycles/m, i.e. by the same
        amount as moving the aperture ``(x_s / z_s) · z`` metres in the
        aperture plane at the object distance ``z``.

        Parameters
        ----------
        source_offset_m : array_like
            Transverse source position(s) relative to the optical axis (m).
        source_distance_m : float
            Distance from the sources to the object (m).
        object_distance_m : float
            Distance from the object to the aperture plane (m), the ``z`` of this scale.

        Returns
        -------
        ndarray, float64
            Shift(s) in spectrum pixels, same shape as ``source_offset_m``.
        """
        if not source_distance_m > 0:
            raise ValueError(f"source distance must be positive, got {source_distance_m}")
        offsets = np.asarray(source_offset_m, dtype=np.float64)
        return self.to_pixels(offsets / source_distance_m * object_distance_m)


def led_fourier_scale(wavelength_m: float, field_width_m: float) -> FourierScale:
    """Spectrum scale of an LED-array (angle-scan) microscope, in units of numerical aperture.

    A spatial frequency ``sin(θ)/λ`` (an illumination angle or an objective NA)
    sits ``sin(θ) * field_width_m / wavelength_m`` spectrum pixels from DC, so
    with ``metres_per_pixel = wavelength_m / field_width_m`` the helpers of
    :class:`FourierScale` take dimensionless NA or ``sin θ`` values in place of
    metres.

    Parameters
    ----------
    wavelength_m : float
        Illumination wavelength (m).
    field_width_m : float
        Object-plane field of view of the reconstruction grid (m).
    """
    return FourierScale(wavelength_m / field_width_m)
