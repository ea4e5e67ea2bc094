"""Report extras: single-lens baselines, USAF reading and speckle contrast.

Baselines are computed from the ground-truth object on the truth grid (an
ideal sensor for every lens, noise-free), so the recovered image, the
array's own lens and a large lens are compared on the same pixels.
"""

from __future__ import annotations

import numpy as np

from cca_cli.metrics import contrast_table, mtf_limit, rmse, speckle_contrast, usaf_gain, usaf_resolution
from cca_cli.optics.baselines import coherent_image, incoherent_image
from cca_cli.optics.fft import fourier_interpolate
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.units import FourierScale, spot_size_m

__all__ = ["baseline_images", "baseline_details", "compare_images", "usaf_summary", "speckle_summary", "region_px",
           "field_intensity_on_grid"]


def baseline_images(truth_field: np.ndarray, geometry: CaptureGeometry, specs) -> dict[str, np.ndarray]:
    """Images of the truth through single lenses, on the truth grid.

    Parameters
    ----------
    truth_field : ndarray, complex, (M, M)
        Ground-truth object field.
    geometry : CaptureGeometry
        The array's optics (wavelength, distance, field width, lens aperture).
    specs : sequence of BaselineSpec
        ``passive_incoherent`` (the array's lens, incoherent light) or
        ``lens`` with ``aperture_diameter_m`` and ``illumination``.

    Returns
    -------
    dict
        ``label → image`` (float32, (M, M), irradiance); see :func:`baseline_details`.
    """
    scale = FourierScale.fraunhofer(geometry.wavelength_m, geometry.distance_m, geometry.field_width_m)
    out = {}
    for spec in specs:
        diameter, light = _spec_optics(spec, geometry)
        radius = scale.pupil_radius_px(diameter)
        image = coherent_image(truth_field, radius) if light == "coherent" else incoherent_image(truth_field, radius)
        out[spec.label()] = image
    return out


def _spec_optics(spec, geometry: CaptureGeometry) -> tuple[float, str]:
    """Aperture diameter (m) and illumination of a baseline; ``passive_incoherent`` is the array's own lens."""
    if spec.kind == "passive_incoherent":
        return geometry.aperture_diameter_m, "incoherent"
    return spec.aperture_diameter_m, spec.illumination


def _spec_info(spec, geometry: CaptureGeometry) -> dict:
    diameter, light = _spec_optics(spec, geometry)
    return {"kind": spec.kind, "aperture_diameter_m": diameter, "illumination": light,
            "spot_size_object_m": spot_size_m(geometry.wavelength_m, geometry.distance_m, diameter)}


def compare_images(images: dict[str, np.ndarray], truth: np.ndarray, bars, *, threshold: float) -> dict:
    """MTF20, RMSE and contrast table of each image (all on the truth grid)."""
    out = {}
    for name, image in images.items():
        entry = {"rmse": rmse(image, truth)}
        if bars:
            table = contrast_table(image, bars)
            entry["mtf20_px"] = mtf_limit(table, threshold=threshold)
            entry["contrast"] = table.to_dict()
        out[name] = entry
    return out


def field_intensity_on_grid(field: np.ndarray, size: int) -> np.ndarray:
    """``|field|²`` on a ``size`` x ``size`` grid, the field resampled first.

    Parameters
    ----------
    field : ndarray, complex, (M, M)
        Band-limited complex field (e.g. the recovered object).
    size : int
        Output side, ``>= M`` for an exact result.

    Returns
    -------
    ndarray, float32, (size, size)
        Intensity, scaled so a constant field keeps its value.

    Notes
    -----
    The intensity of a field band-limited to the grid's Nyquist frequency
    has twice that bandwidth, so ``|field|²`` on the field's own grid is
    aliased; zero-padding the field's spectrum before squaring is not.
    """
    field = np.asarray(field, np.complex64)
    n = field.shape[-1]
    if size == n:
        return (np.abs(field) ** 2).astype(np.float32)
    return (np.abs(fourier_interpolate(field, (size, size))) ** 2).astype(np.float32)


def usaf_summary(images: dict[str, np.ndarray], chart, *, threshold: float, criterion: str = "three_bar") -> dict:
    """USAF reading (finest resolved group/element and lp/mm) of every image, and the gain recovered/observed.

    ``criterion`` is passed to :func:`cca_cli.metrics.usaf_resolution`
    (default: every gap darker than both neighbouring bars).
    """
    readings = {name: usaf_resolution(image, chart, threshold=threshold, criterion=criterion)
                for name, image in images.items()}
    out = {}
    for name, r in readings.items():
        d = r.to_dict()
        d.pop("contrasts")
        out[name] = d
    if "observed" in readings and "recovered" in readings:
        out["gain"] = usaf_gain(readings["observed"], readings["recovered"])
    out["elements"] = [{"group": c.group, "element": c.element, "lp_per_mm": c.lp_per_mm}
                       for c in readings[next(iter(readings))].contrasts]
    return out


def region_px(fractions, size) -> tuple[int, int, int, int]:
    """A region given as fractions of the field → a half-open pixel box on a grid of ``size`` (``n`` or ``(h, w)``).

    Rows are fractions of the field's height, columns of its width.
    """
    rows, cols = (int(size), int(size)) if np.ndim(size) == 0 else (int(v) for v in tuple(size)[-2:])
    y0, y1, x0, x1 = (float(v) for v in fractions)
    box = (int(round(y0 * rows)), int(round(y1 * rows)), int(round(x0 * cols)), int(round(x1 * cols)))
    if not (0 <= box[0] < box[1] <= rows and 0 <= box[2] < box[3] <= cols):
        raise ValueError(f"report.speckle_region {list(fractions)} is not a box inside the field (fractions 0…1)")
    return box


def speckle_summary(images: dict[str, np.ndarray], fractions) -> dict[str, float]:
    """Speckle contrast σ/μ of every image over the region (fractions of the field)."""
    return {name: speckle_contrast(image, region_px(fractions, image.shape[-2:])) for name, image in images.items()}


def baseline_details(specs, geometry: CaptureGeometry) -> dict:
    """Aperture, illumination and spot size of each baseline, by label."""
    return {spec.label(): _spec_info(spec, geometry) for spec in specs}
