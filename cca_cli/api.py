"""The Python interface to cca: arrays in, arrays out, SI units at the boundary.

Import it as ``import cca_cli as cca``; every name below is available there.

Geometry
    :func:`camera_scan` (a camera scanned over a grid of aperture positions),
    :func:`stage_scan` (a camera at measured stage positions), :func:`led_array`
    (an LED-array microscope), :func:`led_grid_sines` (illumination angles of a
    flat LED grid).
Scenes
    :func:`resolution_chart`, :func:`usaf_chart`.
Imaging and recovery
    :func:`simulate` (object → captured intensities), :func:`reconstruct`
    (intensities → :class:`Reconstruction`).
Files
    :func:`load` and :func:`save` of the pipeline's HDF5 files (a
    :class:`CaptureSet` or a :class:`Reconstruction`), :func:`export` of a
    recovery as TIFF, PNG or ``.npy``.
Metrics
    :func:`contrast`, :func:`mtf20`, :func:`usaf_reading`, :func:`rmse`.

Examples
--------
Simulate a small camera array looking at a bar chart 50 m away, recover the
chart and measure the resolution before and after:

>>> import cca_cli as cca
>>> geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
...                            pixel_pitch_m=2e-6, distance_m=50, field_width_m=12e-3, grid=5, overlap=0.61)
>>> geometry.n_images, round(geometry.synthetic_aperture_ratio, 2)
(25, 2.56)
>>> chart = cca.resolution_chart(96, widths=(6, 4, 3, 2))
>>> images = cca.simulate(chart.image, geometry, snr_db=40, seed=1)
>>> images.shape
(25, 96, 96)
>>> result = cca.reconstruct(images, geometry, iterations=30, tol=0)
>>> result.intensity.shape, result.stopped_by
((96, 96), 'plateau')
>>> cca.mtf20(images[geometry.centre_index], chart), cca.mtf20(result.intensity, chart)
(6, 2)
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from cca_cli.errors import ConfigError, InputError
from cca_cli.library.data import CaptureSet, Reconstruction, TiledReconstruction
from cca_cli.sampling.geometry import CaptureGeometry

__all__ = [
    "CaptureGeometry",
    "CaptureSet",
    "Reconstruction",
    "camera_scan",
    "stage_scan",
    "led_array",
    "led_grid_sines",
    "resolution_chart",
    "usaf_chart",
    "simulate",
    "reconstruct",
    "TiledReconstruction",
    "reconstruct_tiles",
    "load",
    "save",
    "export",
    "contrast",
    "mtf20",
    "usaf_reading",
    "rmse",
]


# ---------------------------------------------------------------------------------------------------- checks


def _is_number(value) -> bool:
    """Whether ``value`` is a finite real number (a bool is not one)."""
    return (isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
            and bool(np.isfinite(value)))


def _count(name: str, value) -> int:
    """A whole number ≥ 1 (``10`` or ``10.0``), or ``ValueError`` naming the argument."""
    if not (_is_number(value) and value == int(value) and value >= 1):
        raise ValueError(f"{name} must be a whole number ≥ 1, got {value!r}")
    return int(value)


def _number(name: str, value, *, low: float = -np.inf) -> float:
    """A finite real number ≥ ``low``, or ``ValueError`` naming the argument."""
    if not (_is_number(value) and value >= low):
        bound = "" if low == -np.inf else f" ≥ {low:g}"
        raise ValueError(f"{name} must be a finite number{bound}, got {value!r}")
    return float(value)


def _real_images(values, name: str) -> np.ndarray:
    """``values`` as float32, or ``ValueError`` naming the argument when they are complex, not numbers, or
    images of different shapes."""
    try:
        array = np.asarray(values)
    except ValueError:   # numpy refuses a list of arrays of different shapes
        shapes = sorted({"x".join(map(str, np.shape(v))) for v in values}) if isinstance(values, (list, tuple)) else []
        raise ValueError(f"{name}: the images differ in shape ({', '.join(shapes[:4])}); give images of one "
                         "shape, as one (K, H, W) array") from None
    if np.iscomplexobj(array):
        raise ValueError(f"{name} holds complex values; give real intensities (|field|², ≥ 0)")
    if array.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be real numbers, got {array.dtype} values")
    return array.astype(np.float32)


# ---------------------------------------------------------------------------------------------------- geometry


#: Most aperture positions along a side of a camera scan (a million captures).
MAX_GRID = 1001


def camera_scan(*, wavelength_m: float, focal_length_m: float, aperture_diameter_m: float, pixel_pitch_m: float,
                distance_m: float, field_width_m: float, grid: int | None = None, overlap: float = 0.61,
                sar: float | None = None) -> CaptureGeometry:
    """Geometry of a camera scanned over a square grid of aperture positions (the paper's array).

    Parameters
    ----------
    wavelength_m, focal_length_m, aperture_diameter_m, pixel_pitch_m, distance_m : float
        Illumination wavelength, lens focal length and aperture diameter,
        sensor pixel pitch and object distance (m).
    field_width_m : float
        Object-plane width to image (m); rounded to whole sensor pixels.
    grid : int, optional
        Positions along each side. Give ``grid`` or ``sar``.
    overlap : float
        Linear overlap of neighbouring apertures, ``1 - step/d`` (0.61 by default; above 0.5).
    sar : float, optional
        Synthetic aperture ratio to reach; the grid is the smallest odd one that does.

    Returns
    -------
    CaptureGeometry
        Pupil centres in SI and spectrum pixels; ``field_width_m`` is a whole
        number of sensor pixels.

    Raises
    ------
    ValueError
        Neither or both of ``grid`` and ``sar``, a quantity that is not a positive, finite
        number (named), optics that leave too few pixels, or a grid over :data:`MAX_GRID` a side.

    Examples
    --------
    >>> g = camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3,
    ...                 pixel_pitch_m=2e-6, distance_m=50, field_width_m=64e-3, grid=21, overlap=0.61)
    >>> g.n_images, round(g.synthetic_aperture_ratio, 2), round(g.pupil_radius_px, 2)
    (441, 8.8, 20.95)
    """
    from cca_cli.sampling.geometry import camera_scan_geometry
    from cca_cli.sampling.overlap import grid_for_sar

    if (grid is None) == (sar is None):
        raise ValueError("give either grid (positions per side) or sar (synthetic aperture ratio), not both")
    overlap = _number("overlap", overlap)
    if not 0 <= overlap < 1:
        raise ValueError(f"overlap must be in [0, 1), got {overlap!r}")
    n = _count("grid", grid) if grid is not None else grid_for_sar(_number("sar", sar, low=1.0), overlap)
    if n > MAX_GRID:
        what = f"grid {n}" if grid is not None else f"sar {sar!r} needs a grid of {n} positions per side, which"
        raise ValueError(f"{what} is beyond any array (at most {MAX_GRID} positions per side); check "
                         f"{'grid' if grid is not None else 'sar and overlap'}")
    geometry, _ = camera_scan_geometry(wavelength_m=wavelength_m, focal_length_m=focal_length_m,
                                       aperture_diameter_m=aperture_diameter_m, pixel_pitch_m=pixel_pitch_m,
                                       distance_m=distance_m, field_width_m=field_width_m, grid=n, overlap=overlap)
    return geometry


def stage_scan(positions_yx_m, *, wavelength_m: float, focal_length_m: float, aperture_diameter_m: float,
               pixel_pitch_m: float, distance_m: float, image_pixels: int, camera_index=None) -> CaptureGeometry:
    """Geometry of a camera moved to measured aperture-plane positions (a lab X–Y stage), or of a camera array.

    Parameters
    ----------
    positions_yx_m : array_like, (K, 2)
        Aperture centre [y, x] of each capture in the aperture plane (m); +x is image right, +y image down.
    wavelength_m, focal_length_m, aperture_diameter_m, pixel_pitch_m, distance_m : float
        The camera and the object distance (m).
    image_pixels : int
        Side of the (square) images in sensor pixels.
    camera_index : array_like of int, (K,), optional
        For a camera array: the camera (0, 1, …) of each capture, each with its own lens and pupil
        (``pupil_recovery: per_camera`` recovers one per camera).

    Returns
    -------
    CaptureGeometry

    Raises
    ------
    ValueError
        Positions that are not finite (K, 2) pairs, or a quantity that is not a positive, finite number (named).

    Examples
    --------
    >>> steps = np.array([[y, x] for y in (-1e-3, 0, 1e-3) for x in (-1e-3, 0, 1e-3)])
    >>> g = stage_scan(steps, wavelength_m=633e-9, focal_length_m=75e-3, aperture_diameter_m=2.5e-3,
    ...                pixel_pitch_m=3.75e-6, distance_m=1.5, image_pixels=128)
    >>> g.n_images, g.grid_shape, round(g.field_width_m * 1e3, 3)
    (9, (3, 3), 9.6)
    """
    from cca_cli.sampling.capture import stage_scan_geometry
    from cca_cli.sampling.geometry import check_positive
    from cca_cli.units import sensor_field_width_m

    check_positive(pixel_pitch_m=pixel_pitch_m, focal_length_m=focal_length_m, distance_m=distance_m)
    field_width = sensor_field_width_m(_count("image_pixels", image_pixels), pixel_pitch_m, focal_length_m, distance_m)
    geometry = stage_scan_geometry(positions_yx_m, wavelength_m=wavelength_m, focal_length_m=focal_length_m,
                                   aperture_diameter_m=aperture_diameter_m, pixel_pitch_m=pixel_pitch_m,
                                   distance_m=distance_m, field_width_m=field_width)
    if camera_index is None:
        return geometry
    cameras = np.asarray(camera_index)
    if (cameras.shape != (geometry.n_images,) or not np.issubdtype(cameras.dtype, np.integer)
            or (cameras < 0).any() or (cameras >= 2**31).any()):
        raise ValueError(f"camera_index must hold one camera number ≥ 0 (an integer) per capture, "
                         f"{geometry.n_images} in all; got {cameras.shape} of {cameras.dtype}")
    return replace(geometry, camera_index=cameras.astype(np.int32))


def led_grid_sines(grid: int, *, pitch_m: float, height_m: float, axis_m=(0.0, 0.0)) -> np.ndarray:
    """Illumination sines [sin θy, sin θx] of a flat ``grid x grid`` LED array under the sample.

    Parameters
    ----------
    grid : int
        LEDs along each side (an odd count puts one LED on axis; an even one has none there).
    pitch_m : float
        LED spacing (m).
    height_m : float
        Distance from the LED plane to the sample (m).
    axis_m : (float, float)
        [x, y] where the optical axis meets the LED plane, from the grid's middle (m): a manifest's
        ``illumination.led_axis_m``. An even grid whose LED at (row 4, col 5) of 10 sits on the axis has it at
        ``[0.5 * pitch, -0.5 * pitch]``.

    Returns
    -------
    ndarray, float64, (grid², 2)
        Row-major over the LED grid.

    Raises
    ------
    ValueError
        A grid that is not a whole number ≥ 1, a pitch or height that is not a positive, finite number, or one
        that reads as typed in mm (a pitch of 0.1 m or more, a height of 10 m or more).

    Examples
    --------
    >>> s = led_grid_sines(3, pitch_m=4e-3, height_m=90e-3)
    >>> s.shape, float(s[4, 0]), round(float(s[5, 1]), 4)
    ((9, 2), 0.0, 0.0444)
    """
    from cca_cli.sampling.geometry import check_positive, unit_slip

    grid = _count("grid", grid)
    check_positive(pitch_m=pitch_m, height_m=height_m)
    for name, meaning, value in (("pitch_m", "led_pitch_m", pitch_m), ("height_m", "led_distance_m", height_m)):
        slip = unit_slip(meaning, float(value))
        if slip is not None:
            raise ValueError(f"{name}: {slip}")
    axis = np.asarray(axis_m, np.float64).reshape(-1)
    if axis.shape != (2,) or not np.isfinite(axis).all():
        raise ValueError(f"axis_m: give [x, y] in metres, two finite numbers; got {axis_m!r}")
    offsets = (np.arange(grid) - (grid - 1) / 2) * float(pitch_m)
    y, x = np.meshgrid(offsets - axis[1], offsets - axis[0], indexing="ij")
    r = np.sqrt(x**2 + y**2 + float(height_m) ** 2)
    return np.stack([(y / r).ravel(), (x / r).ravel()], axis=1)


def led_array(sin_yx, *, wavelength_m: float, numerical_aperture: float, pixel_pitch_object_m: float,
              image_pixels: int, sign: int = -1) -> CaptureGeometry:
    """Geometry of an LED-array microscope (Fourier ptychographic microscopy).

    Parameters
    ----------
    sin_yx : array_like, (K, 2)
        Illumination direction of each capture, [sin θy, sin θx] (see :func:`led_grid_sines`): the reverse
        of a manifest's ``kx_norm, ky_norm`` columns.
    wavelength_m : float
        Wavelength (m).
    numerical_aperture : float
        Objective NA.
    pixel_pitch_object_m : float
        Camera pixel at the sample (m).
    image_pixels : int
        Width of the images in pixels (their side, for square ones).
    sign : {-1, +1}
        Which side of DC the pupil of a positive ``sin θ`` sits on (-1: the usual FPM convention).

    Returns
    -------
    CaptureGeometry
        Pupil radius ``NA·W/λ`` pixels; capture k's pupil at ``sign · sin θ · W/λ``.

    Raises
    ------
    ValueError
        Sines that are not finite, real (K, 2) pairs in [-1, 1], an NA outside (0, 1), a quantity that
        is not a positive, finite number (named), or a pixel too coarse for the NA (over λ/(2 NA)).

    Examples
    --------
    >>> g = led_array(led_grid_sines(15, pitch_m=4e-3, height_m=90.88e-3), wavelength_m=532e-9,
    ...               numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6, image_pixels=128)
    >>> g.n_images, round(g.pupil_radius_px, 2), round(g.synthetic_aperture_ratio, 2)
    (225, 44.39, 3.94)
    """
    from cca_cli.sampling.capture import led_array_geometry
    from cca_cli.sampling.geometry import check_positive

    check_positive(pixel_pitch_object_m=pixel_pitch_object_m)
    if np.iscomplexobj(np.asarray(sin_yx)):
        raise ValueError("sin_yx holds complex numbers; give the real sines [sin θy, sin θx]")
    pixels = _count("image_pixels", image_pixels)
    geometry = led_array_geometry(sin_yx, wavelength_m=wavelength_m, numerical_aperture=numerical_aperture,
                                  pixel_pitch_object_m=pixel_pitch_object_m,
                                  field_width_m=pixels * float(pixel_pitch_object_m), sign=sign)
    if geometry.pupil_radius_px > pixels / 2:
        finest = float(wavelength_m) / (2 * float(numerical_aperture))
        raise ValueError(f"numerical_aperture: an NA of {float(numerical_aperture):g} at {float(wavelength_m):g} m "
                         f"needs a camera pixel at the sample of at most λ/(2 NA) = {finest:.3g} m, and "
                         f"pixel_pitch_object_m is {float(pixel_pitch_object_m):g} m: the images cannot sample the "
                         "objective's band; check both (and the magnification)")
    return geometry


# ------------------------------------------------------------------------------------------------------ scenes


def resolution_chart(size_px: int = 512, *, widths=(20, 18, 16, 14, 12, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1)):
    """A bar chart with a known layout (the paper's Fig. 5 target): ``.image`` (amplitude) and ``.groups``.

    Parameters
    ----------
    size_px : int
        Side of the square chart (pixels).
    widths : sequence of int
        Bar widths (pixels), one group of three bars each way per width.

    Returns
    -------
    BarChart
        ``image`` (float32 (size_px, size_px) amplitude in [0, 1]), ``groups`` (where each bar group lies)
        and ``widths``.

    Raises
    ------
    ValueError
        A size that is not a whole number ≥ 1, widths that are not integers ≥ 1, or a chart that does
        not fit ``size_px`` (named).

    Examples
    --------
    >>> chart = resolution_chart(64, widths=(4, 2))
    >>> chart.image.shape, chart.widths
    ((64, 64), (4, 2))
    """
    from cca_cli.targets import resolution_chart as draw

    size = _count("size_px", size_px)
    try:
        widths = tuple(widths)
    except TypeError:
        raise ValueError(f"widths: expected a sequence of integers >= 1, got {widths!r}") from None
    try:
        return draw(size, widths=widths)
    except ValueError as exc:   # the drawing calls it size: name this function's argument
        text = str(exc)
        raise ValueError(f"size_px{text[4:]}" if text.startswith("size:") else text) from None


def usaf_chart(size_px: int, *, pixel_pitch_m: float, groups=(-1, 0, 1, 2, 3)):
    """A USAF-1951 target drawn at ``pixel_pitch_m`` (m per pixel): ``.image`` (amplitude) and ``.elements``.

    Elements too large for ``size_px`` are left out.

    Parameters
    ----------
    size_px : int
        Side of the square chart (pixels).
    pixel_pitch_m : float
        Size of one pixel at the object (m).
    groups : sequence of int
        USAF groups to draw (elements 1-6 of each).

    Returns
    -------
    UsafChart
        ``image`` (float32 (size_px, size_px) amplitude in [0, 1]), ``elements`` (group, element, lp/mm and
        where each lies) and ``size``.

    Raises
    ------
    ValueError
        A size that is not a whole number ≥ 1, or a pixel pitch that is not a positive number (named).

    Examples
    --------
    >>> chart = usaf_chart(512, pixel_pitch_m=25e-6, groups=(0, 1))
    >>> len(chart.elements), chart.elements[0].lp_per_mm
    (12, 1.0)
    """
    from cca_cli.targets import usaf1951_chart

    pitch = _number("pixel_pitch_m", pixel_pitch_m)
    if not pitch > 0:
        raise ValueError(f"pixel_pitch_m must be a positive size at the object (m), got {pixel_pitch_m!r}")
    return usaf1951_chart(_count("size_px", size_px), pixel_pitch_m=pitch, groups=tuple(groups))


# -------------------------------------------------------------------------------------------- imaging, recovery


def simulate(obj, geometry: CaptureGeometry, *, snr_db: float | None = 30.0, photons_per_unit: float | None = None,
             read_noise_e: float = 0.0, seed: int = 0) -> np.ndarray:
    """Images the geometry's cameras record of an object.

    Parameters
    ----------
    obj : array_like, (S, S)
        The object's field over the geometry's field of view (complex, or a
        real amplitude), on any square grid; it is resampled in Fourier space
        to the recovery grid.
    geometry : CaptureGeometry
    snr_db : float or None
        Gaussian noise at this SNR per image, ``σ² = var(I)/10^(SNR/10)`` (the
        paper's definition; at least -10 dB, below which the noise swamps the
        images); None for no Gaussian noise.
    photons_per_unit, read_noise_e : float, optional
        Shot noise (photons per unit intensity, at most 1e12) and read noise
        (electrons) instead of Gaussian noise.
    seed : int
        Seed of the noise (≥ 0).

    Returns
    -------
    ndarray, float32, (K, N, N)
        Intensities on the sensor grid (N pixels across the field), centred,
        in the object's units squared (irradiance).

    Raises
    ------
    ValueError
        An ``obj`` that is not a finite, square 2-D array of numbers, a noise
        setting out of range (each names its argument), or images that would
        not fit the machine's memory (named ``geometry``).

    Examples
    --------
    >>> g = camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
    ...                 pixel_pitch_m=2e-6, distance_m=50, field_width_m=12e-3, grid=3, overlap=0.61)
    >>> flat = simulate(np.ones((96, 96)), g, snr_db=None)
    >>> flat.shape, bool(np.allclose(flat[g.centre_index], 1.0, atol=1e-3))
    ((9, 96, 96), True)
    """
    from cca_cli.library.simulation import simulate as simulate_images

    if not isinstance(geometry, CaptureGeometry):
        raise TypeError(f"geometry: give a CaptureGeometry (camera_scan, stage_scan or led_array), got "
                        f"{type(geometry).__name__}")
    field_in = _object_field(obj)
    noise = _noise(snr_db, photons_per_unit, read_noise_e, seed)
    _check_simulation_memory(geometry)
    return simulate_images(field_in, geometry, noise=noise)


def _check_simulation_memory(geometry: CaptureGeometry) -> None:
    """Refuse, before anything is allocated, images that would not fit the machine's memory (ValueError naming
    ``geometry``): the float32 images themselves, a lower bound of what simulating them takes."""
    from cca_cli.sampling.capture import object_pixel_m
    from cca_cli.io.capacity import memory_available, size_text

    pixels = geometry.field_width_m / object_pixel_m(geometry)
    need = 4.0 * geometry.n_images * pixels * pixels
    have = memory_available()
    if need > have:
        raise ValueError(f"geometry: {geometry.n_images} images of {pixels:.4g}² px need at least {size_text(need)} of "
                         f"memory, more than the {size_text(have)} there is; check the field width and pixel (in "
                         "metres) or use fewer captures")


def _object_field(obj) -> np.ndarray:
    """The object as a finite, square 2-D array of numbers (real or complex), or ``ValueError`` naming ``obj``."""
    field_in = np.asarray(obj)
    if field_in.dtype.kind not in "biufc":
        raise ValueError(f"obj must be numbers (a real amplitude or a complex field), got {field_in.dtype} values")
    if field_in.ndim != 2 or field_in.shape[0] != field_in.shape[1]:
        raise ValueError(f"obj must be a square 2-D array, got shape {field_in.shape}")
    bad = int(np.size(field_in) - np.count_nonzero(np.isfinite(field_in)))
    if bad:
        raise ValueError(f"obj holds {bad} NaN or infinite pixel(s); every pixel of the object must be finite")
    return field_in


def _noise(snr_db, photons_per_unit, read_noise_e, seed):
    """The noise arguments of :func:`simulate`, checked as the config's noise section is."""
    from cca_cli.library.simulation import Noise
    from cca_cli.optics.noise import MIN_SNR_DB

    if snr_db is not None and _number("snr_db", snr_db) < MIN_SNR_DB:
        raise ValueError(f"snr_db {snr_db:g}: the noise would swamp the signal (σ {10 ** (-snr_db / 20):.3g} times "
                         f"each image's standard deviation); use a value of at least {MIN_SNR_DB:g} dB")
    if photons_per_unit is not None and not 0 < _number("photons_per_unit", photons_per_unit) <= 1e12:
        raise ValueError(f"photons_per_unit must be in (0, 1e12] (electrons at irradiance 1), got {photons_per_unit!r}")
    if not (_is_number(seed) and isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ValueError(f"seed must be a whole number ≥ 0, got {seed!r}")
    read_noise = _number("read_noise_e", read_noise_e, low=0.0)
    if photons_per_unit is not None:
        return Noise("poisson", photons_per_unit=photons_per_unit, read_noise_e=read_noise, seed=seed)
    if snr_db is not None:
        return Noise("gaussian", snr_db=snr_db, seed=seed)
    return Noise("none", seed=seed)


def reconstruct(intensities, geometry: CaptureGeometry | None = None, *, engine: str = "auto", weight=None,
                callback: Callable | None = None, init=None, padding: str = "auto", device: str = "cpu",
                boundary: str | None = None, **options) -> Reconstruction:
    """Recover the high-resolution object from captured intensities.

    Parameters
    ----------
    intensities : array_like (K, N, N) or (K, H, W), or CaptureSet
        Captured images (linear, centred), or a :class:`CaptureSet` (which
        brings its geometry, weights, truth, units, boundary and known pupil).
        Non-square images, and recorded ones (a CaptureSet with ``boundary``
        ``open``, as :func:`load` reads an ingested file), are placed in the
        middle of a square grid with a weight-0 guard band
        (:mod:`cca_cli.sampling.region`) and the recovery is cut back to them,
        as ``cca reconstruct`` does.
    geometry : CaptureGeometry
        Where each capture's pupil sits (for non-square images, over a field
        ``W`` pixels wide); not needed with a CaptureSet.
    engine : str
        ``auto`` (the paper's alternating minimisation when a ground truth is
        given, the calibrating ``momentum`` engine for recorded captures; see
        :mod:`cca_cli.engines.presets`), ``altmin`` or ``momentum``.
    weight : array_like, shaped as the images, optional
        Per-pixel confidence in [0, 1].
    callback : callable, optional
        Called after every iteration with its record (``iteration``,
        ``residual``, ``change``, ``seconds``); returning False ends the run
        there (the result's ``stopped_by`` is ``callback``).
    init : path, Reconstruction or array_like (M, M), optional
        Start from this spectrum (a recon.h5, an earlier result, or the array)
        instead of the upsampled centre capture; it must be on the same grid.
    padding : {"auto", "off"}
        ``off`` recovers square recorded images as they are (periodic), like
        ``reconstruct.padding.mode: off``.
    boundary : {"open", "periodic"}, optional
        What plain arrays are: ``open`` for recorded frames (a window on a larger scene: they get the
        guard band, as an ingested file does), ``periodic`` for simulated ones; default periodic for
        square arrays, or the CaptureSet's own.
    device : {"cpu", "cuda", "auto"}
        Where the engine runs, like ``reconstruct.device``: ``cpu``; ``cuda``, the engine's batched
        form on a CUDA GPU through CuPy (``pip install 'cca[gpu]'``); ``auto``, ``cuda`` when CuPy finds
        a GPU and the options run there, else ``cpu``. The result's ``device`` says which ran.
    **options
        The engine's options: ``tau``, ``iterations`` (alias of
        ``max_iterations``), ``tol`` and the engine's own (see
        ``cca_cli.engines.registry.ENGINES[engine].options``).

    Returns
    -------
    Reconstruction

    Raises
    ------
    ValueError
        Unknown engine or option (the message lists the valid ones); images
        that do not match the geometry; intensities or weights the CLI would
        refuse in a captures file (complex, NaN or infinite values, an image
        with a mean below zero beyond its noise, every image flat, weights outside [0, 1]), each
        naming ``intensities`` or ``weight``; or more dead (constant) images
        than can be left out, or a dead centre image. Up to 5% dead images are
        left out with a warning, as ``cca reconstruct`` does. ``device="cuda"`` where CuPy or a GPU
        is missing, or with options the GPU engines do not run (position refinement, brightness,
        held-back captures): one line naming them and the fix.

    Examples
    --------
    >>> g = camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
    ...                 pixel_pitch_m=2e-6, distance_m=50, field_width_m=12e-3, grid=5, overlap=0.61)
    >>> chart = resolution_chart(96, widths=(6, 4, 3, 2))
    >>> result = reconstruct(simulate(chart.image, g, snr_db=40), g, engine="momentum", iterations=10)
    >>> result.iterations <= 10, mtf20(result.intensity, chart)
    (True, 2)
    """
    from cca_cli.engines.registry import resolve
    from cca_cli.library.data import check_intensity, check_weight
    from cca_cli.library.recovery import reconstruct as recover_captures
    from cca_cli.library.stray_light import holds_stray_light

    captures = intensities if isinstance(intensities, CaptureSet) else None
    if captures is not None:
        geometry = captures.geometry if geometry is None else geometry
        weight = captures.weight if weight is None else weight
        intensities = captures.intensity
    if geometry is None:
        raise ValueError("geometry: give the capture geometry (camera_scan, stage_scan or led_array), or a CaptureSet")
    images = _real_images(intensities, "intensities")
    if images.ndim != 3 or len(images) != geometry.n_images:
        hint = ("; the images seem to be stacked along the last axis: np.moveaxis(intensities, -1, 0) puts them first"
                if images.ndim == 3 and images.shape[-1] == geometry.n_images else "")
        raise ValueError(f"intensities must be (K, N, N) or (K, H, W) with K = {geometry.n_images} images of the "
                         f"geometry, got shape {images.shape}{hint}")
    _check_frame_width(images.shape[-1], geometry, "intensities")
    kind = captures.kind if captures is not None else geometry.kind
    frame_scale = captures.frame_scale if captures is not None else "shared"
    try:
        name, engine_options = resolve(engine, kind, options, frame_scale=frame_scale)
    except ValueError as exc:   # name the argument first, as every other refusal here does
        text = str(exc)
        name = "engine" if "is not an engine" in text else "options" if text.startswith("unknown option") else None
        raise ValueError(f"{name}: {text}" if name else text) from None
    check_intensity(images, "intensities")
    weights = None if weight is None else _real_images(weight, "weight")
    if weights is not None:
        check_weight(weights, images.shape, "weight")
    if kind == "led_array" and holds_stray_light(images, geometry.spectrum_centres_yx_px, geometry.pupil_radius_px,
                                                 weights):   # the captures turn the background fit on
        name, engine_options = resolve(engine, kind, options, frame_scale=frame_scale, stray_light=True)
    engine = name
    if boundary not in (None, "open", "periodic"):
        raise ValueError(f"boundary: 'open' (recorded frames) or 'periodic' (simulated ones), got {boundary!r}")
    captures = (CaptureSet(images, geometry, weights) if captures is None
                else replace(captures, intensity=images, weight=weights, geometry=geometry))
    if boundary is not None:
        captures = replace(captures, boundary=boundary)
    if isinstance(init, (str, Path)):
        from cca_cli.io.recon import read_spectrum

        init, _ = read_spectrum(Path(init))
    elif isinstance(init, Reconstruction):
        init = init.spectrum
    return recover_captures(captures, engine=engine, options=engine_options, padding=padding, init=init,
                            on_iteration=callback, device=device)


def reconstruct_tiles(captures, geometry: CaptureGeometry | None = None, *, size_px: int, overlap_px: int,
                      pupil: str = "per_tile", engine: str = "auto", output=None, client=None,
                      workers: int | None = None, scheduler: str | None = None, device: str = "cpu",
                      **options) -> TiledReconstruction:
    """Recover a wide frame in overlapping tiles on Dask, each tile with its own pupil (``cca reconstruct`` with
    ``reconstruct.tiles``).

    Parameters
    ----------
    captures : path, CaptureSet or array_like (K, H, W)
        A captures file (workers read their tiles from it: with ``scheduler`` it must be on a path every
        worker sees), a :class:`CaptureSet`, or images with ``geometry`` (written to a temporary file).
    geometry : CaptureGeometry, optional
        With images: where each capture's pupil sits, over a field ``W`` pixels wide.
    size_px, overlap_px : int
        Tile side and the least overlap between neighbours (frame pixels; overlap below half the tile).
    pupil : {"per_tile", "global"}
        Every tile recovers its own pupil (from a finished neighbour's), or the centre tile's is held fixed.
    engine : str
        ``auto`` (the calibrating preset of the geometry's kind), ``momentum`` or ``altmin``.
    output : path, optional
        Also write the result as a recon.h5 there (``cca report`` reads it).
    client : distributed.Client, optional
        Where the tiles run; default a local cluster of ``workers`` processes (one per core; with
        ``device="cuda"`` also one per core, as many per GPU as its memory holds), or ``scheduler``.
    device : {"cpu", "cuda", "auto"}
        Where every tile's engine runs, as ``reconstruct.device``.
    **options
        ``iterations``, ``tol``, ``tau`` and the engine's options.

    Returns
    -------
    TiledReconstruction

    Raises
    ------
    ValueError
        Images (an array or a CaptureSet) or a captures file that ``cca reconstruct`` would refuse (naming
        ``captures`` or the file), options it would refuse, or ``device="cuda"`` where the tiles cannot run there.
    """
    import contextlib
    import tempfile

    from cca_cli.config.model import ReconstructSection
    from cca_cli.io.h5 import Provenance
    from cca_cli.library.data import check_intensity
    from cca_cli.workflows.cluster import open_client
    from cca_cli.workflows.tiled import reconstruct_tiled, run_fingerprint

    from pydantic import ValidationError

    from cca_cli.values import validation_message

    if "max_iterations" in options:
        options["iterations"] = options.pop("max_iterations")
    section_keys = {key: options.pop(key) for key in ("iterations", "tol", "tau") if key in options}
    try:
        section = ReconstructSection.model_validate({"engine": engine, "options": options, **section_keys,
                                                     "device": device,
                                                     "tiles": {"size_px": size_px, "overlap_px": overlap_px,
                                                               "pupil": pupil}})
    except ValidationError as exc:
        raise ValueError(validation_message(exc)) from None
    with contextlib.ExitStack() as stack:
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="cca-tiles-")))
        if isinstance(captures, (str, Path)):
            path = Path(captures)
        else:
            if not isinstance(captures, CaptureSet):
                if geometry is None:
                    raise ValueError("give the capture geometry with the images, or a CaptureSet or a captures file")
                captures = CaptureSet(_real_images(captures, "captures"), geometry)
            check_intensity(np.asarray(captures.intensity, np.float32), "captures", error=ValueError)
            path = save(captures, folder / "captures.h5")
        if client is None and (workers is not None or scheduler is not None):
            client = stack.enter_context(open_client(workers=workers, scheduler=scheduler))
        target = Path(output) if output is not None else folder / "recon.h5"
        provenance = Provenance.make("reconstruct", "", "", [path])
        try:
            tiled = reconstruct_tiled(path, section, target, run_fingerprint=run_fingerprint(section, [], path),
                                      provenance=provenance, client=client)
        except (ConfigError, InputError) as exc:   # the API's argument names, not the config's keys
            raise ValueError(str(exc).replace("reconstruct.device:", "device:", 1)) from None
        from cca_cli.io.tiles import remove_tile_folder

        if output is not None:
            from cca_cli.io.recon import write_recon

            result, tiles = tiled.as_reconstruction()
            write_recon(target, result, provenance, tiles=tiles)
        remove_tile_folder(target)
    results = tiled.results
    plan = tiled.plan
    have_waves = all(r.zernike_waves is not None for r in results)
    have_pupils = all(r.pupil is not None for r in results)
    return TiledReconstruction(
        object=tiled.object, upsampling=plan.upsampling, pixel_size_m=plan.frame_pixel_m / plan.upsampling,
        boxes_px=np.array([r.box for r in results]),
        zernike_waves=np.stack([np.atleast_2d(r.zernike_waves) for r in results]) if have_waves else None,
        zernike_modes=list(results[0].zernike_modes) if have_waves else [],
        pupils=np.stack([r.pupil for r in results]) if have_pupils else None,
        residual=np.array([[r.residual.get(n, np.nan) for n in ("all", "bright_field", "dark_field")]
                           for r in results]),
        seconds=tiled.seconds, engine=tiled.engine, options=tiled.options)


# ------------------------------------------------------------------------------------------------------- files


def load(path) -> CaptureSet | Reconstruction:
    """Read a pipeline file: a :class:`Reconstruction` from ``recon.h5``, else a :class:`CaptureSet`.

    Parameters
    ----------
    path : path
        ``captures.h5`` (simulate), ``raw.h5`` of single exposures (ingest),
        ``hdr.h5``, ``registered.h5`` or ``recon.h5``.

    Returns
    -------
    Reconstruction or CaptureSet
        A ``recon.h5``'s recovery (object, spectrum, pupil, history, fit); else the captures (intensity,
        weight, geometry) that :func:`reconstruct` takes.

    Raises
    ------
    InputError
        One line naming the file: missing, not a cca file, multiplexed
        captures, or exposure brackets not yet merged.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> g = camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
    ...                 pixel_pitch_m=2e-6, distance_m=50, field_width_m=12e-3, grid=3, overlap=0.61)
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "captures.h5"
    >>> _ = save(CaptureSet(simulate(np.ones((96, 96)), g, snr_db=None), g), path)
    >>> back = load(path)
    >>> back.intensity.shape, back.geometry.n_images
    ((9, 96, 96), 9)
    """
    from cca_cli.io.h5 import open_input

    with open_input(path) as handle:
        stage = str(handle.attrs.get("stage", ""))
        if "multiplex" in handle:
            raise InputError(f"{path}: multiplexed captures cannot be loaded as a CaptureSet yet; "
                             "use cca reconstruct on the file")
    if "reconstruct" in stage.split(","):
        from cca_cli.io.recon import read_recon

        return read_recon(Path(path)).result
    if stage == "ingest":
        with open_input(path) as handle:
            if "/measurements/intensity" not in handle:
                raise InputError(f"{path}: several exposures per position and no /measurements; "
                                 "merge them first with cca hdr")
    from cca_cli.io.captures import read_captures

    return read_captures(Path(path))


def _check_frame_width(width: int, geometry: CaptureGeometry, name: str) -> None:
    """Refuse images whose width is not the field the geometry describes (a crop with the uncropped geometry)."""
    pixel = geometry.pixel_pitch_m * geometry.distance_m / geometry.focal_length_m   # one pixel at the object
    expected = geometry.field_width_m / pixel
    if abs(expected - width) > 0.5:
        fix = (f"image_pixels = {width}" if geometry.kind == "led_array"
               else f"field_width_m = {width * pixel:.6g} (camera_scan) or image_pixels = {width} (stage_scan)")
        raise ValueError(f"{name} are {width} px wide but the geometry's field ({geometry.field_width_m:.6g} m at "
                         f"{pixel:.6g} m a pixel) is {expected:.6g} px: build the geometry with {fix}, or pass the "
                         "images it was built for")


def save(data: CaptureSet | Reconstruction, path, *, force: bool = False) -> Path:
    """Write a :class:`CaptureSet` (as ``captures.h5``) or a :class:`Reconstruction` (as ``recon.h5``).

    The files are the pipeline's own: ``cca reconstruct`` reads the first,
    ``cca report`` and ``cca export`` the second. They appear atomically and an
    existing file is replaced only with ``force``.

    Parameters
    ----------
    data : CaptureSet or Reconstruction
    path : path
        The file to write.
    force : bool
        Replace an existing file that cca wrote.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    OutputExistsError
        ``path`` exists and ``force`` is False.
    ValueError
        A CaptureSet whose images do not match its geometry (count or width).
    TypeError
        ``data`` is neither.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> g = camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
    ...                 pixel_pitch_m=2e-6, distance_m=50, field_width_m=12e-3, grid=3, overlap=0.61)
    >>> path = save(CaptureSet(simulate(np.ones((96, 96)), g, snr_db=None), g),
    ...             pathlib.Path(tempfile.mkdtemp()) / "captures.h5")
    >>> path.name, save(load(path), path, force=True) == path
    ('captures.h5', True)
    """
    import hashlib

    import yaml

    from cca_cli.io.captures import write_capture_set
    from cca_cli.io.h5 import Provenance, check_output
    from cca_cli.io.recon import write_recon

    path = Path(path)
    check_output(path, force=force)
    if isinstance(data, Reconstruction):
        text = yaml.safe_dump({"reconstruct": {"engine": data.engine, "options": data.options}}, sort_keys=False)
        provenance = Provenance.make("reconstruct", text, hashlib.sha256(text.encode()).hexdigest())
        write_recon(path, data, provenance, force=force)
        return path
    if isinstance(data, CaptureSet):
        shape = np.shape(data.intensity)
        if len(shape) != 3 or shape[0] != data.geometry.n_images:
            raise ValueError(f"the CaptureSet holds intensities of shape {shape} but its geometry describes "
                             f"{data.geometry.n_images} captures; give one image per capture")
        _check_frame_width(shape[-1], data.geometry, "the CaptureSet's intensities")
        write_capture_set(path, data, Provenance.make("api", "", ""), force=force)
        return path
    raise TypeError(f"save takes a CaptureSet or a Reconstruction, got {type(data).__name__}")


def export(data, path, *, quantity: str = "amplitude", pixel_size_m: float | None = None, format: str | None = None,
           force: bool = False) -> Path:
    """Write a recovery as float32 TIFF, 16-bit PNG or ``.npy`` with its pixel size (see ``cca export``).

    Parameters
    ----------
    data : Reconstruction, path to recon.h5, or array_like (H, W)
        What to export; an array needs ``pixel_size_m``.
    path : path
        ``.tif``/``.tiff`` (float32 at full resolution), ``.png`` (16-bit,
        ``value = offset + scale · code`` in the text chunks) or ``.npy``.
    quantity : {'amplitude', 'intensity', 'phase'}
    pixel_size_m : float, optional
        Object-plane pixel size (m) of an array.
    format : {'tiff', 'png', 'npy'}, optional
        Overrides the suffix.
    force : bool
        Replace an existing file.

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    ValueError
        A path whose suffix names no format (and no ``format``), an unknown ``quantity``, an array without a
        ``pixel_size_m`` under 1 m, or one that is not a finite, real 2-D image (each names its argument).
    OutputExistsError
        ``path`` exists and ``force`` is not set.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> out = export(np.ones((4, 4)), folder / "flat.tif", quantity="intensity", pixel_size_m=1e-6)
    >>> out.name
    'flat.tif'
    """
    from cca_cli.io.export import QUANTITIES, export_image, export_recon

    _check_export_path(path, format)
    if isinstance(data, (str, Path)):
        return export_recon(data, path, quantity=quantity, format=format, force=force)
    if isinstance(data, Reconstruction):
        if quantity not in QUANTITIES:
            raise ValueError(f"quantity {quantity!r}: choose one of {', '.join(QUANTITIES)}")
        values = {"amplitude": data.amplitude, "intensity": data.intensity, "phase": data.phase}[quantity]
        base = data.units or "irradiance"
        units = {"amplitude": f"√({base})", "intensity": base, "phase": "rad"}[quantity]
        return export_image(values, path, pixel_size_m=data.pixel_size_m, quantity=quantity, units=units,
                            format=format, force=force)
    if quantity not in QUANTITIES:
        raise ValueError(f"quantity {quantity!r}: choose one of {', '.join(QUANTITIES)}")
    if pixel_size_m is None:
        raise ValueError("pixel_size_m: give the object pixel size (m) when exporting an array")
    size = _number("pixel_size_m", pixel_size_m, low=0.0)
    if not 0 < size < 1:
        raise ValueError(f"pixel_size_m {pixel_size_m!r}: give the object pixel size in metres (under 1 m; 125e-6 "
                         "for 125 µm)")
    values = np.asarray(data)
    if values.dtype.kind not in "biuf" or values.ndim != 2 or not np.isfinite(values).all():
        raise ValueError(f"data: give a finite, real 2-D image (H, W), got {values.dtype} values of shape "
                         f"{values.shape}" + ("" if values.dtype.kind not in "biuf" or values.ndim != 2 else
                                              ", some not finite"))
    return export_image(values, path, pixel_size_m=size, quantity=quantity, format=format, force=force)


def _check_export_path(path, format) -> None:
    """A ``format`` cca writes (:data:`~cca_cli.io.export.FORMATS`), or a ``path`` whose suffix names one
    (ValueError naming which)."""
    from cca_cli.io.export import FORMATS

    if format is not None:
        if format not in set(FORMATS.values()):
            raise ValueError(f"format {format!r}: choose one of tiff, png, npy")
        return
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"path {str(path)!r}: its suffix {suffix or '(none)'} names no format cca writes; end it in "
                         ".tif, .png or .npy, or give format")


# ----------------------------------------------------------------------------------------------------- metrics


def contrast(intensity, chart):
    """Bar contrast ``(w̄ − b̄)/(w̄ + b̄)`` of every bar group of a chart, per width and orientation.

    Parameters
    ----------
    intensity : array_like, (S, S)
        Intensity image on the chart's grid.
    chart : BarChart or sequence of BarGroup

    Returns
    -------
    ContrastTable
        ``widths_px``, ``horizontal``, ``vertical`` (and ``to_dict()``).

    Examples
    --------
    >>> chart = resolution_chart(64, widths=(4, 2))
    >>> table = contrast(chart.image ** 2, chart)
    >>> table.widths_px.tolist(), [round(float(c), 3) for c in table.horizontal]
    ([4, 2], [1.0, 1.0])
    """
    from cca_cli.metrics import contrast_table

    return contrast_table(np.asarray(intensity), chart)


def mtf20(intensity, chart, *, threshold: float = 0.2) -> int | None:
    """Finest bar width (px) whose contrast, and every wider one's, reaches ``threshold`` in both orientations.

    Parameters
    ----------
    intensity : array_like, (S, S)
        Intensity (not amplitude) on the chart's grid.
    chart : BarChart
    threshold : float
        Michelson contrast every group down to the limit must reach, in (0, 1).

    Returns
    -------
    int or None
        The limit in pixels of the chart's grid; None when not even the widest group is resolved.

    Raises
    ------
    ValueError
        An image that is not finite, or a threshold outside (0, 1).

    Examples
    --------
    >>> chart = resolution_chart(64, widths=(4, 2))
    >>> mtf20(chart.image ** 2, chart), mtf20(np.ones((64, 64)), chart)
    (2, None)
    """
    from cca_cli.metrics import contrast_table, mtf_limit

    threshold = _number("threshold", threshold)
    if not 0 < threshold < 1:
        raise ValueError(f"threshold must be a contrast in (0, 1), got {threshold!r}")
    image = np.asarray(intensity)
    if image.dtype.kind not in "biuf" or not np.isfinite(image).all():
        raise ValueError("intensity must be finite, real numbers (an intensity image on the chart's grid)")
    return mtf_limit(contrast_table(image, chart), threshold=threshold)


def usaf_reading(intensity, chart, *, threshold: float = 0.2):
    """Finest resolved element of a USAF chart (every coarser one resolved too), with its lp/mm.

    Parameters
    ----------
    intensity : array_like
        Intensity on the chart's grid (``chart.size``).
    chart : UsafChart
    threshold : float
        Three-bar contrast every element must reach in both orientations.

    Returns
    -------
    UsafReading
        ``group``, ``element``, ``lp_per_mm`` (None when nothing is resolved).

    Examples
    --------
    >>> chart = usaf_chart(512, pixel_pitch_m=25e-6, groups=(0, 1))
    >>> reading = usaf_reading(chart.image ** 2, chart)
    >>> reading.group, reading.element, round(reading.lp_per_mm, 2)
    (1, 6, 3.56)
    """
    from cca_cli.metrics import usaf_resolution

    return usaf_resolution(np.asarray(intensity), chart, threshold=threshold)


def rmse(recovered, truth) -> float:
    """RMSE of an intensity against the truth after a least-squares intensity scale, over the truth's maximum.

    Parameters
    ----------
    recovered, truth : array_like, (S, S)
        Intensities on one grid.

    Returns
    -------
    float
        ``‖s·recovered − truth‖_rms / max(truth)`` with ``s`` the least-squares scale.

    Raises
    ------
    ValueError
        Arrays of different shapes, or values that are not finite.

    Examples
    --------
    >>> truth = np.ones((8, 8)); truth[2:4] = 0
    >>> rmse(2 * truth, truth), round(rmse(np.ones((8, 8)), truth), 3)
    (0.0, 0.433)
    """
    from cca_cli.metrics import rmse as _rmse

    return _rmse(np.asarray(recovered), np.asarray(truth))
