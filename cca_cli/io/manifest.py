"""Capture manifests: which image files were recorded where, with which exposure and optics.

A manifest is a YAML file, or a CSV table of images with a YAML/JSON sidecar
of the same stem. A YAML manifest may list its images itself (``images:``)
or point at a lab's own table (``images_csv:``) whose column names it maps
onto cca's (``columns:``, ``units:``); the optics may live in a separate
setup file (``setup: setup.json``). Rows have a kind: ``coherent`` (the
captures), ``calibration`` (the registration board photographed at a
position), ``dark`` and ``flat`` (sensor calibration frames). Everything is
validated here with one-line errors that name the file and the key. See the
README section "Real captures" for the format.
"""

from __future__ import annotations

import csv
import difflib
import json
import math
import os
import re
import string
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import (BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, PrivateAttr, ValidationError,
                      field_validator, model_validator)

from cca_cli.config.messages import accepted_keys, error_message, shown_value
from cca_cli.config.yaml_text import read_text_file, read_yaml_file
from cca_cli.errors import ConfigError, InputError, short
from cca_cli.io.h5 import unique_paths
from cca_cli.io.ptylab import is_ptylab_file, read_ptylab
from cca_cli.sampling.geometry import unit_slip

__all__ = ["Manifest", "ImageEntry", "CapturePlan", "LoadedManifest", "KINDS", "TABLE_COLUMNS", "load_manifest",
           "read_manifest", "plan_captures", "manifest_files", "read_pupil"]

#: Kinds of image rows.
KINDS = ("coherent", "calibration", "dark", "flat")
Kind = Literal["coherent", "calibration", "dark", "flat"]

#: cca's names for the columns of an image table, with the column read when ``columns:`` does not map them.
TABLE_COLUMNS = {"path": "path", "kind": "kind", "exposure": "exposure_s", "stage_x": "stage_x_mm",
                 "stage_y": "stage_y_mm", "row": "row", "col": "col", "kx_norm": "kx_norm", "ky_norm": "ky_norm",
                 "led_x": "led_x_mm", "led_y": "led_y_mm", "led_z": "led_z_mm", "camera": "camera",
                 "bit_depth": "bit_depth"}
#: Position columns of a table, read in ``units.position``.
_POSITION_COLUMNS = ("stage_x", "stage_y", "led_x", "led_y", "led_z")
_EXPOSURE_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
_POSITION_MM = {"m": 1e3, "cm": 10.0, "mm": 1.0, "um": 1e-3}
_SECTION_KEYS = ("optics", "illumination", "sensor", "checkerboard", "stage_pitch_mm", "values", "columns", "units",
                 "kind_values")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class _KnownPupil(_Strict):
    """Optional prior knowledge of the pupil, for the engines (not used by ingest itself)."""

    defocus_m: float | None = Field(None, allow_inf_nan=False,
                                    description="Known defocus of the object plane (m), stored as /geometry defocus_m.")
    pupil: Path | None = Field(None, description="Initial pupil: a .npy complex array sampled on the objective's NA "
                                                 "disc (the disc inscribed in the array), stored as "
                                                 "/calibration/initial_pupil.")


def _in_metres(value, info):
    """A length that reads as typed in nm, µm or mm instead of metres is refused (one line, with the fix)."""
    slip = None if value is None else unit_slip(info.field_name, value)
    if slip is not None:
        raise ValueError(slip)
    return value


class OpticsSpec(_KnownPupil):
    """Camera-scan optics (SI)."""

    wavelength_m: PositiveFloat
    focal_length_m: PositiveFloat
    aperture_diameter_m: PositiveFloat
    pixel_pitch_m: PositiveFloat
    distance_m: PositiveFloat

    _metres = field_validator("wavelength_m", "focal_length_m", "aperture_diameter_m", "pixel_pitch_m")(_in_metres)


class IlluminationSpec(_KnownPupil):
    """LED-array (angle-scan) microscope."""

    wavelength_m: PositiveFloat
    numerical_aperture: float = Field(..., gt=0, lt=1)
    pixel_pitch_object_m: PositiveFloat | None = Field(
        None, description="Camera pixel at the sample (m): the camera's pixel over the magnification; or give "
                          "pixel_pitch_m and magnification.")
    pixel_pitch_m: PositiveFloat | None = Field(None, description="The camera's own pixel (m), with magnification.")
    magnification: PositiveFloat | None = Field(None, description="The objective's (and tube lens') magnification.")
    sign: Literal[-1, 1] = Field(-1, description="Pupil at sign·sinθ·W/λ (−1: Zheng's reference convention).")
    led_distance_m: PositiveFloat | None = Field(
        None, allow_inf_nan=False, description="Distance of the LED plane from the sample (m), stored as /geometry "
                                               "led_distance_m: tiled reconstructions then light each tile from its "
                                               "own angles; with LED positions in mm, their distance.")
    led_axis_m: tuple[float, float] = Field(
        (0.0, 0.0), description="[x, y] where the optical axis meets the LED plane, in the coordinates of the images' "
                                "LED positions (m); default: their origin (for grid indices: the grid's middle).")
    led_pitch_m: PositiveFloat | None = Field(
        None, allow_inf_nan=False, description="Spacing of an LED matrix (m): images that give grid indices [row, col] "
                                               "are then at (col, row) × pitch from the grid's middle.")

    _metres = field_validator("wavelength_m", "pixel_pitch_object_m", "pixel_pitch_m", "led_pitch_m",
                              "led_distance_m")(_in_metres)

    @model_validator(mode="before")
    @classmethod
    def _object_pixel(cls, data):
        """The pixel at the sample: given, or the camera's pixel over the magnification (never both)."""
        if not isinstance(data, dict):
            return data
        camera = [data.get("pixel_pitch_m"), data.get("magnification")]
        if data.get("pixel_pitch_object_m") is not None:
            if any(v is not None for v in camera):
                raise ValueError("give either pixel_pitch_object_m or pixel_pitch_m with magnification, not both")
            return data
        if None in camera:
            raise ValueError("give pixel_pitch_object_m (the camera pixel at the sample, m), or the camera's "
                             "pixel_pitch_m and the magnification")
        try:
            return {**data, "pixel_pitch_object_m": float(camera[0]) / float(camera[1])}
        except (TypeError, ValueError, ZeroDivisionError):
            return data   # the fields' own checks name what is wrong

    @field_validator("led_axis_m")
    @classmethod
    def _finite_axis(cls, value):
        if not all(math.isfinite(v) for v in value):
            raise ValueError("must be two finite numbers [x, y] in metres")
        return value


class BayerSpec(_Strict):
    """Which sites of a single-channel colour mosaic to keep (half resolution)."""

    pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"]
    colour: Literal["R", "G", "B"] = "G"


class SensorSpec(_Strict):
    """How stored values become linear counts (see :mod:`cca_cli.io.sensor`)."""

    black_level: float = Field(0.0, ge=0, description="Offset to subtract when there are no dark frames (counts).")
    bit_depth: PositiveInt | None = Field(None, le=32, description="Significant bits N; levels are then N-bit codes.")
    container_bits: Literal[8, 16, 32] | None = Field(None, description="Bits of the files' integer type.")
    alignment: Literal["msb", "lsb"] | None = Field(None, description="N-bit codes at the top (msb) or bottom of "
                                                                      "the container; default: from the values.")
    white_level: PositiveFloat | None = Field(None, description="Clipping level (default: full scale).")
    channel: int | str | None = Field(None, description="Channel of colour files to use (index or name).")
    bayer: BayerSpec | None = Field(None, description="Colour sites to keep from single-channel mosaics.")
    read_noise: PositiveFloat | None = Field(None, description="Read noise, counts RMS (default: from dark frames "
                                                               "or the exposure brackets).")
    electrons_per_count: PositiveFloat | None = Field(None, description="Conversion gain (default: from flat "
                                                                        "pairs or the exposure brackets).")
    frame_scale: Literal["shared", "per_frame"] = Field(
        "shared", description="per_frame: each image was scaled on its own (to its own maximum, by an automatic "
                              "exposure), so the captures' relative brightness is unknown and the recovery fits it.")

    @model_validator(mode="after")
    def _one_colour_rule(self):
        if self.channel is not None and self.bayer is not None:
            raise ValueError("give sensor.channel (colour files) or sensor.bayer (mosaics), not both")
        if self.bit_depth is not None and self.container_bits is not None and self.bit_depth > self.container_bits:
            raise ValueError(f"bit_depth {self.bit_depth} does not fit container_bits {self.container_bits}")
        return self


class CheckerboardSpec(_Strict):
    """The registration board (beside the object, or photographed in calibration views)."""

    pattern: tuple[PositiveInt, PositiveInt]
    square_m: PositiveFloat | None = None


class SourceSpec(_Strict):
    """Images stored in one file (already merged, one image per illumination): a MATLAB variable with a table of
    the LEDs' sines, or a PtyLab FPM dataset (its images and geometry, :mod:`cca_cli.io.ptylab`)."""

    mat: Path | None = None
    variable: str = "imlow_HDR"
    illumination_csv: Path | None = None
    ptylab: Path | None = Field(None, description="A PtyLab FPM dataset (HDF5: ptychogram, encoder, zled, …).")

    @model_validator(mode="after")
    def _one_file(self):
        if (self.mat is None) == (self.ptylab is None):
            raise ValueError("give one of mat (with illumination_csv) or ptylab")
        if self.mat is not None and self.illumination_csv is None:
            raise ValueError("mat needs illumination_csv: the table of each image's LED (kx_norm, ky_norm)")
        if self.ptylab is not None and self.illumination_csv is not None:
            raise ValueError("a ptylab file holds its LEDs' positions: remove illumination_csv")
        return self


class UnitsSpec(_Strict):
    """Units of an image table's exposure and position columns."""

    exposure: Literal["s", "ms", "us"] = "s"
    position: Literal["m", "cm", "mm", "um"] = "mm"


class ImageEntry(_Strict):
    """One image: its kind, where it was taken, its exposure and its file."""

    #: ``(table file name, line)`` of a row read from an image table (for messages).
    _origin: tuple[str, int] | None = PrivateAttr(None)

    path: Path
    kind: Kind = "coherent"
    exposure_s: PositiveFloat = Field(1.0, allow_inf_nan=False)
    stage_x_mm: float | None = Field(None, allow_inf_nan=False)
    stage_y_mm: float | None = Field(None, allow_inf_nan=False)
    grid: tuple[int, int] | None = None
    kx_norm: float | None = Field(None, ge=-1, le=1, allow_inf_nan=False)
    ky_norm: float | None = Field(None, ge=-1, le=1, allow_inf_nan=False)
    led_x_mm: float | None = Field(None, allow_inf_nan=False)
    led_y_mm: float | None = Field(None, allow_inf_nan=False)
    led_z_mm: PositiveFloat | None = Field(None, allow_inf_nan=False)
    camera: int | None = Field(None, ge=0, le=2**31 - 1,
                               description="Camera of a camera array that took the image (0, 1, …): each camera "
                                           "its own lens and pupil.")
    bit_depth: PositiveInt | None = Field(None, le=32)

    @model_validator(mode="after")
    def _one_position(self):
        stage = self.stage_x_mm is not None or self.stage_y_mm is not None
        sines = self.kx_norm is not None or self.ky_norm is not None
        placed = self.led_x_mm is not None or self.led_y_mm is not None
        if stage and (self.stage_x_mm is None or self.stage_y_mm is None):
            raise ValueError("give both stage_x_mm and stage_y_mm")
        if sines and (self.kx_norm is None or self.ky_norm is None):
            raise ValueError("give both kx_norm and ky_norm")
        if placed and (self.led_x_mm is None or self.led_y_mm is None):
            raise ValueError("give both led_x_mm and led_y_mm")
        if self.led_z_mm is not None and not placed and self.kind in ("coherent", "calibration"):
            raise ValueError("led_z_mm goes with led_x_mm and led_y_mm")
        if sines and placed:
            raise ValueError("give the illumination as kx_norm/ky_norm or as led_x_mm/led_y_mm, not both")
        if stage and (sines or placed):
            raise ValueError("give a stage position or an illumination angle, not both")
        if self.kind in ("coherent", "calibration") and not (stage or sines or placed or self.grid is not None):
            raise ValueError("give a position: stage_x_mm/stage_y_mm, grid, kx_norm/ky_norm or led_x_mm/led_y_mm")
        return self

    @property
    def position_kind(self) -> str | None:
        """``stage``, ``led``, ``grid`` (grid indices only) or None (dark/flat frames without a position)."""
        if self.stage_x_mm is not None:
            return "stage"
        if self.kx_norm is not None or self.led_x_mm is not None:
            return "led"
        return "grid" if self.grid is not None else None


class Manifest(_Strict):
    """A capture manifest."""

    optics: OpticsSpec | None = None
    illumination: IlluminationSpec | None = None
    sensor: SensorSpec = SensorSpec()
    checkerboard: CheckerboardSpec | None = None
    stage_pitch_mm: PositiveFloat | None = None
    values: Literal["intensity", "amplitude"] = "intensity"
    setup: Path | None = Field(None, description="YAML or JSON file holding the optics (or other sections).")
    columns: dict[str, str] | None = Field(None, description="cca column name → the table's column name.")
    units: UnitsSpec = UnitsSpec()
    kind_values: dict[str, Kind] | None = Field(None, description="The table's kind words → cca kinds.")
    images: list[ImageEntry] | None = None
    images_csv: Path | None = None
    image_files: str | None = Field(None, description="With images_csv: each row's file name, from its cells "
                                                        "(img_{index:03d}.tif), where the table has no file column.")
    source: SourceSpec | None = None

    @field_validator("image_files")
    @classmethod
    def _a_pattern(cls, pattern):
        if pattern is None:
            return pattern
        fields = [name for _, name, _, _ in string.Formatter().parse(pattern) if name is not None]
        if not fields or any(not name for name in fields):
            raise ValueError(f"{pattern!r} names no table column; write a file name with the columns in braces, "
                             "e.g. img_{index:03d}.tif")
        return pattern

    @field_validator("columns")
    @classmethod
    def _known_columns(cls, columns):
        unknown = sorted(set(columns or {}) - set(TABLE_COLUMNS))
        if unknown:
            raise ValueError(f"unknown cca column name(s) {', '.join(unknown)}; map any of {', '.join(TABLE_COLUMNS)}")
        return columns

    @model_validator(mode="after")
    def _consistent(self):
        if (self.optics is None) == (self.illumination is None):
            raise ValueError("give exactly one of optics (camera scan) or illumination (LED array)")
        if sum(x is not None for x in (self.images, self.images_csv, self.source)) != 1:
            raise ValueError("give exactly one of images, images_csv or source")
        if self.source is not None and self.illumination is None:
            raise ValueError("source (a .mat of LED-array images) needs an illumination section")
        if self.source is not None and self.source.ptylab is not None and self.optics is not None:
            raise ValueError("source.ptylab holds an LED-array microscope: give illumination keys, not optics")
        if self.image_files is not None and self.images_csv is None:
            raise ValueError("image_files names the files of an image table's rows; give images_csv too")
        return self

    @property
    def known_pupil(self) -> _KnownPupil:
        """The optics or illumination section (where defocus_m and pupil live)."""
        return self.optics if self.optics is not None else self.illumination


@dataclass(frozen=True)
class LoadedManifest:
    """A validated manifest, the files it was read from and the notes to show once."""

    manifest: Manifest
    files: list[Path]
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class CapturePlan:
    """The images of a manifest grouped by kind and position, exposures ascending.

    Attributes
    ----------
    manifest : Manifest
    path : Path
        The manifest file.
    files : list of list of Path
        ``files[k][e]``: coherent image of position k, exposure e (empty for a .mat source).
    exposure_s : ndarray, (K, E)
    positions : ndarray, (K, 2)
        Stage [y, x] in metres (camera scan) or [sin θy, sin θx] (LED array).
    grid_indices : ndarray, (K, 2) or None
        Given grid indices, else None.
    labels : list of str
        One readable name per position (used in errors and the report).
    calibration : list of list of (Path, float) or None
        Board images (file, exposure) of each position; None without calibration rows.
    darks, flats : list of (Path, float)
        Dark and flat frames with their exposures.
    bit_depth : int or None
        Bit depth the coherent, dark and flat rows state (one value for all of them).
    calibration_bit_depths : dict of Path to int
        Bit depth each calibration row states, where it states one (board views may be
        taken in another camera mode than the captures).
    notes : list of str
        What was noticed while planning (ignored columns …), to show once.
    camera_index : ndarray, int32, (K,) or None
        Camera of each position in a camera array, when the rows name it.
    """

    manifest: Manifest
    path: Path
    files: list[list[Path]]
    exposure_s: np.ndarray
    positions: np.ndarray
    grid_indices: np.ndarray | None
    labels: list[str]
    calibration: list[list[tuple[Path, float]]] | None = None
    darks: list[tuple[Path, float]] = field(default_factory=list)
    flats: list[tuple[Path, float]] = field(default_factory=list)
    bit_depth: int | None = None
    calibration_bit_depths: dict[Path, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    camera_index: np.ndarray | None = None

    @property
    def kind(self) -> str:
        """``camera_scan`` or ``led_array``."""
        return "camera_scan" if self.manifest.optics is not None else "led_array"

    def all_files(self) -> list[Path]:
        """Every image file of the plan: coherent, calibration, dark and flat frames."""
        out = [p for row in self.files for p in row]
        for views in self.calibration or ():
            out += [p for p, _ in views]
        return out + [p for p, _ in self.darks] + [p for p, _ in self.flats]


def _describe(error: dict, source: str) -> str:
    loc = ".".join(str(p) for p in error["loc"]) or "(top level)"
    if error["type"] == "extra_forbidden":
        keys = ", ".join(accepted_keys(Manifest, error["loc"])) or "see the README"
        return f"{source}: {loc}: unknown key; accepted keys here: {keys}"
    value = error.get("input")
    suffix = f" (got {shown_value(value)})" if not isinstance(value, dict) else ""
    return f"{source}: {loc}: {error_message(error)}{suffix}"


def _first_error(exc: ValidationError) -> dict:
    """A misspelled key explains a missing one, so report unknown keys first."""
    errors = exc.errors()
    return next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])


def _with_ptylab(data: dict, path: Path, source: str, files: list[Path], notes: list[str]) -> LoadedManifest:
    """A manifest whose images are a PtyLab FPM file: its illumination keys from the file, the manifest's own
    ``illumination`` keys over them (``numerical_aperture`` where the file has no ``NA``)."""
    ptylab = Path(data["source"]["ptylab"])
    if not ptylab.is_file():
        raise InputError(f"{ptylab}: file not found (manifest source.ptylab); check the path")
    found = read_ptylab(ptylab)
    given = data.get("illumination") or {}
    if not isinstance(given, dict):
        raise ConfigError(f"{source}: illumination must be a mapping of keys")
    if found.numerical_aperture is None and "numerical_aperture" not in given:
        where = "in a manifest beside it: source: {ptylab: " + ptylab.name + "}, illumination: {numerical_aperture: …}" \
            if path == ptylab else f"in {source}'s illumination section"
        raise ConfigError(f"{ptylab}: has no NA, and cca needs the objective's numerical aperture: give it {where}")
    if given.get("pupil") is not None:   # a known pupil beside the manifest
        given = {**given, "pupil": str(_resolve(path.parent, given["pupil"]))}
        files = [*files, Path(given["pupil"])]
    data = {**data, "illumination": {**found.illumination(), **given}}
    try:
        manifest = Manifest.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_describe(_first_error(exc), source)) from None
    return LoadedManifest(manifest, [*files, ptylab] if ptylab not in files else files, [*notes, *found.notes])


def _read_mapping(path: Path, what: str) -> dict:
    """A YAML or JSON file that must hold a mapping (read with the safe YAML reader: no aliases bombs, no pipes)."""
    if path.suffix.lower() == ".json":
        text = read_text_file(path, what=what)
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"{path}: line {exc.lineno}: not valid JSON ({exc.msg})") from None
    else:
        data = read_yaml_file(path, what=what)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a {what}: the top level must be a mapping (optics, sensor, images …)")
    if what == "manifest" and data and not set(map(str, data)) & set(Manifest.model_fields):
        raise ConfigError(f"{path}: not a capture manifest: none of its top-level keys is a manifest key "
                          f"({', '.join(Manifest.model_fields)})")
    return data


def _resolve(base: Path, p) -> Path:
    p = Path(p).expanduser()
    return p if p.is_absolute() else base / p


def _merge_setup(data: dict, setup_path: Path, source: str, notes: list[str]) -> tuple[dict, set[str], list[str]]:
    """Sections of a setup file merged into a manifest mapping (a section given twice is an error).

    A setup file (the optics or illumination section itself, or a file of
    sections) may carry the lab's other facts too: keys cca does not know
    are ignored, with a note. Returns the mapping, the sections the setup
    file gave and the keys it ignored.
    """
    setup = _read_mapping(setup_path, "setup file")
    if any(k in setup for k in ("images", "images_csv", "source", "setup")):
        raise ConfigError(f"{setup_path}: a setup file holds optics and sensor sections, not images; "
                          "remove images/images_csv/source/setup from it")
    if not any(k in setup for k in _SECTION_KEYS):
        name = "illumination" if "numerical_aperture" in setup else "optics"
        model = IlluminationSpec if name == "illumination" else OpticsSpec
        ignored = [k for k in setup if k not in model.model_fields]
        if ignored:
            notes.append(f"{setup_path.name}: keys not used by cca, ignored: {', '.join(ignored)}")
        setup = {name: {k: v for k, v in setup.items() if k in model.model_fields}}
    else:   # a file of sections: the lab's other facts beside them are ignored alike, but not cca's own keys
        ignored = [k for k in setup if k not in _SECTION_KEYS]
        for key in ignored:
            home = next((name for name, model in (("sensor", SensorSpec), ("optics", OpticsSpec),
                                                  ("illumination", IlluminationSpec)) if key in model.model_fields),
                        None)
            if home is not None:
                raise ConfigError(f"{setup_path}: {key} belongs in the {home} section; move it there")
            close = difflib.get_close_matches(key, _SECTION_KEYS, n=1, cutoff=0.8)
            if close:
                raise ConfigError(f"{setup_path}: {key} is not a section; did you mean {close[0]}?")
        if ignored:
            notes.append(f"{setup_path.name}: keys not used by cca, ignored: {', '.join(ignored)}")
        setup = {k: v for k, v in setup.items() if k in _SECTION_KEYS}
    for name in ("optics", "illumination"):
        section = setup.get(name)
        if isinstance(section, dict) and section.get("pupil") is not None:
            section["pupil"] = str(_resolve(setup_path.parent, section["pupil"]))
    for key, value in setup.items():
        if key in data:
            raise ConfigError(f"{source}: {key} is given both here and in {setup_path.name}; keep one")
        data[key] = value
    return data, set(setup), ignored


def _whole_number(text: str) -> bool:
    """Whether a table cell holds a camera number: empty, or a whole number ≥ 0."""
    try:
        value = float(text) if text != "" else 0.0
    except ValueError:
        return False
    return math.isfinite(value) and value >= 0 and value == int(value)


def _plain_name(column: str) -> str:
    """A column name as unit suffixes are matched: lower case, no spaces, µ as u."""
    return column.lower().replace(" ", "").replace("µ", "u")


def _unit_of_name(column: str, units: dict[str, float]) -> str | None:
    """The unit a column name announces by its suffix (``exposure_ms``, ``exposure [ms]`` → ``ms``), if any."""
    plain = _plain_name(column)
    for unit in sorted(units, key=len, reverse=True):
        if plain.endswith(f"_{unit}") or plain.endswith(f"[{unit}]") or plain.endswith(f"({unit})"):
            return unit
    return None


def _column_in_any_unit(header: list[str], stem: str, units: dict[str, float], source: str,
                        table: Path) -> str | None:
    """The column named ``stem`` with a unit (``exposure_ms``, ``exposure [ms]``), if the table has one."""
    forms = {f"{stem}{form}" for unit in units for form in (f"_{unit}", f"[{unit}]", f"({unit})")}
    found = [h for h in header if _plain_name(h) in forms]
    if len(found) > 1:
        raise ConfigError(f"{source}: {table.name} has {' and '.join(repr(h) for h in found)}: say which one to "
                          f"read with columns: {{{stem}: <column>}}")
    return found[0] if found else None


def _is_value(cell: str) -> bool:
    """Whether a table cell is a number or an image file's name (a header line holds neither)."""
    try:
        float(cell.replace(",", "."))
        return True
    except ValueError:
        return Path(cell).suffix.lower() in (".tif", ".tiff", ".png", ".jpg", ".jpeg", ".exr", ".fits", ".dpx",
                                             ".bmp", ".pgm", ".raw", ".npy")


#: Column names (lower case, no spaces or underscores) that hold exposure times, though without a unit.
_EXPOSURE_WORDS = ("exposure", "exposuretime", "exptime", "exp", "integrationtime", "shutter", "shutterspeed")


#: Separators a table may use instead of commas (spreadsheets in locales with decimal commas write ``;``).
_SEPARATORS = {";": "semicolons", "\t": "tabs"}


def read_table(table: Path, source: str) -> tuple[list[str], list[tuple[int, dict]], str | None]:
    """A CSV table's header and rows (with their line numbers), cells stripped.

    A byte-order mark (a spreadsheet's "CSV UTF-8") is dropped, and a header with no comma but
    semicolons or tabs is read with that separator.

    Returns
    -------
    header : list of str
    rows : list of (int, dict)
    separator : str or None
        What separates the columns, when not commas (for a note).
    """
    try:
        with open(table, newline="", encoding="utf-8-sig") as handle:
            first = handle.readline()
            handle.seek(0)
            separator = None if "," in first else next((s for s in _SEPARATORS if s in first), None)
            reader = csv.DictReader(handle, delimiter=separator or ",")
            header = [h.strip() for h in (reader.fieldnames or []) if h is not None]
            rows = []
            for row in reader:
                rows.append((reader.line_num, {(k or "").strip(): (v or "").strip() for k, v in row.items()
                                               if k is not None and not isinstance(v, list)}))
    except FileNotFoundError:
        raise InputError(f"{table}: image table not found (named by {source})") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{table}: cannot read the table ({exc})") from None
    return header, rows, None if separator is None else _SEPARATORS[separator]


#: A number written with a decimal comma (``-20,5``; no thousands separators).
_DECIMAL_COMMA = re.compile(r"[+-]?(\d+,\d*|,\d+)([eE][+-]?\d+)?")


def _unknown_kind(word: str, kind_words: dict, table: Path, line: int, source: str) -> str:
    """The message for a table's kind word that is neither cca's nor one ``kind_values`` maps."""
    mapped = difflib.get_close_matches(word.lower(), list(kind_words), n=1, cutoff=0.6)
    if mapped:
        return (f"{table}: line {line}: kind {word!r} is not one of cca's kinds ({', '.join(KINDS)}); kind_values in "
                f"{source} maps {mapped[0]!r}: did you mean {word!r} there?")
    words = f" nor a word kind_values maps ({', '.join(kind_words)})" if kind_words else ""
    return (f"{table}: line {line}: kind {word!r} is not one of cca's kinds ({', '.join(KINDS)}){words}; map the "
            f"table's words in {source}, e.g. kind_values: {{{word}: coherent}} (or calibration, dark, flat)")


#: Where a row's file name made from ``image_files`` is kept among its cells.
_PATTERN_PATH = "\0image_files"


class _CellFormatter(string.Formatter):
    """Fills a file-name pattern from a row's cells: a cell stays the text it is (``001`` stays ``001``) unless
    its field asks for a number (``{index:03d}``, ``{x:.1f}``): then a whole number is an integer, any other a
    float."""

    def format_field(self, value, format_spec):
        if isinstance(value, str) and format_spec and format_spec[-1] in "bcdoxXneEfFgG%":
            number = float(value)
            value = int(number) if number.is_integer() and format_spec[-1] in "bcdoxXn" else number
        return super().format_field(value, format_spec)


def _file_of_row(pattern: str, row: dict, table: Path, line: int) -> str:
    """``pattern`` filled from the row's cells (:class:`_CellFormatter`)."""
    try:
        return _CellFormatter().vformat(pattern, (), row)
    except (KeyError, ValueError, IndexError) as exc:
        raise ConfigError(f"{table}: line {line}: image_files {pattern!r} cannot be filled from this row ({exc}); "
                          "check the row's cells and the pattern's formats") from None


def _table_entries(table: Path, manifest: Manifest, source: str) -> tuple[list[dict], list[str], list[int]]:
    """Rows of an image table as ImageEntry mappings (cca names, SI-ish units), the notes, and each row's line."""
    header, rows, separator = read_table(table, source)
    if header and sum(_is_value(cell) for cell in header) >= max(2, len(header) / 2):
        raise ConfigError(f"{table}: its first line holds values ({', '.join(header[:4])}), not column names: add a "
                          "header line naming the columns (path, exposure_ms, stage_x_mm, …; see columns: to map "
                          "the lab's own names)")
    mapping = dict(TABLE_COLUMNS)
    explicit = manifest.columns or {}
    mapping.update(explicit)
    # exposure_ms where exposure_s is looked for: taken, and checked against units below like any named column
    sines = any(mapping[name] in header for name in ("kx_norm", "ky_norm"))
    for name in ("exposure", *_POSITION_COLUMNS):
        if name not in explicit and mapping[name] not in header and not (sines and name in _POSITION_COLUMNS):
            found = _column_in_any_unit(header, mapping[name].rsplit("_", 1)[0],
                                        _EXPOSURE_S if name == "exposure" else _POSITION_MM, source, table)
            if found is not None:
                mapping[name] = found
    for name, column in explicit.items():
        if column not in header:
            raise ConfigError(f"{source}: columns.{name}: {table.name} has no column {column!r} "
                              f"(its columns: {', '.join(header)})")
    if mapping["exposure"] not in header:
        unitless = [h for h in header if re.sub(r"[\s_]", "", _plain_name(h)) in _EXPOSURE_WORDS]
        if unitless:
            raise ConfigError(f"{source}: {table.name}'s column {unitless[0]!r} gives no unit, so it is not read as "
                              f"the exposure: name it with its unit ({unitless[0]}_ms, _s or _us), or map it with "
                              f"columns: {{exposure: {unitless[0]}}} and units: {{exposure: ms}} (or s, us)")
    used = {name: column for name, column in mapping.items() if column in header}
    pattern = manifest.image_files
    if pattern is not None:
        if "path" in explicit:
            raise ConfigError(f"{source}: give either image_files or columns.path, not both")
        used.pop("path", None)
        wanted = [name for _, name, _, _ in string.Formatter().parse(pattern) if name is not None]
        lacking = [name for name in wanted if name not in header]
        if lacking:
            raise ConfigError(f"{source}: image_files {pattern!r} names {', '.join(repr(n) for n in lacking)}, which "
                              f"{table.name} lacks (its columns: {', '.join(header)})")
        for line, row in rows:
            row[_PATTERN_PATH] = _file_of_row(pattern, row, table, line)
        used["path"] = _PATTERN_PATH
    elif "path" not in used:
        raise ConfigError(f"{table}: no file column (looked for {mapping['path']!r}); map it with columns: "
                          f"{{path: <column>}} in {source}, or name the files from the rows' cells with "
                          "image_files: img_{index:03d}.tif")
    if "camera" in used and "camera" not in explicit and (manifest.illumination is not None or not all(
            _whole_number(row.get(used["camera"], "")) for _, row in rows)):
        used.pop("camera")   # a column merely called so (a camera model, an LED array's): the lab's notes
    if any(name in used for name in ("kx_norm", "ky_norm", "stage_x", "stage_y")):
        for name in ("led_x", "led_y", "led_z"):   # the table's own positions given: LED positions are notes beside
            if name not in explicit:
                used.pop(name, None)
    # A column whose name announces its unit is read in it where units: leaves that unit unstated; a stated one
    # must agree with every column's name.
    stated = manifest.units.model_fields_set
    chosen_units = {"exposure": manifest.units.exposure, "position": manifest.units.position}
    for key, table_units, names in (("exposure", _EXPOSURE_S, ("exposure",)),
                                    ("position", _POSITION_MM, _POSITION_COLUMNS)):
        announced = {used[name]: _unit_of_name(used[name], table_units) for name in names if name in used}
        announced = {column: unit for column, unit in announced.items() if unit is not None}
        if key not in stated and len(set(announced.values())) == 1:
            chosen_units[key] = next(iter(announced.values()))
        for column, unit in announced.items():
            if unit != chosen_units[key]:
                why = f"units.{key} is {chosen_units[key]}" if key in stated else ", ".join(
                    f"{c!r} looks like {u}" for c, u in announced.items() if u != unit)
                raise ConfigError(f"{source}: column {column!r} of {table.name} looks like {unit} but {why}; "
                                  f"set units: {{{key}: {unit}}} (or rename the columns to agree)")
    notes = [] if separator is None else [f"{table.name}: columns separated by {separator}, read so"]
    named = set(used.values()) | ({n for _, n, _, _ in string.Formatter().parse(pattern) if n} if pattern else set())
    ignored = [h for h in header if h not in named]
    if ignored:
        notes.append(f"{table.name}: columns not used by cca, ignored: {', '.join(ignored)}")
    exposure_factor = _EXPOSURE_S[chosen_units["exposure"]]
    position_factor = _POSITION_MM[chosen_units["position"]]
    kind_words = {k.lower(): v for k, v in (manifest.kind_values or {}).items()}
    stated = "exposure" in used and any(row.get(used["exposure"], "") for _, row in rows)
    entries = []
    decimal_commas = []
    for line, row in rows:
        def number(name: str):
            text = row.get(used[name], "") if name in used else ""
            if text == "":
                return None
            try:
                value = float(text)
            except ValueError:
                # a spreadsheet in a locale with decimal commas separates its columns otherwise: 1,5 is 1.5
                if separator is not None and _DECIMAL_COMMA.fullmatch(text):
                    decimal_commas.append(used[name])
                    value = float(text.replace(",", "."))
                else:
                    image = row.get(used["path"], "") if "path" in used else ""
                    image = f" ({Path(image).name})" if image else ""
                    raise ConfigError(f"{table}: line {line}{image}: column {used[name]!r} is {text!r}, not a "
                                      "number; fix the row") from None
            if not math.isfinite(value):
                where = f" ({row.get(used['path'])})" if row.get(used["path"]) else ""
                raise ConfigError(f"{table}: line {line}{where}: column {used[name]!r} is {text!r}; every position "
                                  "and exposure must be a finite number: fix or remove the row")
            return value

        entry: dict = {"path": row.get(used["path"], "")}
        if not entry["path"]:
            raise ConfigError(f"{table}: line {line}: column {used['path']!r} is empty; give the image file")
        if "kind" in used and row.get(used["kind"]):
            word = row[used["kind"]].lower()
            kind = kind_words.get(word, word)
            if kind not in KINDS:
                raise ConfigError(_unknown_kind(row[used["kind"]], kind_words, table, line, source))
            entry["kind"] = kind
        if stated and not row.get(used["exposure"], "") and entry.get("kind") != "calibration":
            raise ConfigError(f"{table}: line {line} ({entry['path']}): column {used['exposure']!r} is empty; give "
                              "this image's exposure as the other rows do")
        exposure = number("exposure")
        if exposure is not None:
            entry["exposure_s"] = exposure * exposure_factor
        x, y = number("stage_x"), number("stage_y")
        if x is not None or y is not None:
            entry["stage_x_mm"] = None if x is None else x * position_factor
            entry["stage_y_mm"] = None if y is None else y * position_factor
        row_index, col_index = number("row"), number("col")
        if row_index is not None or col_index is not None:
            entry["grid"] = [row_index, col_index]
        for name in ("kx_norm", "ky_norm"):
            value = number(name)
            if value is not None:
                entry[name] = value
        for name in ("led_x", "led_y", "led_z"):
            value = number(name)
            if value is not None:
                entry[f"{name}_mm"] = value * position_factor
        bits = number("bit_depth")
        if bits is not None:
            entry["bit_depth"] = bits
        camera = number("camera")
        if camera is not None:
            entry["camera"] = camera
        entries.append((line, entry, row))
    out = []
    for line, entry, row in entries:
        try:
            ImageEntry.model_validate(entry)
        except ValidationError as exc:
            err = _first_error(exc)
            loc = ".".join(str(p) for p in err["loc"])
            # name the table's own column and the value it holds (the entry's keys are cca's)
            cca_name = next((n for n, key in TABLE_COLUMNS.items() if key == loc), loc)
            column = f"column {used[cca_name]!r} ({loc})" if cca_name in used and used[cca_name] != loc else loc
            text = row.get(used[cca_name], "") if cca_name in used else ""
            got = f" (got {text})" if text else ""   # as the table holds it (before any unit conversion)
            hint = "; it is sin θ of the illumination, not an angle" if loc in ("kx_norm", "ky_norm") else ""
            positions = ("stage_x", "stage_y", "row", "col", "kx_norm", "ky_norm", "led_x", "led_y")
            if not loc and "give a position" in error_message(err) and not any(n in used for n in positions):
                raise ConfigError(f"{table}: line {line} ({entry['path']}): no position column found: "
                                  f"{table.name} has {', '.join(header)}; name its position columns in {source} "
                                  "with columns: {led_x: <column>, led_y: <column>} (LED positions, with "
                                  "led_distance_m), {stage_x: …, stage_y: …}, {kx_norm: …, ky_norm: …} or "
                                  "{row: …, col: …}, and their unit with units: {position: mm}") from None
            raise ConfigError(f"{table}: line {line} ({entry['path']}): {column + ': ' if loc else ''}"
                              f"{error_message(err)}{got}{hint}") from None
        out.append(entry)
    if decimal_commas:
        notes.append(f"{table.name}: decimal commas in {', '.join(sorted(set(decimal_commas)))} read as decimal points")
    return out, notes, [line for line, _, _ in entries]


def read_manifest(path: str | Path) -> LoadedManifest:
    """Read and validate a manifest (YAML, or CSV with a sidecar ``<stem>.yaml``/``.json``).

    Relative paths are resolved against the directory of the file naming them.

    Raises
    ------
    ConfigError
        A key is unknown or a value is invalid: one line naming the file and key.
    InputError
        The manifest (or its table or setup file) cannot be read.
    """
    path = Path(path)
    files = [path]
    if path.suffix.lower() in (".h5", ".hdf5") and is_ptylab_file(path):
        data = {"source": {"ptylab": str(path.resolve())}}
        return _with_ptylab(data, path, str(path), files, [])
    if path.suffix.lower() == ".csv":
        if not path.is_file():
            raise InputError(f"{path}: manifest not found; check the path")
        sidecar = next((s for s in (path.with_suffix(".yaml"), path.with_suffix(".yml"), path.with_suffix(".json"))
                        if s.is_file()), None)
        if sidecar is None:
            raise InputError(f"{path}: a CSV manifest needs the optics in {path.with_suffix('.yaml').name} (or .json) "
                             "next to it; write that file, or a YAML manifest with images_csv and setup")
        data = _read_mapping(sidecar, "manifest")
        if any(k in data for k in ("images", "images_csv", "source")):
            raise ConfigError(f"{sidecar}: a CSV manifest's sidecar must not list images; remove images/images_csv/source")
        data["images_csv"] = str(path.resolve())
        source = str(sidecar)
        files.append(sidecar)
    else:
        data = _read_mapping(path, "manifest")
        source = str(path)
    notes: list[str] = []
    from_setup, setup_ignored = set(), []
    if data.get("setup") is not None:
        setup_path = _resolve(path.parent, data["setup"])
        data, from_setup, setup_ignored = _merge_setup(data, setup_path, source, notes)
        data["setup"] = str(setup_path)
        files.append(setup_path)
    given = data.get("source")
    if isinstance(given, dict) and given.get("ptylab") is not None:
        data = {**data, "source": {**given, "ptylab": str(_resolve(path.parent, given["ptylab"]))}}
        return _with_ptylab(data, path, source, files, notes)
    try:
        manifest = Manifest.model_validate(data)
    except ValidationError as exc:
        error = _first_error(exc)
        if not (error["loc"] and error["loc"][0] in from_setup):
            raise ConfigError(_describe(error, source)) from None
        message = _describe(error, str(setup_path))
        key = str(error["loc"][-1])
        close = difflib.get_close_matches(key, setup_ignored, n=1, cutoff=0.6) if error["type"] == "missing" else []
        if close:   # wavelength_nm for wavelength_m: the lab's own name for a key cca needs
            message += f"; {setup_path.name} has {close[0]} (not read): give {key} instead"
        raise ConfigError(message) from None
    base = path.parent
    if manifest.images_csv is not None:
        table = _resolve(base, manifest.images_csv)
        entries, table_notes, lines = _table_entries(table, manifest, source)
        notes += table_notes
        # A table's file names are relative to the table itself (it usually sits beside the images).
        images = [ImageEntry.model_validate(e) for e in entries]
        images = [e.model_copy(update={"path": _resolve(table.parent, e.path)}) for e in images]
        for image, line in zip(images, lines):
            image._origin = (table.name, line)
            if not (image.path.exists() or image.path.is_symlink()):
                raise InputError(f"{image.path}: named by line {line} of {table} but not found; check that row "
                                 f"(paths are relative to the table's folder)")
        notes += _unlisted_images(table, images)
        manifest = manifest.model_copy(update={"images": images, "images_csv": table})
        files.append(table)
    elif manifest.columns is not None:
        raise ConfigError(f"{source}: columns maps the columns of an image table; give images_csv or remove columns")
    if manifest.images_csv is None and manifest.images is not None:
        manifest = manifest.model_copy(update={"images": [e.model_copy(update={"path": _resolve(base, e.path)})
                                                          for e in manifest.images]})
    if manifest.source is not None and manifest.source.mat is not None:
        manifest = manifest.model_copy(update={"source": manifest.source.model_copy(update={
            "mat": _resolve(base, manifest.source.mat),
            "illumination_csv": _resolve(base, manifest.source.illumination_csv)})})
    known = manifest.known_pupil
    if known.pupil is not None:
        pupil = _resolve(base, known.pupil)
        section = "optics" if manifest.optics is not None else "illumination"
        manifest = manifest.model_copy(update={section: known.model_copy(update={"pupil": pupil})})
        files.append(pupil)
    if manifest.images is not None and not manifest.images:
        raise ConfigError(f"{source}: images: the list is empty; list at least one image")
    return LoadedManifest(manifest=manifest, files=files, notes=notes)


def _unlisted_images(table: Path, images: list) -> list[str]:
    """A note when the folder of the table's images holds more image files like them than the table lists."""
    folders = {image.path.parent for image in images}
    suffixes = {image.path.suffix.lower() for image in images}
    if len(folders) != 1 or not suffixes:
        return []
    folder = folders.pop()
    listed = {image.path.name for image in images}
    try:
        others = sorted(p.name for p in folder.iterdir()
                        if p.suffix.lower() in suffixes and p.name not in listed and p.is_file())
    except OSError:
        return []
    if not others:
        return []
    shown = ", ".join(others[:3]) + (", …" if len(others) > 3 else "")
    return [f"{folder} holds {len(others)} more {'/'.join(sorted(suffixes))} file(s) than {table.name} lists "
            f"({shown}); they are not read: add their rows if they are captures"]


def load_manifest(path: str | Path) -> Manifest:
    """Read and validate a manifest (see :func:`read_manifest`)."""
    return read_manifest(path).manifest


def manifest_files(path: str | Path) -> list[Path]:
    """The manifest and every file it names (for provenance hashing)."""
    loaded = read_manifest(path)
    manifest = loaded.manifest
    files = list(loaded.files)
    if manifest.images is not None:
        files += [e.path for e in manifest.images]
    if manifest.source is not None:
        files += [f for f in (manifest.source.mat, manifest.source.illumination_csv, manifest.source.ptylab)
                  if f is not None]
    return unique_paths(files)   # a CSV manifest is also its own table


def read_pupil(path: Path, source: str) -> np.ndarray:
    """Load an initial pupil file: a square complex (or real) .npy array on the objective's NA disc.

    Raises
    ------
    InputError
        Missing or unreadable file, wrong shape or non-finite values; one line naming the file.
    """
    try:
        pupil = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(f"{path}: pupil file not found (named by {source}); check the path") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read the pupil ({' '.join(str(exc).split())}); save it with numpy.save") from None
    if pupil.ndim != 2 or pupil.shape[0] != pupil.shape[1] or pupil.shape[0] < 4:
        raise InputError(f"{path}: the pupil must be a square 2-D array (the NA disc inscribed in it), "
                         f"got shape {pupil.shape}")
    if not np.issubdtype(pupil.dtype, np.number):
        raise InputError(f"{path}: the pupil holds {pupil.dtype} values; save a complex array")
    pupil = pupil.astype(np.complex64)
    if not np.isfinite(pupil).all():
        raise InputError(f"{path}: the pupil holds NaN or infinite values; fix it")
    return pupil


def _fmt(v: float) -> str:
    return f"{v:g}"


def _position_text(key: tuple) -> str:
    if key[0] == "stage":
        return f"position (x {_fmt(key[2])}, y {_fmt(key[1])}) mm"
    if key[0] == "grid":
        return f"grid position (row {key[1]}, col {key[2]})"
    return f"illumination (kx {_fmt(key[2])}, ky {_fmt(key[1])})"


def _source(manifest: Manifest, path: Path) -> Path:
    """The file that lists the images: the manifest's table, else the manifest."""
    return manifest.images_csv if manifest.images_csv is not None else path


def _key(entry: ImageEntry) -> tuple:
    """Group key of a coherent or calibration row: grid indices when given, else the position itself."""
    if entry.grid is not None:
        return ("grid", *entry.grid)
    if entry.stage_x_mm is not None:
        return ("stage", entry.stage_y_mm, entry.stage_x_mm)
    return ("led", entry.ky_norm, entry.kx_norm)


def _led_positions_as_sines(manifest: Manifest, path: Path) -> Manifest:
    """The manifest with LED positions (mm) turned into the sines of their illumination.

    An LED at ``(x, y)`` in the LED plane, ``z`` from the sample, lights it at ``sin θx = (x − x₀) / r``,
    ``sin θy = (y − y₀) / r`` with ``r = √((x − x₀)² + (y − y₀)² + z²)`` and ``(x₀, y₀)`` where the optical axis
    meets the plane (``illumination.led_axis_m``).
    """
    manifest = _led_grid_as_positions(manifest, path)
    placed = [e for e in manifest.images if e.led_x_mm is not None]
    if not placed:
        return manifest
    source = _source(manifest, path)
    if manifest.illumination is None:
        raise ConfigError(f"{path}: images give LED positions (led_x_mm/led_y_mm) but the manifest has optics, not "
                          "illumination")
    distance = manifest.illumination.led_distance_m
    if distance is None and any(e.led_z_mm is None for e in placed):
        first = next(e for e in placed if e.led_z_mm is None)
        raise ConfigError(f"{source}: {first.path.name} gives its LED's position but not its height above the "
                          "sample: set illumination.led_distance_m (or give each image led_z_mm)")
    images = []
    for entry in manifest.images:
        if entry.led_x_mm is not None:
            z = entry.led_z_mm if entry.led_z_mm is not None else distance * 1e3
            kx, ky = _led_sines(entry.led_x_mm, entry.led_y_mm, z, manifest.illumination.led_axis_m)
            entry = entry.model_copy(update={"kx_norm": kx, "ky_norm": ky})
        images.append(entry)
    return manifest.model_copy(update={"images": images})


def _led_sines(x_mm, y_mm, z_mm, axis_m) -> tuple:
    """sin θx, sin θy of an LED at ``(x, y)`` mm in its plane, ``z`` mm from the sample, the optical axis meeting
    the plane at ``axis_m`` (metres): ``sin θx = (x − x₀) / √((x − x₀)² + (y − y₀)² + z²)``."""
    x, y = np.subtract(x_mm, 1e3 * axis_m[0]), np.subtract(y_mm, 1e3 * axis_m[1])
    r = np.sqrt(x * x + y * y + np.square(z_mm))
    return x / r, y / r


def _led_grid_as_positions(manifest: Manifest, path: Path) -> Manifest:
    """An LED matrix given by grid indices: each image's LED position (mm) from ``illumination.led_pitch_m``.

    Positions are centred, as a stage grid's: the middle of the coherent rows' grid sits at 0.
    """
    illumination = manifest.illumination
    if illumination is None:
        return manifest
    indexed = [e for e in manifest.images if e.position_kind == "grid"]
    if not indexed:
        return manifest
    if illumination.led_pitch_m is None:
        raise ConfigError(f"{_source(manifest, path)}: {indexed[0].path.name} gives only grid indices [row, col]: "
                          "set illumination.led_pitch_m (the LEDs' spacing) and led_distance_m, or give each image "
                          "kx_norm/ky_norm")
    grid = np.array([e.grid for e in manifest.images if e.kind == "coherent" and e.grid is not None], np.float64)
    middle = (grid.max(axis=0) + grid.min(axis=0)) / 2.0 if grid.size else np.zeros(2)
    pitch_mm = illumination.led_pitch_m * 1e3
    images = [e.model_copy(update={"led_x_mm": (e.grid[1] - middle[1]) * pitch_mm,
                                   "led_y_mm": (e.grid[0] - middle[0]) * pitch_mm})
              if e.position_kind == "grid" else e for e in manifest.images]
    return manifest.model_copy(update={"images": images})


def _led_columns(header: list[str]) -> tuple[str, str, str | None] | None:
    """The LED x, y (and z) columns of a table, each with a length unit in its name (``led_x_mm``), or None."""
    found = [next((h for h in header if _plain_name(h) in {f"led_{axis}_{unit}" for unit in _POSITION_MM}), None)
             for axis in "xyz"]
    return None if found[0] is None or found[1] is None else (found[0], found[1], found[2])


def _mat_rows_with_sines(rows: list[dict], header: list[str], manifest: Manifest, table: Path,
                         path: Path) -> list[dict]:
    """An illumination table's rows with kx_norm, ky_norm worked out from its LED positions (as an image table's)."""
    x_col, y_col, z_col = _led_columns(header)
    distance = manifest.illumination.led_distance_m
    if z_col is None and distance is None:
        raise ConfigError(f"{path}: {table.name} gives LED positions ({x_col}, {y_col}) but not their height above "
                          "the sample: set illumination.led_distance_m (or give a led_z_mm column)")

    def mm(row: dict, column: str, line: int) -> float:
        try:
            return float(row[column]) * _POSITION_MM[_unit_of_name(column, _POSITION_MM)]
        except (TypeError, ValueError):
            raise InputError(f"{table}: row {line}: {column} is {row.get(column)!r}, not a number; fix the row") \
                from None

    out = []
    for line, row in enumerate(rows, start=1):
        z = mm(row, z_col, line) if z_col is not None else distance * 1e3
        kx, ky = _led_sines(mm(row, x_col, line), mm(row, y_col, line), z, manifest.illumination.led_axis_m)
        out.append({**row, "kx_norm": str(float(kx)), "ky_norm": str(float(ky))})
    return out


def _mat_plan(manifest: Manifest, path: Path) -> CapturePlan:
    table = manifest.source.illumination_csv
    header, numbered, _ = read_table(table, str(path))
    rows = [row for _, row in numbered]
    missing = [name for name in ("kx_norm", "ky_norm") if name not in header]
    if missing and _led_columns(header):
        rows = _mat_rows_with_sines(rows, header, manifest, table, path)
        header = [*header, "kx_norm", "ky_norm"]
        missing = []
    if missing:
        raise InputError(f"{table}: needs the columns kx_norm and ky_norm (sin θ of each LED's light; its columns: "
                         f"{', '.join(header) or 'none'}); from LED positions x, y and the LEDs' distance z, "
                         "kx_norm = x / √(x² + y² + z²)")
    try:
        kx = np.array([float(r["kx_norm"]) for r in rows])
        ky = np.array([float(r["ky_norm"]) for r in rows])
    except ValueError as exc:
        raise InputError(f"{table}: kx_norm and ky_norm must be numbers ({exc})") from None
    if not (np.isfinite(kx).all() and np.isfinite(ky).all()):
        bad = int(np.argmax(~(np.isfinite(kx) & np.isfinite(ky))))
        raise InputError(f"{manifest.source.illumination_csv}: row {bad + 1} has a NaN or infinite kx_norm/ky_norm; "
                         "fix the row")
    positions = np.stack([ky, kx], axis=1)
    labels = [f"image {i + 1} (kx {a:+.4f}, ky {b:+.4f})" for i, (a, b) in enumerate(zip(kx, ky))]
    grid = None
    if rows and "led_row_abs" in rows[0] and "led_col_abs" in rows[0]:
        grid = np.array([[int(r["led_row_abs"]), int(r["led_col_abs"])] for r in rows], np.int32)
        grid -= grid.min(axis=0)
    return CapturePlan(manifest, path, [[] for _ in rows], np.ones((len(rows), 1)), positions, grid, labels)


def _ptylab_plan(manifest: Manifest, path: Path, notes: list[str]) -> CapturePlan:
    """One position per image of a PtyLab file, at its LED's sines."""
    found = read_ptylab(manifest.source.ptylab)
    ky, kx = found.sines_yx[:, 0], found.sines_yx[:, 1]
    labels = [f"image {i + 1} (kx {a:+.4f}, ky {b:+.4f})" for i, (a, b) in enumerate(zip(kx, ky))]
    return CapturePlan(manifest, path, [[] for _ in labels], np.ones((len(labels), 1)), found.sines_yx.copy(), None,
                       labels, notes=list(notes))


def plan_captures(manifest: Manifest, path: str | Path, *, notes: list[str] | None = None) -> CapturePlan:
    """Group a manifest's images by kind and position and check the exposure brackets.

    Coherent rows are grouped by grid indices when the rows give them (a stage
    read-back that varies between exposures then does no harm), else by their
    position. Calibration rows are matched to the coherent positions the same
    way; dark and flat rows need no position.

    Raises
    ------
    ConfigError
        An exposure listed twice at one position, one image file listed for
        two positions or exposures (also under another name: a link to it),
        positions with different numbers of exposures, grid entries without
        ``stage_pitch_mm``, a calibration row without a coherent position (or
        the reverse), rows stating different bit depths, or no coherent rows.
    """
    path = Path(path)
    if manifest.source is not None and manifest.source.ptylab is not None:
        return _ptylab_plan(manifest, path, notes or [])
    if manifest.source is not None:
        return _mat_plan(manifest, path)
    manifest = _led_positions_as_sines(manifest, path)
    notes = list(notes or [])
    by_kind: dict[str, list[ImageEntry]] = {k: [] for k in KINDS}
    for entry in manifest.images:
        by_kind[entry.kind].append(entry)
    coherent = by_kind["coherent"]
    if not coherent:
        raise ConfigError(f"{path}: no coherent images listed (rows of kind coherent); list the captures")
    bit_depth = _stated_bit_depth(coherent + by_kind["dark"] + by_kind["flat"], manifest, path)

    kinds = {e.position_kind for e in coherent}
    if "led" in kinds and "stage" in kinds:
        raise ConfigError(f"{path}: images mix stage positions and illumination angles; use one kind for all images")
    kind = "led" if "led" in kinds else "stage" if "stage" in kinds else "grid"
    if kind != "grid" and "grid" in kinds and any(e.position_kind == "grid" for e in coherent):
        bad = next(e for e in coherent if e.position_kind == "grid")
        raise ConfigError(f"{path}: {bad.path.name} gives only grid indices while other rows give positions; "
                          "give every row a position")
    if kind == "led" and manifest.illumination is None:
        raise ConfigError(f"{path}: images give kx_norm/ky_norm (LED array) but the manifest has optics, not illumination")
    if kind != "led" and manifest.optics is None:
        raise ConfigError(f"{path}: images give stage positions but the manifest has no optics section")
    if kind == "grid" and manifest.stage_pitch_mm is None:
        raise ConfigError(f"{path}: stage_pitch_mm: needed when images give grid: [row, col]")

    if not any("exposure_s" in e.model_fields_set for e in coherent):
        notes.append("no image gives its exposure: each is taken as 1 s, so intensities are the recorded counts "
                     "(labelled counts/s); give exposure_s (or an exposure column) where exposures differ")
    groups: dict[tuple, list[ImageEntry]] = {}
    for entry in coherent:
        groups.setdefault(_key(entry), []).append(entry)
    files, exposures, positions, grid, labels = [], [], [], [], []
    n_exp = None
    for key, entries in groups.items():
        entries = sorted(entries, key=lambda e: e.exposure_s)
        times = [e.exposure_s for e in entries]
        where = _position_text(key)
        for first_entry, second in zip(entries[:-1], entries[1:]):
            if first_entry.exposure_s == second.exposure_s:
                stated = "exposure_s" in first_entry.model_fields_set or "exposure_s" in second.model_fields_set
                exposure = f"with exposure {_fmt(second.exposure_s)} s" if stated else "with no exposure time stated"
                if first_entry.path == second.path:
                    raise ConfigError(f"{_source(manifest, path)}: {second.path.name} is listed twice at {where} "
                                      f"{exposure}; remove one of the two")
                raise ConfigError(f"{_source(manifest, path)}: {first_entry.path.name} and {second.path.name} are both "
                                  f"at {where} {exposure}; each position takes one image per exposure: fix the "
                                  "position of one (or give their exposure times)")
        if n_exp is None:
            n_exp, first = len(times), where
        elif len(times) != n_exp:
            raise ConfigError(f"{path}: {where} has {len(times)} exposure(s) but {first} has {n_exp}; "
                              "list the same number of exposures at every position")
        files.append([e.path for e in entries])
        exposures.append(times)
        if key[0] == "grid":
            grid.append(key[1:])
        if kind == "stage":
            xy = np.array([[e.stage_y_mm, e.stage_x_mm] for e in entries])
            positions.append(xy.mean(axis=0) * 1e-3)
        elif kind == "led":
            positions.append(np.array([[e.ky_norm, e.kx_norm] for e in entries]).mean(axis=0))
        else:
            positions.append(np.asarray(key[1:], np.float64) * manifest.stage_pitch_mm * 1e-3)
        labels.append(f"{where} ({entries[0].path.name})")
    _check_distinct_files(groups, path)
    pos = np.asarray(positions, np.float64)
    grid_idx = None
    if grid:
        g = np.asarray(grid, np.int32)
        grid_idx = g - g.min(axis=0)
        if len({tuple(r) for r in grid_idx}) != len(grid_idx):
            raise ConfigError(f"{path}: two positions share grid indices; fix the row/col columns")
        if kind == "grid":
            centre = (g.max(axis=0) + g.min(axis=0)) / 2.0
            pos = (g - centre) * manifest.stage_pitch_mm * 1e-3
        else:
            _check_grouped_positions(groups, pos, path, kind)
            if kind == "stage":   # an LED board's sines are not linear in its indices (a flat board's bend outwards)
                _check_positions_follow_grid(groups, g, pos, path, kind)
    calibration = _match_calibration(by_kind["calibration"], list(groups), pos, kind, path, labels)
    darks = [(e.path, e.exposure_s) for e in by_kind["dark"]]
    flats = [(e.path, e.exposure_s) for e in by_kind["flat"]]
    if calibration is None and manifest.checkerboard is None and by_kind["calibration"]:
        notes.append(f"{path.name}: calibration rows given but no checkerboard section; they are not used")
    board_bits = {e.path: e.bit_depth for e in by_kind["calibration"] if e.bit_depth is not None}
    return CapturePlan(manifest, path, files, np.asarray(exposures, np.float64), pos, grid_idx, labels,
                       calibration=calibration, darks=darks, flats=flats, bit_depth=bit_depth,
                       calibration_bit_depths=board_bits, notes=notes,
                       camera_index=_cameras_checked(groups, by_kind["calibration"], kind, manifest, path, notes))


def _cameras_checked(groups: dict[tuple, list[ImageEntry]], calibration: list[ImageEntry], kind: str,
                     manifest: Manifest, path: Path, notes: list[str]) -> np.ndarray | None:
    """:func:`_camera_index`, a calibration row that names another camera than its position's images refused, and
    a camera that took the images of several positions named in a note (one pupil for them all)."""
    cameras = _camera_index(groups, kind, manifest, path)
    if cameras is None:
        return None
    at = {key: int(camera) for key, camera in zip(groups, cameras)}
    for row in calibration:
        key = _key(row)
        if row.camera is not None and key in at and row.camera != at[key]:
            raise ConfigError(f"{_source(manifest, path)}: calibration image {row.path.name} names camera {row.camera} "
                              f"but the images at {_position_text(key)} name camera {at[key]}; fix one of them")
    numbers, counts = np.unique(cameras, return_counts=True)
    for number in numbers[counts > 1]:
        where = [_position_text(key) for key, camera in at.items() if camera == number]
        notes.append(f"camera {int(number)} took the images at {len(where)} positions ({'; '.join(where[:3])}"
                     f"{'; …' if len(where) > 3 else ''}): they share one pupil; if they are different cameras, fix "
                     "the camera column")
    return cameras


def _camera_index(groups: dict[tuple, list[ImageEntry]], kind: str, manifest: Manifest,
                  path: Path) -> np.ndarray | None:
    """The camera of each position (in the groups' order), when the rows name cameras; None when none does.

    Raises
    ------
    ConfigError
        Some rows name a camera and others not, the rows of one position name different cameras, or an LED
        array's rows name cameras (it has one objective).
    """
    named = [e for entries in groups.values() for e in entries if e.camera is not None]
    if not named:
        return None
    source = _source(manifest, path)
    if kind == "led":
        raise ConfigError(f"{source}: {named[0].path.name} names a camera, but an LED array has one objective; "
                          "remove the camera column")
    unnamed = next((e for entries in groups.values() for e in entries if e.camera is None), None)
    if unnamed is not None:
        raise ConfigError(f"{source}: {unnamed.path.name} names no camera while {named[0].path.name} names camera "
                          f"{named[0].camera}; give every image its camera")
    cameras = []
    for key, entries in groups.items():
        numbers = sorted({e.camera for e in entries})
        if len(numbers) > 1:
            raise ConfigError(f"{source}: the images at {_position_text(key)} name cameras "
                              f"{', '.join(map(str, numbers))}; one position is one camera's")
        cameras.append(numbers[0])
    return np.asarray(cameras, np.int32)


def _stated_bit_depth(entries: list[ImageEntry], manifest: Manifest, path: Path) -> int | None:
    """The one bit depth the capture, dark and flat rows state (calibration rows may state their own).

    Raises
    ------
    ConfigError
        Two depths stated, or one that contradicts ``sensor.bit_depth``.
    """
    bits = sorted({e.bit_depth for e in entries if e.bit_depth is not None})
    if len(bits) > 1:
        first = next(e for e in entries if e.bit_depth == bits[0])
        other = next(e for e in entries if e.bit_depth == bits[1])
        raise ConfigError(f"{path}: rows state bit depths {bits[0]} ({first.path.name}) and {bits[1]} "
                          f"({other.path.name}); the captures, darks and flats of a set must have the same bit "
                          "depth (calibration views may have their own)")
    bit_depth = bits[0] if bits else None
    if bit_depth is not None and manifest.sensor.bit_depth is not None and bit_depth != manifest.sensor.bit_depth:
        first = next(e for e in entries if e.bit_depth == bit_depth)
        raise ConfigError(f"{path}: the rows state bit depth {bit_depth} ({first.path.name}) but sensor.bit_depth is "
                          f"{manifest.sensor.bit_depth}; make them agree")
    return bit_depth


def _file_identity(path: Path) -> tuple:
    """What makes two paths one file: device and inode (links included), else the resolved path."""
    try:
        stat = os.stat(path)
    except OSError:  # missing or unreadable: reading it later says so
        return ("path", os.path.realpath(path))
    return ("inode", stat.st_dev, stat.st_ino)


def _check_distinct_files(groups: dict, path: Path) -> None:
    """Every coherent row must name its own image: one file at two positions or exposures is a copy-paste slip."""
    seen: dict[tuple, tuple[tuple, ImageEntry]] = {}
    for key, entries in groups.items():
        for entry in entries:
            identity = _file_identity(entry.path)
            if identity not in seen:
                seen[identity] = (key, entry)
                continue
            first_key, first = seen[identity]
            same = (f"the same file {entry.path.name}" if first.path.name == entry.path.name
                    else f"{entry.path.name}, the same file as {first.path.name}")
            if first._origin is not None and entry._origin is not None:   # rows of a table: name its lines
                table, lines = first._origin[0], sorted((first._origin[1], entry._origin[1]))
                raise ConfigError(f"{path}: lines {lines[0]} and {lines[1]} of {table} both name {same}; each "
                                  "position and exposure needs its own image: fix the path of one of the rows")
            if first_key == key:
                raise ConfigError(f"{path}: {_position_text(key)} lists {same} for exposures "
                                  f"{_fmt(first.exposure_s)} s and {_fmt(entry.exposure_s)} s; each exposure needs "
                                  "its own image")
            raise ConfigError(f"{path}: {_position_text(first_key)} and {_position_text(key)} both name {same}; "
                              "each position needs its own image: fix the path of one of the rows")


def _check_grouped_positions(groups: dict, pos: np.ndarray, path: Path, kind: str) -> None:
    """Rows grouped by grid index must agree on their position (within a quarter of the smallest step)."""
    if len(pos) < 2:
        return
    dist = np.hypot(*(pos[:, None, :] - pos[None, :, :]).transpose(2, 0, 1))
    step = float(dist[dist > 0].min()) if (dist > 0).any() else 0.0
    scale = 1e-3 if kind == "stage" else 1.0
    for (key, entries), centre in zip(groups.items(), pos):
        offsets = [np.hypot(((e.stage_y_mm if kind == "stage" else e.ky_norm) * scale - centre[0]),
                            ((e.stage_x_mm if kind == "stage" else e.kx_norm) * scale - centre[1])) for e in entries]
        if step > 0 and max(offsets) > 0.25 * step:
            lines = [e._origin for e in entries if e._origin is not None]
            if len(lines) == len(entries) == 2:   # rows of a table: by their lines
                where = f"; lines {lines[0][1]} and {lines[1][1]} of {lines[0][0]} disagree"
            elif len(lines) == len(entries):   # the one farthest from the others
                at = _odd_one_out(entries, kind)
                where = f"; line {entries[at]._origin[1]} of {entries[at]._origin[0]} differs from the others"
            else:
                where = ""
            raise ConfigError(f"{path}: rows at {_position_text(key)} give positions that differ by more than a "
                              f"quarter of the grid step{where}; fix the positions or the grid indices")


def _odd_one_out(entries: list[ImageEntry], kind: str) -> int:
    """Index of the row whose position lies farthest from the median of its group's."""
    xy = np.array([[e.stage_y_mm, e.stage_x_mm] if kind == "stage" else [e.ky_norm, e.kx_norm] for e in entries],
                  np.float64)
    return int(np.argmax(np.hypot(*(xy - np.median(xy, axis=0)).T)))


#: A position given with grid indices may lie this share of the grid step from where the other positions put
#: its row and column (a stage's repeatability, a camera mounted a little off).
GRID_TOLERANCE = 0.5


def _check_positions_follow_grid(groups: dict, grid: np.ndarray, pos: np.ndarray, path: Path, kind: str) -> None:
    """Positions given with grid indices must lie on one lattice: a slipped digit in one position is refused.

    The lattice's step along each index is the median difference between neighbours in the grid, and its origin
    the median of what each position implies, so one wrong position cannot move it.
    """
    grid = np.asarray(grid, np.int64)
    index = {tuple(row): i for i, row in enumerate(grid)}
    steps = []
    for unit in ((1, 0), (0, 1)):
        differences = [pos[index[(r + unit[0], c + unit[1])]] - pos[i] for i, (r, c) in enumerate(grid)
                       if (r + unit[0], c + unit[1]) in index]
        if not differences:
            return
        steps.append(np.median(differences, axis=0))
    lattice = np.asarray(steps)                       # position change per row, per column
    origin = np.median(pos - grid @ lattice, axis=0)
    expected = origin + grid @ lattice
    step = float(min(np.hypot(*lattice[0]), np.hypot(*lattice[1])))
    if not step > 0:
        return
    off = np.hypot(*(pos - expected).T)
    worst = int(np.argmax(off))
    if off[worst] <= GRID_TOLERANCE * step:
        return
    key, entries = list(groups.items())[worst]
    origin_of = entries[0]._origin
    where = f" (line {origin_of[1]} of {origin_of[0]})" if origin_of is not None else ""
    if kind == "stage":
        (y, x), (ey, ex) = pos[worst] * 1e3, expected[worst] * 1e3
        given, near = f"x {x:.4g}, y {y:.4g} mm", f"x {ex:.4g}, y {ey:.4g} mm"
    else:
        (y, x), (ey, ex) = pos[worst], expected[worst]
        given, near = f"kx {x:.4g}, ky {y:.4g}", f"kx {ex:.4g}, ky {ey:.4g}"
    raise ConfigError(f"{path}: {_position_text(key)}{where} is at {given}, {off[worst] / step:.3g} grid steps from "
                      f"where the other positions put that row and col ({near}); fix that position (a slipped "
                      "digit?) or its grid indices")


def _match_calibration(rows: list[ImageEntry], keys: list[tuple], positions: np.ndarray, kind: str, path: Path,
                       labels: list[str]) -> list[list[tuple[Path, float]]] | None:
    """Calibration (board) images of each coherent position, matched by grid index or nearest position."""
    if not rows:
        return None
    views: list[list[tuple[Path, float]]] = [[] for _ in keys]
    index = {key: i for i, key in enumerate(keys)}
    dist = np.hypot(*(positions[:, None, :] - positions[None, :, :]).transpose(2, 0, 1))
    step = float(dist[dist > 0].min()) if (dist > 0).any() else 1.0
    for row in rows:
        key = _key(row)
        if key in index:
            views[index[key]].append((row.path, row.exposure_s))
            continue
        if row.position_kind in (None, "grid"):
            raise ConfigError(f"{path}: calibration image {row.path.name} is at {_position_text(key)}, where no "
                              "coherent image was taken; fix its position")
        if kind == "stage":
            where = np.array([row.stage_y_mm, row.stage_x_mm]) * 1e-3
        else:
            where = np.array([row.ky_norm, row.kx_norm])
        gap = np.hypot(*(positions - where).T)
        nearest = int(np.argmin(gap))
        if gap[nearest] > 0.25 * step:
            raise ConfigError(f"{path}: calibration image {row.path.name} is at {_position_text(key)}, where no "
                              "coherent image was taken; fix its position")
        views[nearest].append((row.path, row.exposure_s))
    missing = [labels[i] for i, v in enumerate(views) if not v]
    if missing:
        raise ConfigError(f"{path}: {missing[0]} has no calibration image ({len(missing)} position(s) lack one); "
                          "photograph the board at every position, or remove the calibration rows")
    return views
