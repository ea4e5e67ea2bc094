"""Stage `report`: recon.h5 → report/ (report.json and PNG figures)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from cca_cli.config.model import ReportSection
from cca_cli.errors import InputError
from cca_cli.io.h5 import Provenance
from cca_cli.io.outputs import atomic_path, check_output, write_marker
from cca_cli.io.recon import read_recon
from cca_cli.report.summary import ReportInputs, summarize
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent
from cca_cli.workflows.scenes import table_to_bars

__all__ = ["SECTIONS", "REPORT_JSON", "run"]

SECTIONS = ("report",)
REPORT_JSON = "report.json"


def run(recon_path: Path, section: ReportSection, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> dict:
    """Compute the report of ``recon_path`` and write it (atomically) as directory ``output``."""
    check_output(output, force=force, kind="folder", inputs=[recon_path])
    recon = read_recon(recon_path)
    result, attrs, region_px = recon.result, recon.attrs, recon.region_px
    geometry, spectrum, obj, observed = result.geometry, result.spectrum, result.object, result.observed
    recovered = result.intensity
    residual, change = result.history["residual"], result.history["change"]
    truth_obj = _finite(recon_path, "/truth/object", result.truth.get("object"), 2)
    bars = _bars(recon_path, result.truth["bars"]) if "bars" in result.truth else ()
    usaf_table = _table(recon_path, "/truth/usaf", result.truth["usaf"], 11) if "usaf" in result.truth else None
    units = result.units or "irradiance"
    multiplex, capture_summary = recon.multiplex, recon.capture_summary
    calibration, tiles = recon.calibration, recon.tiles
    # The spectrum and the truth are square grids; a recovered region (/recon/region_px) may be a rectangle.
    for name, image in (("/truth/object", truth_obj),):
        if image is not None and image.shape[0] != image.shape[1]:
            raise InputError(f"{recon_path}: {name} has shape {image.shape}, expected a square image")
    if truth_obj is not None:
        _check_truth(recon_path, truth_obj, bars)
    truth = None if truth_obj is None else (np.abs(truth_obj) ** 2).astype(np.float32)
    inputs = ReportInputs(geometry=geometry, observed=observed, recovered=recovered, truth=truth, bars=bars,
                          engine=str(attrs.get("engine")), iterations=int(attrs.get("iterations", 0)),
                          seconds=float(attrs.get("seconds", 0.0)), hires_size=int(attrs.get("hires_size")),
                          lowres_size=int(attrs.get("lowres_size")), truth_field=truth_obj)
    summary = summarize(inputs, threshold=section.mtf_threshold)
    summary.update(_stopping(attrs, change))
    summary["device"] = str(attrs.get("device", "cpu"))
    if "dropped_captures" in attrs:
        summary["dropped_captures"] = [int(i) for i in np.atleast_1d(attrs["dropped_captures"])]
    held_back = result.history["held_back"] if result.held_back else None
    if held_back is not None:
        best = int(np.nanargmin(held_back))
        summary.update(held_back_captures=len(result.held_back), residual_held_back=round(float(held_back[best]), 5),
                       held_back_best_iteration=best + 1)
    summary["intensity_units"] = units
    summary.update(capture_summary)
    if calibration is not None:
        summary.update(calibration_summary(calibration, geometry))
    if tiles is not None:
        tiles = dict(tiles, truth_waves=truth_at_tiles(result.truth, tiles))
        summary["tiles"] = tiles_summary(tiles)
    coverage = None
    if multiplex is not None:
        from cca_cli.workflows.multiplex import coverage_summary

        stats, coverage, band = coverage_summary(multiplex, int(attrs.get("hires_size")))
        summary.update(stats)
    if section.bar_elements:
        from cca_cli.report.bar_reading import finest_resolved

        summary["bar_contrast"], offset = _bar_reading(section, geometry, observed, obj,
                                                       int(attrs.get("hires_size")), region_px)
        summary["bar_offset_px"] = [round(v, 3) for v in offset]
        for image in ("observed", "recovered"):  # resolved: contrast ≥ the resolution threshold (MTF20: 0.2)
            summary[f"bar_finest_resolved_{image}"] = finest_resolved(summary["bar_contrast"], image,
                                                                      section.mtf_threshold)
    comparison = _comparison(summary, section, geometry, truth_obj, truth, observed, recovered, bars, usaf_table,
                             recovered_object=obj)
    region = _zoom_region(summary, bars, truth, usaf_table, recovered, geometry, int(attrs.get("hires_size")))
    if region is not None:
        summary["zoom_region"] = region.to_dict()
    progress(ProgressEvent("report", "metrics", 1, 2))
    with atomic_path(output, force=True, kind="folder", inputs=[recon_path]) as tmp:
        tmp.mkdir(parents=True)
        if section.figures:
            from cca_cli.report.figures import write_figures

            # A region cut from the recovery grid (/recon/region_px) is that share of the grid's field wide;
            # the spectrum (and the pupils' pixels) belong to the whole grid.
            figures = write_figures(tmp, observed=observed, recovered_object=obj, spectrum=spectrum,
                                    pupil_centres_px=geometry.spectrum_centres_yx_px,
                                    pupil_radius_px=geometry.pupil_radius_px,
                                    field_width_m=geometry.field_width_m * obj.shape[-1] / int(attrs.get("hires_size")),
                                    spectrum_field_width_m=geometry.field_width_m,
                                    residual=residual, change=change, held_back=held_back, summary=summary,
                                    truth=truth, units=units,
                                    region=region, grid_indices=geometry.grid_indices)
            if comparison:
                from cca_cli.report.figures import write_comparison_figures

                figures += write_comparison_figures(tmp, comparison, summary, field_width_m=geometry.field_width_m,
                                                    region=region, units=units)
            if calibration is not None:
                from cca_cli.report.figures import write_calibration_figures

                figures += write_calibration_figures(tmp, calibration)
            if tiles is not None:
                from cca_cli.report.figures import write_tile_figure

                frame_shape = tuple(region_px[1][2:]) if region_px is not None else observed.shape[-2:]
                figures.append(write_tile_figure(tmp / "tiles.png", tiles, frame_shape=frame_shape,
                                                 field_width_m=geometry.field_width_m * frame_shape[1]
                                                 / (region_px[2] if region_px is not None else frame_shape[1])))
            if coverage is not None:
                from cca_cli.report.figures import write_coverage_figure

                figures.append(write_coverage_figure(tmp / "coverage.png", coverage, band, summary))
            summary["figures"] = [p.name for p in figures]
        document = dict(summary)
        document["provenance"] = {k: (v if isinstance(v, str) else str(v)) for k, v in provenance.items()}
        (tmp / REPORT_JSON).write_text(json.dumps(_json_safe(document), indent=2, allow_nan=False))
        write_marker(tmp, "report")
    progress(ProgressEvent("report", "figures", 2, 2))
    return summary


def _json_safe(value):
    """``value`` with every NaN or infinity as None: JSON has no such numbers (an empty set's residual is NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def _bar_reading(section: ReportSection, geometry, observed, recovered_object, hires_size: int, region_px) -> dict:
    """``report.bar_elements`` read on the recovered and the observed amplitude (boxes in frame pixels)."""
    from cca_cli.report.bar_reading import FrameToRecovery, read_elements

    if region_px is None or not region_px[2]:
        sensor, offset, origin = observed.shape[-1], (0, 0), (0, 0)
    else:
        (oy, ox, _, _), (sy, sx, _, _), sensor = region_px
        origin, offset = (oy, ox), (sy, sx)
    to_recovery = FrameToRecovery(sensor, hires_size, offset_yx=offset, origin_yx=origin)
    frame_pixel_m = geometry.field_width_m / sensor
    elements = [spec.model_dump() for spec in section.bar_elements]
    from cca_cli.report.bar_reading import offset_to_observed
    from cca_cli.report.summary import on_grid

    recovered = np.abs(recovered_object) ** 2
    # The recovered region covers the frames' field: compare below 80% of the frames' Nyquist frequency.
    offset = offset_to_observed(recovered, on_grid(observed, recovered.shape[-2:]), 0.4 * min(observed.shape[-2:]))
    readings = read_elements(recovered_object, observed, elements, frame_pixel_m, to_recovery, offset_yx=offset)
    return readings, offset


def truth_at_tiles(truth: dict, tiles: dict) -> dict | None:
    """A simulation's aberration (``/truth/aberration_waves`` at its field points, blended bilinearly as the
    simulation blends it) at each tile's centre, by the tiles' mode names; None without one."""
    waves, nodes = truth.get("aberration_waves"), truth.get("aberration_nodes_px")
    if waves is None or nodes is None or "zernike_names" not in tiles:
        return None
    from cca_cli.optics.field_aberration import MODES, aberration_at
    from cca_cli.optics.zernike import zernike_name

    boxes = np.asarray(tiles["box_px"], np.float64)
    at_tiles = aberration_at(waves, np.asarray(nodes, np.float64), boxes[:, :2] + (boxes[:, 2:] - 1) / 2.0)
    names = [zernike_name(*mode) for mode in MODES]
    return {name: at_tiles[:, j] for j, name in enumerate(names) if name in tiles["zernike_names"]}


def tiles_summary(tiles: dict) -> dict:
    """report.json entry of a tiled reconstruction: the tile grid, the residuals and the aberration's range."""
    attrs = tiles["attrs"]
    residual = tiles["residual"][np.isfinite(tiles["residual"])]
    out = {"count": int(len(tiles["box_px"])), "grid": [int(attrs.get("rows", 0)), int(attrs.get("cols", 0))],
           "size_px": int(attrs.get("size_px", 0)), "overlap_px": int(attrs.get("overlap_px", 0)),
           "pupil": str(attrs.get("pupil", "")),
           "iterations_median": float(np.median(tiles["iterations"])),
           "seconds_per_tile_median": round(float(np.median(tiles["seconds"])), 3)}
    if residual.size:
        out["residual_all_median_max"] = [round(float(np.median(residual)), 5), round(float(residual.max()), 5)]
    if "zernike_waves" in tiles:
        waves = tiles["zernike_waves"]
        out["zernike_waves_min_median_max"] = {
            name: [round(float(v), 4) for v in (waves[:, j].min(), np.median(waves[:, j]), waves[:, j].max())]
            for j, name in enumerate(tiles["zernike_names"][:6])}
        truth = tiles.get("truth_waves") or {}
        if truth:   # a simulation: how far each tile's recovered mode lies from the lens's
            out["zernike_waves_vs_truth"] = {
                name: {"rms_error": round(float(np.sqrt(np.mean((waves[:, tiles["zernike_names"].index(name)]
                                                                - values) ** 2))), 4),
                       "truth_min_max": [round(float(values.min()), 4), round(float(values.max()), 4)]}
                for name, values in truth.items()}
    return out


def calibration_summary(calibration: dict, geometry) -> dict:
    """report.json entries of the final model's fit and calibration."""
    out = {f"residual_{k}": round(v, 5) for k, v in calibration["totals"].items()}
    if calibration["totals_without_brightness"] != calibration["totals"]:
        out.update({f"residual_{k}_without_brightness": round(v, 5)
                    for k, v in calibration["totals_without_brightness"].items()})
    out["bright_field_images"] = int(np.sum(calibration["bright_field"]))
    moves = np.hypot(*(calibration["refined_px"] - calibration["nominal_px"]).T)
    out["position_change_px_rms"] = round(float(np.sqrt(np.mean(moves ** 2))), 4)
    out["position_change_px_max"] = round(float(moves.max()), 4) if moves.size else 0.0
    if "position_model" in calibration:
        out["position_model"] = calibration["position_model"]
        out["position_parameters"] = {k: round(v, 6) for k, v in calibration["position_parameters"].items()}
    if calibration.get("brightness") is not None and np.any(calibration["brightness"] != 1):   # fitted
        b = calibration["brightness"]
        out["brightness_min_median_max"] = [float(f"{v:.4g}") for v in (b.min(), np.median(b), b.max())]
    if "zernike" in calibration:
        out["pupil_model"] = calibration["pupil_model"]
        out["zernike_waves"] = {k: round(v, 4) for k, v in calibration["zernike"].items()}
        if len(calibration["zernike_per_pupil"]) > 1:
            out["zernike_waves_per_camera"] = np.round(calibration["zernike_per_pupil"], 4).tolist()
            ids = calibration.get("camera_ids")
            if ids is not None and len(ids) == len(calibration["zernike_per_pupil"]):
                out["camera_ids"] = list(ids)   # the lab's number of each row of zernike_waves_per_camera
                out["zernike_waves_camera"] = ids[0]   # zernike_waves is this camera's
        if geometry.kind == "led_array" and "defocus" in calibration["zernike"]:
            from cca_cli.engines.calibration import defocus_zernike

            per_metre = defocus_zernike(1e-6, wavelength_m=geometry.wavelength_m,
                                        numerical_aperture=geometry.numerical_aperture)[0] / 1e-6
            out["defocus_m_equivalent"] = float(f"{calibration['zernike']['defocus'] / per_metre:.4g}")
    return out


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _stopping(attrs: dict, change: np.ndarray) -> dict:
    """Why the reconstruction stopped (``stopped_by``: ``tol`` or ``cap``), its ``tol`` and last relative change."""
    out = {}
    if "stopped_by" in attrs:
        out["stopped_by"] = _text(attrs["stopped_by"])
    try:
        out["tol"] = json.loads(_text(attrs.get("engine_options", "{}"))).get("tol")
    except ValueError:
        pass
    if len(change):
        out["final_change"] = float(change[-1])
    return out


def _zoom_region(summary: dict, bars, truth, usaf_table, recovered, geometry, hires_size: int):
    """Where the figures zoom: the finest resolved chart features, else the recovery's most detailed part."""
    from cca_cli.report import regions

    if usaf_table is not None and len(usaf_table):
        from cca_cli.workflows.scenes import table_to_usaf

        return regions.usaf_region(table_to_usaf(usaf_table), (summary.get("usaf") or {}).get("recovered"))
    if bars and truth is not None:
        return regions.bar_region(bars, summary.get("mtf20_recovered_px"), truth.shape[-1])
    width = recovered.shape[-1]
    # The pupil radius is in spectrum px of the whole recovery grid; a region cut from it holds
    # proportionally fewer cycles per its own width.
    cutoff = min(2.0 * geometry.pupil_radius_px * width / hires_size, width / 2.0)
    return regions.detail_region(recovered, cutoff)


def _bars(path: Path, table) -> tuple:
    """The bar chart's layout from /truth/bars (one line naming the dataset when it is not a layout)."""
    table = _table(path, "/truth/bars", table, 8)
    try:
        return table_to_bars(table)
    except (IndexError, KeyError, ValueError):
        raise InputError(f"{path}: /truth/bars is not a chart layout (each group needs its bars, gaps "
                         "and box, orientation 0 or 1); re-run simulate and reconstruct") from None


def _check_truth(path: Path, truth_obj: np.ndarray, bars) -> None:
    """The truth must hold light, and the chart layout drawn on it must lie on its grid."""
    if not np.any(truth_obj):
        raise InputError(f"{path}: /truth/object is zero everywhere, so there is nothing to compare the recovery "
                         "with; re-run simulate and reconstruct")
    size = truth_obj.shape[-1]
    boxes = np.array([box for group in bars for box in (group.box, *group.bar_boxes, *group.gap_boxes)])
    if boxes.size and (boxes.min() < 0 or boxes[:, [1, 3]].max() > size):
        raise InputError(f"{path}: /truth/object is {size}x{size} px but /truth/bars places bars up to pixel "
                         f"{int(boxes[:, [1, 3]].max())}: the truth and its chart layout do not belong together; "
                         "re-run simulate and reconstruct")


def _finite(path: Path, name: str, values, ndim: int) -> np.ndarray | None:
    """A truth array, checked: ``ndim`` dimensions of finite numbers (None when the file has none)."""
    if values is None:
        return None
    values = np.asarray(values)
    if values.ndim != ndim or not np.all(np.isfinite(values)):
        raise InputError(f"{path}: {name} is not a finite {ndim}-D array; re-run simulate and reconstruct")
    return values


def _table(path: Path, name: str, table, columns: int) -> np.ndarray:
    """A layout table of the truth: (rows, ``columns``) finite numbers."""
    table = _finite(path, name, table, 2)
    if table.shape[1] != columns:
        raise InputError(f"{path}: {name} has shape {table.shape}, expected (rows, {columns})")
    return table


def _comparison(summary: dict, section: ReportSection, geometry, truth_obj, truth, observed, recovered, bars,
                usaf_table, *, recovered_object=None) -> dict[str, np.ndarray]:
    """Add baselines, USAF reading and speckle contrast to ``summary``; return the images compared (truth grid)."""
    if truth_obj is None or not (section.baselines or usaf_table is not None or section.speckle_region):
        return {}
    from cca_cli.errors import ConfigError
    from cca_cli.report import comparison as cmp
    from cca_cli.report.summary import on_grid
    from cca_cli.workflows.scenes import table_to_usaf

    size = truth.shape[-1]
    images = {"observed": on_grid(observed, size), "recovered": on_grid(recovered, size)}
    baselines = cmp.baseline_images(truth_obj, geometry, section.baselines)
    images.update(baselines)
    if baselines:
        summary["baselines"] = cmp.compare_images(baselines, truth, bars, threshold=section.mtf_threshold)
        for name, info in cmp.baseline_details(section.baselines, geometry).items():
            summary["baselines"][name].update(info)
    if usaf_table is not None and len(usaf_table):
        chart = table_to_usaf(usaf_table)
        chart_images = {name: on_grid(image, chart.size) for name, image in images.items()}
        if recovered_object is not None:  # |object|² on the hires grid is aliased; square on the chart grid
            chart_images["recovered"] = cmp.field_intensity_on_grid(recovered_object, chart.size)
        summary["usaf"] = cmp.usaf_summary(chart_images, chart, threshold=section.mtf_threshold)
    if section.speckle_region:
        try:
            speckle = cmp.speckle_summary(images, section.speckle_region)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        summary["speckle_contrast_observed"] = speckle.pop("observed")
        summary["speckle_contrast_recovered"] = speckle.pop("recovered")
        if speckle:
            summary["speckle_contrast_baselines"] = speckle
    images["truth"] = truth
    return images
