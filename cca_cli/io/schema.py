"""The HDF5 schema: every dataset the pipeline writes, with dtype, units and meaning.

This table is the single source of dataset names; ``cca info`` and the README
are generated from it.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SCHEMA_VERSION", "DatasetSpec", "DATASETS", "spec_for", "GEOMETRY_ATTRS"]

SCHEMA_VERSION = "cca/1"


@dataclass(frozen=True)
class DatasetSpec:
    """One dataset of the schema."""

    path: str
    dtype: str
    shape: str
    units: str
    meaning: str


DATASETS: tuple[DatasetSpec, ...] = (
    DatasetSpec("/measurements/intensity", "float32", "(K, N, N)", "irradiance (unit plane wave = 1)",
                "Captured images on the sensor pixel grid, centred on the optical axis, linear."),
    DatasetSpec("/measurements/weight", "float32", "(K, N, N)", "1",
                "Optional per-pixel confidence in [0, 1]; 0 = pixel ignored by the magnitude update."),
    DatasetSpec("/geometry/aperture_centres_yx_m", "float64", "(K, 2)", "m",
                "Aperture centre [y, x] in the aperture (Fourier) plane for each capture."),
    DatasetSpec("/geometry/spectrum_centres_yx_px", "float64", "(K, 2)", "spectrum px",
                "Pupil centre [y, x] relative to DC in spectrum pixels (derived from the optics)."),
    DatasetSpec("/geometry/grid_indices", "int32", "(K, 2)", "1", "Grid [row, column] of each capture."),
    DatasetSpec("/truth/object", "complex64", "(M, M)", "√irradiance",
                "Simulation ground truth: the object's complex field on the simulation grid."),
    DatasetSpec("/truth/bars", "int32", "(B, 8)", "px",
                "Resolution-chart layout: group, width_px, orientation (0 horizontal, 1 vertical), "
                "role (0 bar, 1 gap), y0, y1, x0, x1 on the truth grid."),
    DatasetSpec("/recon/spectrum", "complex64", "(M, M)", "√irradiance · px",
                "Recovered high-resolution spectrum, centred (DC at M//2), orthonormal FFT of the object."),
    DatasetSpec("/recon/object", "complex64", "(M, M)", "√irradiance", "Recovered complex object field."),
    DatasetSpec("/recon/intensity", "float32", "(M, M)", "irradiance", "Recovered intensity |object|²."),
    DatasetSpec("/observed/centre", "float32", "(N, N)", "irradiance",
                "The capture nearest the optical axis (what a single camera sees)."),
    DatasetSpec("/history/residual", "float64", "(iterations,)", "1",
                "Relative data misfit ‖w(|ψ| − √I)‖ / ‖w √I‖ per iteration."),
    DatasetSpec("/history/change", "float64", "(iterations,)", "1", "Relative spectrum change per iteration."),
    DatasetSpec("/history/seconds", "float64", "(iterations,)", "s", "Wall time at the end of each iteration."),
)

#: Attributes of /geometry (all SI).
GEOMETRY_ATTRS = {
    "wavelength_m": "m",
    "focal_length_m": "m",
    "aperture_diameter_m": "m",
    "pixel_pitch_m": "m",
    "distance_m": "m",
    "field_width_m": "m",
    "pupil_radius_px": "spectrum px",
    "overlap": "1",
    "synthetic_aperture_ratio": "1",
    "centre_index": "1",
}


def spec_for(path: str) -> DatasetSpec | None:
    """The schema entry of a dataset path, if any."""
    for spec in DATASETS:
        if spec.path == path:
            return spec
    return None
