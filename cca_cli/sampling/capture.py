"""Capture geometry of recorded data: stage positions or illumination angles → spectrum offsets.

This is the one place where the positions listed in a capture manifest
become pupil centres in spectrum pixels; the conversions themselves are
:class:`cca_cli.units.FourierScale` (camera scan, Fraunhofer) and
:func:`cca_cli.units.led_fourier_scale` (LED array, ``sin θ``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from cca_cli.sampling.geometry import CaptureGeometry, check_lens, check_positive
from cca_cli.units import FourierScale, led_fourier_scale, object_pixel_pitch_m

__all__ = ["stage_scan_geometry", "led_array_geometry", "with_field_width", "object_pixel_m", "grid_from_positions"]


def grid_from_positions(positions_yx: np.ndarray) -> np.ndarray:
    """Grid [row, column] of each position: the rank of its y and x among the rows and columns they form.

    Along each axis, sorted values closer than a quarter of the usual distance between neighbouring positions
    belong to one row (column): an LED matrix's sines, whose x drifts with y, or stage readings that jitter,
    keep the matrix's rows and columns. Values closer than 1e-9 of the largest span are always taken as equal.
    """
    pos = np.asarray(positions_yx, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(pos.shape, np.int32)
    if len(pos) < 2:
        return out
    from scipy.spatial import cKDTree

    spacing = float(np.median(cKDTree(pos).query(pos, k=2)[0][:, 1]))
    for axis in range(2):
        span = max(float(np.ptp(pos[:, axis])), 1e-300)
        order = np.argsort(pos[:, axis], kind="stable")
        gaps = np.diff(pos[order, axis])
        out[order, axis] = np.concatenate([[0], np.cumsum(gaps > max(0.25 * spacing, 1e-9 * span))])
    return out


def stage_scan_geometry(positions_yx_m, *, wavelength_m: float, focal_length_m: float, aperture_diameter_m: float,
                        pixel_pitch_m: float, distance_m: float, field_width_m: float,
                        grid_indices=None) -> CaptureGeometry:
    """Geometry of a camera moved to the given aperture-plane positions.

    Parameters
    ----------
    positions_yx_m : array_like, (K, 2)
        Camera (aperture) centre [y, x] in the aperture plane (m), e.g. the
        X–Y stage readings.
    wavelength_m, focal_length_m, aperture_diameter_m, pixel_pitch_m, distance_m : float
        The camera and object distance (SI).
    field_width_m : float
        Object-plane width of the (square) images the recovery will use (m).
    grid_indices : array_like, (K, 2), optional
        Grid [row, column]; derived from the positions when omitted.

    Returns
    -------
    CaptureGeometry
        ``kind="camera_scan"``; spectrum centres ``positions / (λ z / W)``.

    Raises
    ------
    ValueError
        Positions that are not finite [y, x] pairs, or an optical quantity that is not a positive,
        finite number (named).
    """
    check_positive(wavelength_m=wavelength_m, focal_length_m=focal_length_m, aperture_diameter_m=aperture_diameter_m,
                   pixel_pitch_m=pixel_pitch_m, distance_m=distance_m, field_width_m=field_width_m)
    check_lens(focal_length_m, aperture_diameter_m)
    pos = _pairs(positions_yx_m, "positions_yx_m")
    scale = FourierScale.fraunhofer(wavelength_m, distance_m, field_width_m)
    grid = grid_from_positions(pos) if grid_indices is None else np.asarray(grid_indices, np.int32)
    return CaptureGeometry(
        wavelength_m=float(wavelength_m), focal_length_m=float(focal_length_m),
        aperture_diameter_m=float(aperture_diameter_m), pixel_pitch_m=float(pixel_pitch_m),
        distance_m=float(distance_m), field_width_m=float(field_width_m), aperture_centres_yx_m=pos,
        spectrum_centres_yx_px=scale.to_pixels(pos), grid_indices=grid,
        pupil_radius_px=scale.pupil_radius_px(aperture_diameter_m), kind="camera_scan")


def led_array_geometry(sin_yx, *, wavelength_m: float, numerical_aperture: float, pixel_pitch_object_m: float,
                       field_width_m: float, sign: int = -1, grid_indices=None) -> CaptureGeometry:
    """Geometry of an LED-array (angle-scan) microscope.

    A plane wave tilted by ``sin θ`` shifts the object's spectrum by
    ``sin θ · W / λ`` pixels; the fixed objective then passes the region of
    the original spectrum centred at ``sign · sin θ · W / λ`` (``sign = -1``
    for the convention of Zheng's reference code, where image k's
    sub-aperture sits at ``centre − k0 kx / dk``). The pupil radius is
    ``NA · W / λ`` pixels.

    Parameters
    ----------
    sin_yx : array_like, (K, 2)
        Normalised illumination wave-vector [ky, kx] = [sin θy, sin θx].
    wavelength_m, numerical_aperture, pixel_pitch_object_m, field_width_m : float
        Wavelength, objective NA, camera pixel at the sample and image width (m).
    sign : {-1, +1}
        Which side of DC the pupil sits on for a positive ``sin θ``.

    Returns
    -------
    CaptureGeometry
        ``kind="led_array"`` with ``distance_m = focal_length_m = 1`` so that
        aperture-plane "metres" are ``sin θ`` values and
        ``aperture_diameter_m = 2 NA``: every SI helper (spot size, SAR) then
        reads correctly at the object.

    Raises
    ------
    ValueError
        Sines that are not finite pairs in [-1, 1], an NA outside (0, 1), another ``sign``, or a
        wavelength, pixel or field that is not a positive, finite number (named).
    """
    if sign not in (-1, 1):
        raise ValueError(f"sign must be -1 or +1, got {sign}")
    check_positive(wavelength_m=wavelength_m, pixel_pitch_object_m=pixel_pitch_object_m, field_width_m=field_width_m)
    if isinstance(numerical_aperture, bool) or not 0 < _float(numerical_aperture) < 1:
        raise ValueError(f"numerical_aperture must be a number in (0, 1), got {numerical_aperture!r}")
    sines = _pairs(sin_yx, "sin_yx")
    if (np.abs(sines) > 1).any():
        raise ValueError(f"sin_yx holds sines beyond ±1 (largest {float(np.abs(sines).max()):.4g}); give sin θ, "
                         "not angles or positions")
    centres = sign * sines
    scale = led_fourier_scale(wavelength_m, field_width_m)
    grid = grid_from_positions(centres) if grid_indices is None else np.asarray(grid_indices, np.int32)
    return CaptureGeometry(
        wavelength_m=float(wavelength_m), focal_length_m=1.0, aperture_diameter_m=2.0 * float(numerical_aperture),
        pixel_pitch_m=float(pixel_pitch_object_m), distance_m=1.0, field_width_m=float(field_width_m),
        aperture_centres_yx_m=centres, spectrum_centres_yx_px=scale.to_pixels(centres), grid_indices=grid,
        pupil_radius_px=scale.pupil_radius_px(2.0 * float(numerical_aperture)), kind="led_array",
        numerical_aperture=float(numerical_aperture))


def _float(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def _pairs(values, name: str) -> np.ndarray:
    """``values`` as a finite float64 (K, 2) array of [y, x] pairs, or ``ValueError`` naming the argument."""
    try:
        pairs = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers, shape (K, 2)") from None
    if pairs.shape == (2,):
        pairs = pairs[None]
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.shape[0] == 0:
        raise ValueError(f"{name} must have shape (K, 2) with K ≥ 1 ([y, x] of each capture), got {pairs.shape}")
    if not np.isfinite(pairs).all():
        raise ValueError(f"{name} holds NaN or infinite values (row {int(np.argmax(~np.isfinite(pairs).all(1)))})")
    return pairs


def object_pixel_m(geometry: CaptureGeometry) -> float:
    """Size of one image pixel at the object (m)."""
    return object_pixel_pitch_m(geometry.pixel_pitch_m, geometry.focal_length_m, geometry.distance_m)


def with_field_width(geometry: CaptureGeometry, field_width_m: float, *, keep=None) -> CaptureGeometry:
    """The same captures seen over another field width (after a crop), optionally a subset ``keep``.

    Spectrum centres and the pupil radius scale with the field width
    (one spectrum pixel is ``λ z / W`` of aperture plane).
    """
    index = slice(None) if keep is None else np.asarray(keep, dtype=np.intp)
    centres_m = np.asarray(geometry.aperture_centres_yx_m)[index]
    scale = FourierScale.fraunhofer(geometry.wavelength_m, geometry.distance_m, field_width_m)
    return replace(geometry, field_width_m=float(field_width_m), aperture_centres_yx_m=centres_m,
                   spectrum_centres_yx_px=scale.to_pixels(centres_m),
                   grid_indices=np.asarray(geometry.grid_indices)[index],
                   camera_index=None if geometry.camera_index is None else np.asarray(geometry.camera_index)[index],
                   pupil_radius_px=scale.pupil_radius_px(geometry.aperture_diameter_m))
