"""Stage `hdr`: raw.h5 exposure brackets → hdr.h5 linear radiance, validity weights and checks.

The noise model (read noise, conversion gain) comes from the config, the
sensor calibration ingest stored (dark frames, flat pairs, the manifest),
or else from the exposure brackets of the whole set; each position's
bracket is then merged by :func:`cca_cli.hdr.merge_exposures` with
per-pixel clipping levels (white level minus each pixel's black level,
over its gain).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.config.model import HdrSection
from cca_cli.errors import ConfigError, InputError
from cca_cli.hdr.merge import NoiseModel, estimate_noise, merge_exposures
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, open_input, require, write_dataset
from cca_cli.io.records import carry_capture_records
from cca_cli.io.captures import BOUNDARY_OPEN, read_frame_scale, read_labels, read_sensor, write_labels
from cca_cli.library.orientation import recorded_orientation_advice
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent

__all__ = ["SECTIONS", "HdrOutcome", "run"]

SECTIONS = ("hdr",)

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class HdrOutcome:
    """Summary of a merge."""

    n_positions: int
    n_exposures: int
    dynamic_range_gain: np.ndarray   # (K,)
    valid_fraction: np.ndarray       # (K,)
    exposure_ratio: float
    flux_ratio: np.ndarray | None = None   # (K, E)
    noise: NoiseModel | None = None
    flagged: tuple[str, ...] = ()    # views whose flux ratios do not follow the exposure ratios


def _saturation_levels(src, frames_ds, exposure: np.ndarray, section: HdrSection):
    """Per-position clipping levels: a scalar, or (K, E, H, W)-broadcastable arrays from the sensor calibration."""
    if section.saturation_level is not None:
        return lambda k: section.saturation_level
    sensor = read_sensor(src)
    if sensor is None or sensor.white_level is None or (sensor.darks is None and sensor.gain is None):
        level = float(frames_ds.attrs["saturation_level"])
        return lambda k: level
    cache = {float(t): sensor.saturation_at(float(t)) for t in np.unique(exposure)}
    return lambda k: np.stack([np.broadcast_to(cache[float(t)], frames_ds.shape[-2:]) for t in exposure[k]])


def _noise_model(src, frames: np.ndarray, exposure: np.ndarray, saturation, section: HdrSection) -> NoiseModel:
    sensor = read_sensor(src)
    read_noise = section.read_noise or (sensor.read_noise if sensor else None)
    gain = section.electrons_per_count or (sensor.electrons_per_count if sensor else None)
    if read_noise is not None and gain is not None:
        source = "config" if section.read_noise or section.electrons_per_count else sensor.noise_source
        return NoiseModel(read_noise, gain, source)
    measured = estimate_noise(frames, exposure, saturation_level=saturation,
                              saturation_margin=section.saturation_margin)
    return NoiseModel(read_noise if read_noise is not None else measured.read_noise,
                      gain if gain is not None else measured.electrons_per_count,
                      measured.source if read_noise is None else f"{sensor.noise_source if sensor else 'config'} "
                                                                   f"and {measured.source}")


def run(raw_path: Path, section: HdrSection | None, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> HdrOutcome:
    """Merge every position's exposures of ``raw_path`` and write ``output``."""
    section = section or HdrSection()
    check_output(output, force=force)
    if section.noise_floor is not None:
        _log.warning("hdr.noise_floor is ignored: every unsaturated frame counts, weighted by its noise; "
                     "remove the key")
    with open_input(raw_path, stage="ingest") as src:
        frames_ds = require(src, "/raw/frames", ndim=4)
        frames = np.asarray(frames_ds, np.float32)
        exposure = np.asarray(require(src, "/raw/exposure_s", ndim=2), np.float64)
        values = str(frames_ds.attrs.get("values", "intensity"))
        frame_scale = read_frame_scale(frames_ds.attrs, raw_path, "/raw/frames")
        geometry = read_geometry(src)
        labels = read_labels(src, frames.shape[0])
        k, e = frames.shape[:2]
        levels = _saturation_levels(src, frames_ds, exposure, section)
        # The noise model is measured on at most 12 positions spread over the set (memory stays bounded).
        sample = np.unique(np.linspace(0, k - 1, min(k, 12)).round().astype(int))
        sample_levels = np.stack([np.broadcast_to(np.asarray(levels(i), np.float32), frames.shape[1:])
                                  for i in sample]) if not np.isscalar(levels(0)) else levels(0)
        try:
            noise = _noise_model(src, frames[sample], exposure[sample], sample_levels, section)
        except ValueError as exc:
            raise InputError(f"{raw_path}: {exc}") from None
        radiance = np.empty((k,) + frames.shape[2:], np.float32)
        weight = np.empty_like(radiance)
        gain, dynamic_range, valid = np.empty(k), np.empty(k), np.empty(k)
        flux, flux_sigma = np.empty((k, e)), np.empty((k, e))
        saturated = np.zeros(k)
        ratio = 1.0
        for i in range(k):
            try:
                res = merge_exposures(frames[i], exposure[i], saturation_level=levels(i), noise=noise,
                                      min_weight=section.min_weight, saturation_margin=section.saturation_margin,
                                      warn_saturated=False)
            except ValueError as exc:
                if "saturation" in str(exc):
                    raise ConfigError(f"hdr: {exc}") from None
                raise InputError(f"{raw_path}: {labels[i]}: {exc}") from None
            radiance[i], weight[i] = res.radiance, res.weight
            gain[i], dynamic_range[i], valid[i] = res.dynamic_range_gain, res.dynamic_range, float(res.valid.mean())
            flux[i], flux_sigma[i] = res.flux_ratio, res.flux_ratio_sigma
            ratio = max(ratio, res.exposure_ratio)
            saturated[i] = res.saturated_fraction
            progress(ProgressEvent("hdr", "positions", i + 1, k))
        warning = saturated_note(saturated, labels)
        if warning:
            _log.warning("%s: %s", raw_path, warning)
        flagged = _flag_flux(flux, flux_sigma, labels, section.flux_tolerance)
        if values == "amplitude":
            radiance = np.square(np.maximum(radiance, 0))
        if "registration/board" not in src:   # no registration to come: the merged captures are what is recovered
            warning = recorded_orientation_advice(radiance, weight, geometry, frame_scale)
            if warning is not None:
                _log.warning("%s: %s", raw_path, warning)
        with atomic_h5(output, provenance, force=force) as handle:
            ds = write_dataset(handle, "/measurements/intensity", radiance, units="counts/s")
            ds.attrs["boundary"] = BOUNDARY_OPEN
            ds.attrs["frame_scale"] = frame_scale
            write_dataset(handle, "/measurements/weight", weight)
            write_dataset(handle, "/hdr/dynamic_range_gain", gain)
            write_dataset(handle, "/hdr/dynamic_range", dynamic_range)
            write_dataset(handle, "/hdr/valid_fraction", valid)
            write_dataset(handle, "/hdr/flux_ratio", flux)
            write_dataset(handle, "/hdr/flux_ratio_sigma", flux_sigma)
            group = handle["hdr"]
            group.attrs["exposures"] = e
            group.attrs["exposure_ratio"] = ratio
            group.attrs["read_noise"] = noise.read_noise
            group.attrs["electrons_per_count"] = noise.electrons_per_count
            group.attrs["noise_source"] = noise.source
            if np.isscalar(levels(0)):
                group.attrs["saturation_level"] = float(levels(0))
            write_labels(handle, labels)
            write_geometry(handle, geometry)
            carry_capture_records(src, handle)
    return HdrOutcome(n_positions=k, n_exposures=e, dynamic_range_gain=gain, valid_fraction=valid,
                      exposure_ratio=ratio, flux_ratio=flux, noise=noise, flagged=tuple(flagged))


#: Share of a position's pixels saturated in every exposure above which it is named.
SATURATED_SHARE = 0.01


def saturated_note(saturated: np.ndarray, labels: list[str]) -> str:
    """One warning naming the positions whose pixels are saturated in every exposure beyond :data:`SATURATED_SHARE`
    (the worst three first), or an empty string."""
    over = np.flatnonzero(np.asarray(saturated) > SATURATED_SHARE)
    if not over.size:
        return ""
    worst = over[np.argsort(-np.asarray(saturated)[over], kind="stable")][:3]
    named = ", ".join(f"{labels[i]} {100 * saturated[i]:.1f}%" for i in worst)
    more = f" and {over.size - worst.size} more" if over.size > worst.size else ""
    return (f"{over.size} of {len(saturated)} positions have pixels saturated in every exposure ({named}{more}): "
            "their radiance there is only a lower bound; add a shorter exposure at those positions")


def _flag_flux(flux: np.ndarray, sigma: np.ndarray, labels: list[str], tolerance: float) -> list[str]:
    """Views whose flux ratios stray from 1 by more than the tolerance and 4 standard deviations (warned once)."""
    off = np.abs(flux - 1)
    bad = np.isfinite(off) & (off > tolerance) & (off > 4 * np.nan_to_num(sigma, nan=np.inf))
    flagged = [labels[i] for i in np.nonzero(bad.any(axis=1))[0]]
    if flagged:
        worst = int(np.nanargmax(np.where(bad, off, -1).max(axis=1)))
        _log.warning("%d view(s) have flux ratios between exposures off by more than %.0f%% (worst: %s, ratios %s); "
                     "check the exposure times, the black level, the white level (sensor.bit_depth or white_level: "
                     "clipped pixels) and the sensor's linearity", len(flagged), 100 * tolerance, labels[worst],
                     ", ".join(f"{v:.3f}" for v in flux[worst]))
    return flagged
