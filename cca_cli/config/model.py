"""Typed, frozen configuration models: one section per concern, SI units in key names.

Unknown keys are rejected (``extra="forbid"``) and values are coerced to their
annotated types, so ``550e-9`` (a string to PyYAML) is read as a number; booleans,
integers and finite numbers are read strictly (:mod:`cca_cli.values`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import Field, NonNegativeInt, PositiveFloat, PositiveInt, field_validator, model_validator

from cca_cli.config.section import Section
from cca_cli.engines import presets, registry
from cca_cli.sampling.tiles import MIN_TILE_PX
from cca_cli.optics.noise import MIN_SNR_DB
from cca_cli.sampling.geometry import unit_slip

__all__ = [
    "STAGES",
    "RunSection",
    "OpticsSection",
    "SceneSection",
    "ArraySection",
    "NoiseSection",
    "SimulateSection",
    "AberrationSection",
    "PaddingSection",
    "TilesSection",
    "ReconstructSection",
    "ReportSection",
    "BaselineSpec",
    "SweepSection",
    "MultiplexSection",
    "IngestSection",
    "HdrSection",
    "RegisterSection",
    "DEFAULT_STAGES",
    "RunConfig",
]

#: Stage names in pipeline order (simulate and ingest are alternative sources of captures).
STAGES = ("simulate", "ingest", "hdr", "register", "reconstruct", "report")
StageName = Literal["simulate", "ingest", "hdr", "register", "reconstruct", "report"]
#: The stages a config runs when run.stages is not given.
DEFAULT_STAGES = ("simulate", "reconstruct", "report")


class RunSection(Section):
    """Which stages run and where their files go."""

    out_dir: Path | None = Field(None, description="Output directory; default ./cca-runs/<config name>.")
    stages: list[StageName] = Field(list(DEFAULT_STAGES), description="Stages to run, in pipeline order.")

    @field_validator("stages")
    @classmethod
    def _stages_in_order(cls, stages):
        if not stages:
            raise ValueError("the list is empty, so nothing would run; list stages, e.g. [simulate, reconstruct, report]")
        order = [STAGES.index(s) for s in stages]
        if order != sorted(order) or len(set(order)) != len(order):
            raise ValueError(f"stages must be distinct and in the order {', '.join(STAGES)}")
        if "simulate" in stages and "ingest" in stages:
            raise ValueError("simulate and ingest are alternative sources of captures; list only one")
        return stages


class OpticsSection(Section):
    """The camera: SI units."""

    wavelength_m: PositiveFloat = Field(550e-9, description="Illumination wavelength (m).")
    focal_length_m: PositiveFloat = Field(0.8, description="Lens focal length (m).")
    aperture_diameter_m: PositiveFloat = Field(0.018, description="Lens aperture diameter d (m).")
    pixel_pitch_m: PositiveFloat = Field(2e-6, description="Sensor pixel pitch (m).")
    distance_m: PositiveFloat = Field(50.0, description="Object distance z (m).")

    @field_validator("wavelength_m", "focal_length_m", "aperture_diameter_m", "pixel_pitch_m")
    @classmethod
    def _in_metres(cls, value: float, info) -> float:
        slip = unit_slip(info.field_name, value)
        if slip is not None:
            raise ValueError(slip)
        return value


class SceneSection(Section):
    """The object: a built-in chart or an image file, and its physical width."""

    kind: Literal["resolution_chart", "usaf", "image", "natural", "fingerprint", "face", "label"] = Field(
        "resolution_chart",
        description="resolution_chart (bars 20…1 px), usaf (USAF-1951), image, natural (synthetic portrait-like "
                    "photo), fingerprint, face or label (synthetic scenes of the paper's figures).")
    size_px: PositiveInt = Field(512, description="Scene pixels across (chart or resampled image).")
    field_width_m: PositiveFloat = Field(0.064, description="Object-plane width of the scene (m).")
    widths_px: list[PositiveInt] | None = Field(None, description="Bar widths of the resolution chart (px).")
    image_path: Path | None = Field(None, description="Amplitude image (any OpenImageIO format) for kind=image.")
    phase_path: Path | None = Field(None, description="Optional phase image, scaled to [0, phase_max_rad].")
    phase_max_rad: float = Field(3.141592653589793, description="Phase of a white phase-image pixel (rad).")
    usaf_groups: list[int] | None = Field(None, description="USAF-1951 groups to draw for kind=usaf (default -2…3).")
    ridge_period_m: PositiveFloat = Field(0.5e-3, description="Ridge period of kind=fingerprint (m).")
    chart_inset_px: PositiveInt | None = Field(
        None, description="fingerprint/face/label: a bar chart this many scene px square in the lower-right corner "
                          "(widths_px, or the largest set that fits), so MTF20 can be measured.")
    surface_phase: Literal["none", "random"] = Field(
        "none", description="random: a rough, diffuse surface (random phase) that makes speckle.")
    surface_roughness_rad: float = Field(3.0, ge=0.0, description="RMS of the random surface phase (rad).")
    surface_correlation_px: float = Field(0.0, ge=0.0, description="Gaussian correlation length of the surface phase (simulation px; 0 = per pixel).")
    surface_seed: int = Field(0, ge=0, description="Seed of the random surface phase (≥ 0).")

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
    snr_db: float = Field(30.0, description="Gaussian SNR per image: 10 log10(var(I) / σ²) (dB), at least -10.")
    photons_per_unit: PositiveFloat = Field(
        1000.0, le=1e12, description="Poisson: electrons per pixel at irradiance 1 (at most 1e12, beyond any sensor).")
    read_noise_e: float = Field(2.0, ge=0.0, description="Poisson: read noise (electrons RMS).")
    seed: int = Field(0, ge=0, description="Seed of the noise generator (≥ 0).")

    @field_validator("snr_db")
    @classmethod
    def _signal_not_swamped(cls, snr_db):
        if snr_db < MIN_SNR_DB:
            raise ValueError(f"{snr_db:g} dB: the noise would swamp the signal (σ {10 ** (-snr_db / 20):.3g} times "
                             "each image's standard deviation, so dim images average below zero); use a value of at "
                             f"least {MIN_SNR_DB:g} dB")
        return snr_db


class SimulateSection(Section):
    """How the simulator stores captures."""

    store: Literal["sensor", "band"] = Field(
        "sensor", description="sensor: full sensor pixel grid as a camera records it; band: the smallest grid that holds the band.")


class AberrationSection(Section):
    """The simulated lens's aberration and how it changes across the field (waves RMS, Zernike normalisation).

    h is the field position over half the frame width (1 at the middle of an edge); see
    :mod:`cca_cli.optics.field_aberration`.
    """

    defocus_waves: float = Field(0.0, description="Defocus everywhere in the field (waves RMS).")
    field_curvature_waves: float = Field(0.0, description="Defocus added in proportion to h² (waves RMS at h = 1).")
    astigmatism_waves: float = Field(0.0, description="Astigmatism along the field direction, ∝ h² (waves RMS at "
                                                      "h = 1).")
    coma_waves: float = Field(0.0, description="Coma along the field direction, ∝ h (waves RMS at h = 1).")
    nodes: int = Field(5, ge=2, le=33, description="The pupil is evaluated on nodes x nodes field points, corner "
                                                  "to corner, and blended bilinearly in between.")


class PaddingSection(Section):
    """How recorded frames (windows on a larger scene) are placed on the recovery's square, periodic grid."""

    mode: Literal["auto", "off"] | bool = Field(
        "auto", description="auto: pad recorded or non-square images with a weight-0 guard band and crop the "
                            "recovery back; off: use square images as they are (periodic). YAML's bare off/on "
                            "(false/true) are read as off/auto.")

    @field_validator("mode")
    @classmethod
    def _bare_yaml_word(cls, mode):
        return mode if isinstance(mode, str) else ("auto" if mode else "off")
    guard_px: int | None = Field(None, ge=0, description="Guard band (sensor px); default 4 coherent resolution cells.")
    apodize_px: int | None = Field(None, ge=0, description="Weight taper inside the region edge (sensor px); "
                                                           "default 0 (none).")


class TilesSection(Section):
    """Overlapping tiles of the frame, each recovered with its own pupil (and LED angles), then blended."""

    size_px: PositiveInt = Field(..., ge=MIN_TILE_PX, description="Tile side in frame (sensor) pixels.")
    overlap_px: NonNegativeInt = Field(
        ..., description="Least overlap between neighbouring tiles (px), below half the tile; the blend runs "
                         "across the middle half of each overlap.")
    pupil: Literal["per_tile", "global"] = Field(
        "per_tile", description="per_tile: every tile recovers its own pupil, starting from a finished neighbour's; "
                                "global: the centre tile's recovered pupil is held fixed on every other tile.")

    @model_validator(mode="after")
    def _overlap_below_half(self):
        if 2 * self.overlap_px >= self.size_px:
            raise ValueError(f"overlap_px {self.overlap_px} must be below half of size_px {self.size_px}")
        return self


class ReconstructSection(Section):
    """Phase retrieval."""

    engine: str = Field("auto", description=f"Engine name, or auto: the {presets.summary()}.")
    tau: float | None = Field(None, ge=0.0, description="Tikhonov weight τ (default: the engine's, 1e-3).")
    iterations: PositiveInt | None = Field(None, description="Maximum iterations (default: the engine's or the "
                                                             "preset's).")
    tol: float | None = Field(None, ge=0.0, description="Stop when the relative spectrum change is below this "
                                                        "(default: the engine's, 1e-5).")
    options: dict[str, Any] = Field(default_factory=dict, description="Engine-specific options.")
    padding: PaddingSection = Field(PaddingSection(), description="Guard band for recorded / non-square frames.")
    checkpoint_every: NonNegativeInt = Field(
        50, description="Write <output>.checkpoint every this many iterations (at most 5% of the run time goes into "
                        "it), so an interrupted run resumes from it; 0: never.")
    init: Path | None = Field(None, description="Start from the /recon/spectrum of this recon.h5 (same grid) "
                                                "instead of the upsampled centre capture.")
    tiles: TilesSection | None = Field(
        None, description="Recover the frame in overlapping tiles on Dask (a local cluster, or --scheduler), each "
                          "with its own pupil; none: the whole frame at once.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "cpu", description="Where the engine runs: cpu; cuda (the batched engines on a CUDA GPU through CuPy: pip "
                           "install 'cca[gpu]'); auto: cuda when CuPy finds a GPU and the engine's options run there, "
                           "else cpu. Not part of the recipe: a run's outputs stay current whichever device made them.")

    #: Keys that say where a run computes, not what: left out of the config hash that decides whether an
    #: output is up to date, and of the checkpoint's fingerprint (a run stopped on one device resumes on another).
    NOT_RECIPE: ClassVar[frozenset[str]] = frozenset({"device"})

    # Field validators (not a model validator) so that errors point at reconstruct.engine / .options.
    @field_validator("engine")
    @classmethod
    def _known_engine(cls, engine):
        if engine != "auto" and engine not in registry.ENGINES:
            raise ValueError(f"{engine!r} is not an engine; choose auto or one of {', '.join(registry.engine_names())}")
        return engine

    @field_validator("options")
    @classmethod
    def _engine_options(cls, options, info):
        """Read ``options`` as the engine reads them (:func:`cca_cli.engines.registry.resolve`)."""
        for key in _SECTION_KEYS:
            if key in options:
                raise ValueError(f"{key} is not an option: set it as reconstruct.{_SECTION_KEYS[key]}")
        engine = info.data.get("engine")
        if engine is None:  # the engine was refused already
            return options
        section = {key: info.data.get(key) for key in ("tau", "iterations", "tol") if info.data.get(key) is not None}
        _, read = registry.resolve(engine, None, {**section, **options})
        return {key: getattr(read, key) for key in options}

    def given(self) -> dict:
        """What the user set: ``tau``, ``iterations``, ``tol`` (when set) and the engine's options."""
        section = {key: getattr(self, key) for key in ("tau", "iterations", "tol") if getattr(self, key) is not None}
        return {**section, **self.options}


#: Options set by reconstruct's own keys, not in ``options``.
_SECTION_KEYS = {"tau": "tau", "max_iterations": "iterations", "iterations": "iterations", "tol": "tol"}


class BaselineSpec(Section):
    """A single-lens baseline image computed from the ground truth."""

    kind: Literal["passive_incoherent", "lens"] = Field(
        ..., description="passive_incoherent: the array's own lens under incoherent light; lens: a lens of aperture_diameter_m.")
    aperture_diameter_m: PositiveFloat | None = Field(None, description="Aperture of the lens (kind=lens) (m).")
    illumination: Literal["coherent", "incoherent"] = Field("incoherent", description="Light of a kind=lens baseline.")
    name: str | None = Field(None, description="Label in the report (default from kind, aperture and light).")

    @model_validator(mode="after")
    def _lens_needs_aperture(self):
        if self.kind == "lens" and self.aperture_diameter_m is None:
            raise ValueError("a baseline of kind 'lens' needs aperture_diameter_m")
        return self

    def label(self) -> str:
        """The report's key for this baseline."""
        if self.name:
            return self.name
        if self.kind == "passive_incoherent":
            return "passive_incoherent"
        return f"lens_{self.aperture_diameter_m * 1e3:g}mm_{self.illumination}"


class BarElementSpec(Section):
    """One element of a recorded USAF-1951 target, boxed in the captured frames."""

    element: str = Field(..., pattern=r"^[Gg]-?\d+[Ee][1-6]$", description="Element name, e.g. G9E1 (group 9, element 1).")
    profile: Literal["row", "col"] = Field(
        ..., description="Direction of the profile across the bars: row (bars run along columns) or col.")
    box_px: list[float] = Field(
        ..., min_length=4, max_length=4,
        description="[y0, y1, x0, x1] around the element's three bars, in pixels of the captured frames.")

    @field_validator("box_px")
    @classmethod
    def _ordered(cls, box):
        if not (box[0] < box[1] and box[2] < box[3]):
            raise ValueError(f"box_px must be [y0, y1, x0, x1] with y0 < y1 and x0 < x1, got {box}")
        return box


class ReportSection(Section):
    """Metrics and figures."""

    mtf_threshold: float = Field(0.2, gt=0.0, lt=1.0, description="Contrast threshold of the resolution limit (MTF20: 0.2).")
    figures: bool = Field(True, description="Write PNG figures.")
    baselines: list[BaselineSpec] = Field(
        default_factory=list, description="Single-lens images to compare with: passive_incoherent (the same lens) or lens.")
    speckle_region: list[float] | None = Field(
        None, min_length=4, max_length=4,
        description="Uniform object region [y0, y1, x0, x1] as fractions of the field (0…1) for speckle contrast.")
    bar_elements: list[BarElementSpec] = Field(
        default_factory=list,
        description="Elements of a recorded USAF-1951 target to read (three-bar contrast on the recovered and the "
                    "observed amplitude).")


class SweepSection(Section):
    """A parameter study: many runs of the config above with some keys changed (`cca sweep`)."""

    study: Literal["grid", "overlap", "sar", "noise"] = Field(
        "grid", description="Study kind: grid (any keys), or the paper's overlap, sar and noise studies.")
    points: list[dict[str, Any]] = Field(
        default_factory=list, description="Explicit points: override dicts of dotted keys (keys that change together).")
    parameters: dict[str, list[Any]] = Field(
        default_factory=dict, description="Dotted key → values; the cartesian product is crossed with `points`.")
    x: str | None = Field(None, description="Table column on the x axis of the line plots (default: the study's).")
    group: str | None = Field(None, description="Table column that separates the lines of a plot.")
    highlight: list[float] | None = Field(
        None, description="Values of x whose contrast curves and recovered crops are drawn (default: all, up to 8).")
    figures: bool = Field(True, description="Write the sweep's PNG figures.")


class MultiplexSection(Section):
    """A single-shot camera array lit by several mutually incoherent sources (paper Section VII).

    The cameras use the optics section's lens; ``array`` is ignored when this
    section is present. Sources are given either by the overlap their spectrum
    regions make (``source_overlap``) or by their pitch and distance.
    """

    camera_grid: tuple[PositiveInt, PositiveInt] = Field((7, 7), description="Cameras (rows, columns).")
    camera_pitch_m: PositiveFloat | Literal["abutting"] = Field(
        "abutting", description="Distance between camera centres (m), or 'abutting' (= aperture diameter).")
    source_grid: tuple[PositiveInt, PositiveInt] = Field((7, 7), description="Sources (rows, columns).")
    source_overlap: float | None = Field(
        None, lt=1.0, description="Linear overlap of the spectrum regions of neighbouring sources, in (0, 1).")
    source_pitch_m: PositiveFloat | None = Field(None, description="Distance between neighbouring sources (m).")
    source_distance_m: PositiveFloat | None = Field(None, description="Distance from the sources to the object (m).")
    n_mux: PositiveInt = Field(1, description="Active sources per illumination pattern N_mux.")
    patterns: PositiveInt = Field(1, description="Number of illumination patterns T (random, see pattern_seed).")
    pattern_seed: int = Field(0, ge=0, description="Seed of the random patterns (≥ 0).")
    pattern_list: list[list[int]] | None = Field(
        None, description="Explicit patterns: lists of source indices (row-major, 0…Q−1); overrides n_mux/patterns.")

    @property
    def n_sources(self) -> int:
        """Q."""
        return self.source_grid[0] * self.source_grid[1]

    @model_validator(mode="after")
    def _sources_and_patterns(self):
        by_overlap = self.source_overlap is not None
        by_position = self.source_pitch_m is not None or self.source_distance_m is not None
        if by_overlap == by_position:
            raise ValueError("give either source_overlap or both source_pitch_m and source_distance_m")
        if by_position and (self.source_pitch_m is None or self.source_distance_m is None):
            raise ValueError("source positions need both source_pitch_m and source_distance_m")
        if by_overlap and self.source_overlap <= 0:
            raise ValueError(f"source_overlap {self.source_overlap} makes sources produce no overlap between "
                             "neighbouring spectrum regions, so phases cannot be retrieved; use a value in (0, 1), e.g. 0.66")
        q = self.n_sources
        if self.pattern_list is None:
            if self.n_mux > q:
                raise ValueError(f"n_mux {self.n_mux} is larger than the {q} sources of the "
                                 f"{self.source_grid[0]}x{self.source_grid[1]} illumination array; use n_mux ≤ {q}")
            return self
        if not self.pattern_list:
            raise ValueError("pattern_list is empty; list at least one pattern or remove the key")
        for t, pattern in enumerate(self.pattern_list):
            bad = [s for s in pattern if not 0 <= s < q]
            if bad:
                raise ValueError(f"pattern_list[{t}] names source {bad[0]}, which does not exist; "
                                 f"sources are numbered 0…{q - 1} (row-major over {self.source_grid[0]}x{self.source_grid[1]})")
            if not pattern or len(set(pattern)) != len(pattern):
                raise ValueError(f"pattern_list[{t}] must list distinct sources, got {pattern}")
        return self


class IngestSection(Section):
    """Recorded captures: a manifest of image files (README, "Real captures")."""

    manifest: Path = Field(..., description="Capture manifest (YAML, or CSV with a YAML sidecar); "
                                            "relative to the config file's directory.")


class HdrSection(Section):
    """Merging exposure brackets into linear radiance (README, "Real captures": HDR model)."""

    saturation_level: PositiveFloat | None = Field(
        None, description="Clipping level in black-subtracted counts (default: the manifest's white level minus "
                          "each pixel's black level).")
    read_noise: PositiveFloat | None = Field(
        None, description="Read noise, counts RMS (default: from dark frames or the manifest, else measured "
                          "from the exposure brackets).")
    electrons_per_count: PositiveFloat | None = Field(
        None, description="Conversion gain (default: from flat pairs or the manifest, else measured from the brackets).")
    noise_floor: float | None = Field(
        None, ge=0.0, description="Ignored (kept so that older configs load): every unsaturated frame counts, "
                                  "weighted by its noise.")
    min_weight: float = Field(1e-3, gt=0.0, le=1.0, description="Smallest weight of a valid pixel.")
    saturation_margin: float = Field(0.01, ge=0.0, lt=1.0,
                                     description="Values ≥ saturation_level·(1 − margin) count as saturated.")
    flux_tolerance: float = Field(0.02, gt=0.0, lt=1.0,
                                  description="Warn when a view's flux ratio between exposures is off by more than "
                                              "this (and by more than 4 standard deviations).")


class RegisterSection(Section):
    """Aligning views to the centre view with the checkerboard (config key ``registration``)."""

    crop_xywh: tuple[int, int, PositiveInt, PositiveInt] | None = Field(
        None, description="Object rectangle [x0, y0, width, height] in reference pixels, any aspect (default: the whole "
                          "frame); reconstruct pads it to its square grid.")
    object_xywh: tuple[NonNegativeInt, NonNegativeInt, PositiveInt, PositiveInt] | None = Field(
        None, description="Where the object is [x0, y0, width, height] (reference px), for the registration error "
                          "estimate and the board-hull check (default: the crop).")
    drop_missing: bool = Field(False, description="Drop (with a warning) views where the board is not found.")
    ransac_threshold_px: PositiveFloat = Field(1.0, description="RANSAC inlier threshold (reference px).")
    interpolation: Literal["linear", "cubic", "lanczos"] = Field("cubic", description="Warp kernel.")


class RunConfig(Section):
    """A whole run: one section per concern."""

    run: RunSection = RunSection()
    optics: OpticsSection = OpticsSection()
    scene: SceneSection = SceneSection()
    array: ArraySection = ArraySection(grid=21)
    noise: NoiseSection = NoiseSection()
    simulate: SimulateSection = SimulateSection()
    aberration: AberrationSection | None = None
    reconstruct: ReconstructSection = ReconstructSection()
    report: ReportSection = ReportSection()
    sweep: SweepSection | None = None
    multiplex: MultiplexSection | None = None
    ingest: IngestSection | None = None
    hdr: HdrSection | None = None
    # The register stage's section: "register" would shadow BaseModel.register (ABCMeta).
    registration: RegisterSection | None = None

    @model_validator(mode="after")
    def _ingest_needs_manifest(self):
        if "ingest" in self.run.stages and self.ingest is None:
            raise ValueError("run.stages lists ingest but there is no ingest section; add ingest: {manifest: FILE}")
        return self
