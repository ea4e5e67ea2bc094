"""Typed, frozen configuration models: one section per concern, SI units in key names.

Unknown keys are rejected (``extra="forbid"``) and values are coerced to their
annotated types, so ``550e-9`` (a string to PyYAML) is read as a number.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, model_validator

__all__ = [
    "STAGES",
    "RunSection",
    "OpticsSection",
    "SceneSection",
    "ArraySection",
    "NoiseSection",
    "SimulateSection",
    "ReconstructSection",
    "ReportSection",
    "RunConfig",
]

#: Stage names in pipeline order.
STAGES = ("simulate", "reconstruct", "report")
StageName = Literal["simulate", "reconstruct", "report"]


class Section(BaseModel):
    """Base of every section: frozen, unknown keys rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class RunSection(Section):
    """Which stages run and where their files go."""

    out_dir: Path | None = Field(None, description="Output directory; default ./cca-runs/<config name>.")
    stages: list[StageName] = Field(list(STAGES), description="Stages to run, in pipeline order.")

    @model_validator(mode="after")
    def _stages_in_order(self):
        order = [STAGES.index(s) for s in self.stages]
        if order != sorted(order) or len(set(order)) != len(order):
            raise ValueError(f"stages must be distinct and in the order {', '.join(STAGES)}")
        return self


class OpticsSection(Section):
    """The camera: SI units."""

    wavelength_m: PositiveFloat = Field(550e-9, description="Illumination wavelength (m).")
    focal_length_m: PositiveFloat = Field(0.8, description="Lens focal length (m).")
    aperture_diameter_m: PositiveFloat = Field(0.018, description="Lens aperture diameter d (m).")
    pixel_pitch_m: PositiveFloat = Field(2e-6, description="Sensor pixel pitch (m).")
    distance_m: PositiveFloat = Field(50.0, description="Object distance z (m).")


class SceneSection(Section):
    """The object: a built-in chart or an image file, and its physical width."""

    kind: Literal["resolution_chart", "usaf", "image"] = Field(
        "resolution_chart", description="resolution_chart (bars 20…1 px), usaf (USAF-1951) or image.")
    size_px: PositiveInt = Field(512, description="Scene pixels across (chart or resampled image).")
    field_width_m: PositiveFloat = Field(0.064, description="Object-plane width of the scene (m).")
    widths_px: list[PositiveInt] | None = Field(None, description="Bar widths of the resolution chart (px).")
    image_path: Path | None = Field(None, description="Amplitude image (any OpenImageIO format) for kind=image.")
    phase_path: Path | None = Field(None, description="Optional phase image, scaled to [0, phase_max_rad].")
    phase_max_rad: float = Field(3.141592653589793, description="Phase of a white phase-image pixel (rad).")

    @model_validator(mode="after")
    def _image_needs_path(self):
        if self.kind == "image" and self.image_path is None:
            raise ValueError("scene.kind 'image' needs scene.image_path")
        return self


class ArraySection(Section):
    """The aperture grid: n x n positions (or a target SAR) at a given overlap."""

    grid: PositiveInt | None = Field(None, description="Positions per side n (odd keeps a centre image).")
    sar: float | None = Field(None, ge=1.0, description="Target synthetic aperture ratio (alternative to grid).")
    overlap: float = Field(0.61, ge=0.0, lt=1.0, description="Linear overlap of neighbouring apertures.")

    @model_validator(mode="after")
    def _grid_or_sar(self):
        if (self.grid is None) == (self.sar is None):
            raise ValueError("give exactly one of array.grid or array.sar")
        return self


class NoiseSection(Section):
    """Sensor noise."""

    model: Literal["none", "gaussian", "poisson"] = Field("gaussian", description="none, gaussian (SNR) or poisson (shot + read).")
    snr_db: float = Field(30.0, description="Gaussian SNR per image: 10 log10(var(I) / σ²) (dB).")
    photons_per_unit: PositiveFloat = Field(1000.0, description="Poisson: electrons per pixel at irradiance 1.")
    read_noise_e: float = Field(2.0, ge=0.0, description="Poisson: read noise (electrons RMS).")
    seed: int = Field(0, description="Seed of the noise generator.")


class SimulateSection(Section):
    """How the simulator stores captures."""

    store: Literal["sensor", "band"] = Field(
        "sensor", description="sensor: full sensor pixel grid as a camera records it; band: the smallest grid that holds the band.")


class ReconstructSection(Section):
    """Phase retrieval."""

    engine: str = Field("altmin", description="Engine name (see `cca reconstruct --help`).")
    tau: float = Field(1e-3, ge=0.0, description="Tikhonov weight τ.")
    iterations: PositiveInt = Field(1000, description="Maximum iterations.")
    tol: float = Field(1e-5, ge=0.0, description="Stop when the relative spectrum change is below this.")
    options: dict[str, Any] = Field(default_factory=dict, description="Engine-specific options.")

    @model_validator(mode="after")
    def _known_engine(self):
        from cca_cli.engines.registry import ENGINES, engine_names

        if self.engine not in ENGINES:
            raise ValueError(f"{self.engine!r} is not an engine; choose one of {', '.join(engine_names())}")
        accepted = set(ENGINES[self.engine].option_names()) - {"tau", "max_iterations", "tol"}
        unknown = sorted(set(self.options) - accepted)
        if unknown:
            raise ValueError(f"unknown option(s) {', '.join(unknown)} for engine {self.engine}; "
                             f"accepted: {', '.join(sorted(accepted)) or 'none'}")
        return self


class ReportSection(Section):
    """Metrics and figures."""

    mtf_threshold: float = Field(0.2, gt=0.0, lt=1.0, description="Contrast threshold of the resolution limit (MTF20: 0.2).")
    figures: bool = Field(True, description="Write PNG figures.")


class RunConfig(Section):
    """A whole run: one section per concern."""

    run: RunSection = RunSection()
    optics: OpticsSection = OpticsSection()
    scene: SceneSection = SceneSection()
    array: ArraySection = ArraySection(grid=21)
    noise: NoiseSection = NoiseSection()
    simulate: SimulateSection = SimulateSection()
    reconstruct: ReconstructSection = ReconstructSection()
    report: ReportSection = ReportSection()
