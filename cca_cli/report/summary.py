"""The report's numbers: resolution, error and geometry of one reconstruction."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.metrics import contrast_table, mtf_limit, resolution_gain, rmse
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import band_layout
from cca_cli.targets import BarGroup
from cca_cli.units import grid_pixel_m, spot_size_m

__all__ = ["ReportInputs", "summarize", "derived_quantities", "on_grid", "band_limited_truth", "sharpness_summary"]


@dataclass(frozen=True)
class ReportInputs:
    """Arrays a report is computed from (all intensities in irradiance units)."""

    geometry: CaptureGeometry
    observed: np.ndarray          # (N, N) centre capture, or (h, w) over a recovered region
    recovered: np.ndarray         # (M, M) recovered intensity, or (H, W) of a region of the M x M grid
    truth: np.ndarray | None      # (Mt, Mt) truth intensity
    bars: tuple[BarGroup, ...]    # layout on the truth grid
    engine: str
    iterations: int
    seconds: float
    hires_size: int
    lowres_size: int
    truth_field: np.ndarray | None = None   # (Mt, Mt) complex truth, for the band-limited error


def band_limited_truth(truth_field: np.ndarray, geometry: CaptureGeometry) -> np.ndarray | None:
    """Intensity of the truth seen through the synthetic aperture (union of all pupils).

    This is the best any reconstruction from these captures can do; the error
    against it measures phase retrieval alone, without the detail no aperture
    position could see. None if the band does not fit the truth grid.
    """
    size = truth_field.shape[-1]
    try:
        layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, hires_size=size)
    except ValueError:
        return None
    pupils = circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px)
    coverage = ForwardModel(layout, pupils).normal_diagonal() > 0
    field = fft.ifft2c(fft.fft2c(np.asarray(truth_field, np.complex64)) * coverage)
    return (np.abs(field) ** 2).astype(np.float32)


def on_grid(image: np.ndarray, size) -> np.ndarray:
    """A band-limited intensity resampled to ``size`` x ``size`` (or to ``size = (h, w)``), value-preserving."""
    shape = (int(size), int(size)) if np.ndim(size) == 0 else tuple(int(v) for v in size)
    image = np.asarray(image, np.float32)
    if image.shape[-2:] == shape or (np.ndim(size) == 0 and image.shape[-1] == shape[-1]):
        return image
    if image.shape[-1] == image.shape[-2] and shape[0] == shape[1]:
        return fft.fourier_resample(image[None], shape[0])[0]
    return fft.fourier_interpolate(image, shape).real.astype(np.float32)


def summarize(inputs: ReportInputs, *, threshold: float = 0.2) -> dict:
    """The report dictionary (JSON-ready).

    Keys include ``sar``, ``grid``, ``overlap``, ``n_images``, ``engine``,
    ``iterations``, ``seconds``, ``mtf20_observed_px``, ``mtf20_recovered_px``,
    ``resolution_gain``, ``rmse_observed``, ``rmse_recovered``,
    ``spot_size_sensor_m``, ``spot_size_object_m``, ``recovered_shape_px``
    and ``recovered_field_m`` (``[height, width]`` of the recovered image in
    pixels and at the object: a region of the recovery grid may be neither
    the whole grid nor square) and the contrast per bar width of both images.

    Notes
    -----
    RMSE compares intensities on the truth grid after a least-squares
    intensity scale, normalised by the truth's maximum
    (:func:`cca_cli.metrics.rmse`). ``rmse_*_band`` compare with the
    band-limited truth (:func:`band_limited_truth`) instead.
    """
    g = inputs.geometry
    derived = derived_quantities(g, hires_size=inputs.hires_size, lowres_size=inputs.lowres_size)
    out = {key: derived[key] for key in ("sar", "grid", "overlap", "n_images")}
    out.update({"engine": inputs.engine, "iterations": int(inputs.iterations),
                "seconds": round(float(inputs.seconds), 3)})
    out.update({key: value for key, value in derived.items() if key not in out})
    rows, cols = inputs.recovered.shape[-2:]
    pixel = grid_pixel_m(g.field_width_m, inputs.hires_size)
    out["recovered_shape_px"] = [int(rows), int(cols)]
    out["recovered_field_m"] = [rows * pixel, cols * pixel]
    out["mtf_threshold"] = threshold
    if inputs.truth is None:
        out.update(sharpness_summary(inputs))
        return out
    size = inputs.truth.shape[-1]
    observed = on_grid(inputs.observed, size)
    recovered = on_grid(inputs.recovered, size)
    out["rmse_observed"] = rmse(observed, inputs.truth)
    out["rmse_recovered"] = rmse(recovered, inputs.truth)
    if inputs.truth_field is not None:
        band_truth = band_limited_truth(inputs.truth_field, g)
        if band_truth is not None:
            out["rmse_observed_band"] = rmse(observed, band_truth)
            out["rmse_recovered_band"] = rmse(recovered, band_truth)
    if inputs.bars:
        table_obs = contrast_table(observed, inputs.bars)
        table_rec = contrast_table(recovered, inputs.bars)
        lim_obs = mtf_limit(table_obs, threshold=threshold)
        lim_rec = mtf_limit(table_rec, threshold=threshold)
        out["mtf20_observed_px"] = lim_obs
        out["mtf20_recovered_px"] = lim_rec
        out["resolution_gain"] = resolution_gain(lim_obs, lim_rec)
        # a limit at the chart's finest bar is a bound: the image may resolve finer bars the chart lacks
        finest = min(int(bar.width_px) for bar in inputs.bars)
        out["mtf20_at_finest_bar"] = {"observed": lim_obs == finest, "recovered": lim_rec == finest}
        out["contrast_observed"] = table_obs.to_dict()
        out["contrast_recovered"] = table_rec.to_dict()
    return out


def derived_quantities(geometry: CaptureGeometry, *, sensor_pixels: int | None = None, hires_size: int | None = None,
                       lowres_size: int | None = None) -> dict:
    """The quantities a capture geometry implies: SAR, step, pupil radius, spot sizes, image count, output grid.

    Parameters
    ----------
    geometry : CaptureGeometry
    sensor_pixels : int, optional
        Side of the captured images; used to work out the output grid when
        ``hires_size`` is not given.
    hires_size, lowres_size : int, optional
        Recovery grid and per-capture band grid (px), when already known.

    Returns
    -------
    dict
        ``kind``, ``n_images``, ``grid`` ([rows, columns]), ``overlap`` (the
        grid's; for recorded positions ``1 − s / d`` with ``s`` the median
        distance to the nearest position, at least 0; None for one position),
        ``sar``, ``step_m`` (aperture-plane distance
        of neighbouring positions; sin θ for LED arrays), ``pupil_radius_px``
        (``d·W/(2λz)``), ``spot_size_sensor_m`` (``2.44·λ·f/d``, camera scans
        only), ``spot_size_object_m`` (``2.44·λ·z/d``),
        ``spot_size_synthetic_object_m`` (the same for an aperture SAR·d), and,
        when the grid is known, ``output_grid_px``, ``lowres_grid_px`` and
        ``object_pixel_m``.
    """
    g = geometry
    sar = g.synthetic_aperture_ratio
    out = {
        "kind": g.kind,
        "sar": round(sar, 4),
        "grid": list(g.grid_shape),
        "overlap": None if np.isnan(g.overlap) else g.overlap,
        "n_images": g.n_images,
        "pupil_radius_px": round(g.pupil_radius_px, 4),
        "step_m": _step_m(g),
    }
    if out["overlap"] is None and g.n_images > 1:   # recorded positions: the overlap their usual spacing gives
        out["overlap"] = round(max(0.0, 1.0 - _usual_step_m(g) / g.aperture_diameter_m), 4)
    if hires_size is None and sensor_pixels is not None:
        try:
            layout = band_layout(g.spectrum_centres_yx_px, g.pupil_radius_px, sensor_size=int(sensor_pixels))
            hires_size, lowres_size = layout.hires_size, layout.lowres_size
        except ValueError:
            pass
    if hires_size is not None:
        out["output_grid_px"] = int(hires_size)
        if lowres_size is not None:
            out["lowres_grid_px"] = int(lowres_size)
        out["object_pixel_m"] = grid_pixel_m(g.field_width_m, int(hires_size))
    if g.kind != "led_array":   # an LED array's objective has no stated focal length on the sensor side
        out["spot_size_sensor_m"] = spot_size_m(g.wavelength_m, g.focal_length_m, g.aperture_diameter_m)
    out["spot_size_object_m"] = spot_size_m(g.wavelength_m, g.distance_m, g.aperture_diameter_m)
    out["spot_size_synthetic_object_m"] = spot_size_m(g.wavelength_m, g.distance_m, g.aperture_diameter_m * sar)
    return out


def _usual_step_m(g: CaptureGeometry) -> float:
    """Median distance from each aperture position to its nearest neighbour (m; sin θ for LED arrays)."""
    from scipy.spatial import cKDTree

    c = np.asarray(g.aperture_centres_yx_m, np.float64)
    return float(np.median(cKDTree(c).query(c, k=2)[0][:, 1]))


def _step_m(g: CaptureGeometry) -> float | None:
    """Distance between neighbouring aperture positions along a grid row (m)."""
    c = g.aperture_centres_yx_m
    if len(c) < 2:
        return None
    d = np.hypot(*(c[1:] - c[:-1]).T)
    d = d[d > 0]
    return float(d.min()) if d.size else None


def sharpness_summary(inputs: ReportInputs) -> dict:
    """No-reference sharpness of the observed centre image and the recovery (real captures).

    Both intensities are compared on the recovery's grid. ``spectral_reach_*_lp_per_mm`` is the
    frequency within which 99% of the intensity spectrum's power lies
    (:func:`cca_cli.metrics.sharpness.spectral_reach`) and ``sharpness_gain`` their ratio
    (recovered / observed); ``rms_frequency_*_lp_per_mm`` is the RMS frequency of the same spectrum
    (:func:`cca_cli.metrics.sharpness.rms_frequency`, dominated by the low and middle frequencies);
    ``energy_beyond_cutoff_*`` is the share of spectral power beyond what the single camera can
    record — its coherent intensity cutoff ``2R`` or the sensor's Nyquist frequency, whichever is
    lower (:func:`cca_cli.metrics.sharpness.spectral_energy_beyond`).
    """
    from cca_cli.metrics.sharpness import rms_frequency, spectral_energy_beyond, spectral_reach

    observed = on_grid(inputs.observed, inputs.recovered.shape[-2:])
    pixel_mm = grid_pixel_m(inputs.geometry.field_width_m, inputs.hires_size) * 1e3
    # A recovered region narrower than the recovery grid holds proportionally fewer spectrum pixels per cycle.
    share = inputs.recovered.shape[-1] / inputs.hires_size
    cutoff = min(2.0 * inputs.geometry.pupil_radius_px * share, inputs.observed.shape[-1] / 2.0)
    f_obs = rms_frequency(observed, pixel_mm)
    f_rec = rms_frequency(inputs.recovered, pixel_mm)
    reach_obs = spectral_reach(observed, pixel_mm)
    reach_rec = spectral_reach(inputs.recovered, pixel_mm)
    return {
        "spectral_reach_observed_lp_per_mm": round(reach_obs, 3),
        "spectral_reach_recovered_lp_per_mm": round(reach_rec, 3),
        "sharpness_gain": round(reach_rec / reach_obs, 3) if reach_obs > 0 else None,
        "rms_frequency_observed_lp_per_mm": round(f_obs, 3),
        "rms_frequency_recovered_lp_per_mm": round(f_rec, 3),
        "rms_frequency_gain": round(f_rec / f_obs, 3) if f_obs > 0 else None,
        "single_camera_cutoff_px": round(cutoff, 3),
        "energy_beyond_cutoff_observed": round(spectral_energy_beyond(observed, cutoff), 5),
        "energy_beyond_cutoff_recovered": round(spectral_energy_beyond(inputs.recovered, cutoff), 5),
    }
