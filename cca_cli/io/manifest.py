"""Capture manifests: which image files were recorded where, with which exposure and optics.

A manifest is a YAML file (or a CSV table of images with a YAML sidecar of
the same stem) validated here with one-line errors that name the manifest
and the key. See the README section "Real captures" for the format.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, PositiveInt, ValidationError, model_validator

from cca_cli.config.messages import accepted_keys, error_message
from cca_cli.config.yaml_text import read_yaml_file
from cca_cli.errors import ConfigError, InputError, short

__all__ = ["Manifest", "ImageEntry", "CapturePlan", "load_manifest", "plan_captures", "manifest_files"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class OpticsSpec(_Strict):
    """Camera-scan optics (SI)."""

    wavelength_m: PositiveFloat
    focal_length_m: PositiveFloat
    aperture_diameter_m: PositiveFloat
    pixel_pitch_m: PositiveFloat
    distance_m: PositiveFloat


class IlluminationSpec(_Strict):
    """LED-array (angle-scan) microscope."""

    wavelength_m: PositiveFloat
    numerical_aperture: float = Field(..., gt=0, lt=1)
    pixel_pitch_object_m: PositiveFloat
    sign: Literal[-1, 1] = Field(-1, description="Pupil at sign·sinθ·W/λ (−1: Zheng's reference convention).")


class SensorSpec(_Strict):
    """Raw-value conversion."""

    black_level: float = Field(0.0, ge=0)
    bit_depth: PositiveInt | None = None
    white_level: PositiveFloat | None = None


class CheckerboardSpec(_Strict):
    """The registration board beside the object."""

    pattern: tuple[PositiveInt, PositiveInt]
    square_m: PositiveFloat | None = None


class SourceSpec(_Strict):
    """Images stored in one MATLAB file (already merged, one image per illumination)."""

    mat: Path
    variable: str = "imlow_HDR"
    illumination_csv: Path


class ImageEntry(_Strict):
    """One image: where it was taken, its exposure and its file."""

    path: Path
    exposure_s: PositiveFloat = 1.0
    stage_x_mm: float | None = None
    stage_y_mm: float | None = None
    grid: tuple[int, int] | None = None
    kx_norm: float | None = Field(None, ge=-1, le=1)
    ky_norm: float | None = Field(None, ge=-1, le=1)

    @model_validator(mode="after")
    def _one_position(self):
        stage = self.stage_x_mm is not None or self.stage_y_mm is not None
        led = self.kx_norm is not None or self.ky_norm is not None
        if sum((stage, led, self.grid is not None)) != 1:
            raise ValueError("give exactly one position: stage_x_mm/stage_y_mm, grid, or kx_norm/ky_norm")
        if stage and (self.stage_x_mm is None or self.stage_y_mm is None):
            raise ValueError("give both stage_x_mm and stage_y_mm")
        if led and (self.kx_norm is None or self.ky_norm is None):
            raise ValueError("give both kx_norm and ky_norm")
        return self


class Manifest(_Strict):
    """A capture manifest."""

    optics: OpticsSpec | None = None
    illumination: IlluminationSpec | None = None
    sensor: SensorSpec = SensorSpec()
    checkerboard: CheckerboardSpec | None = None
    stage_pitch_mm: PositiveFloat | None = None
    values: Literal["intensity", "amplitude"] = "intensity"
    images: list[ImageEntry] | None = None
    images_csv: Path | None = None
    source: SourceSpec | None = None

    @model_validator(mode="after")
    def _consistent(self):
        if (self.optics is None) == (self.illumination is None):
            raise ValueError("give exactly one of optics (camera scan) or illumination (LED array)")
        if sum(x is not None for x in (self.images, self.images_csv, self.source)) != 1:
            raise ValueError("give exactly one of images, images_csv or source")
        if self.source is not None and self.illumination is None:
            raise ValueError("source (a .mat of LED-array images) needs an illumination section")
        return self


@dataclass(frozen=True)
class CapturePlan:
    """The images of a manifest grouped by position, exposures ascending.

    Attributes
    ----------
    manifest : Manifest
    path : Path
        The manifest file.
    files : list of list of Path
        ``files[k][e]``: image of position k, exposure e (empty for a .mat source).
    exposure_s : ndarray, (K, E)
    positions : ndarray, (K, 2)
        Stage [y, x] in metres (camera scan) or [sin θy, sin θx] (LED array).
    grid_indices : ndarray, (K, 2) or None
        Given grid indices (grid entries), else None.
    labels : list of str
        One readable name per position (used in errors and the report).
    """

    manifest: Manifest
    path: Path
    files: list[list[Path]]
    exposure_s: np.ndarray
    positions: np.ndarray
    grid_indices: np.ndarray | None
    labels: list[str]

    @property
    def kind(self) -> str:
        """``camera_scan`` or ``led_array``."""
        return "camera_scan" if self.manifest.optics is not None else "led_array"


def _describe(error: dict, source: str) -> str:
    loc = ".".join(str(p) for p in error["loc"]) or "(top level)"
    if error["type"] == "extra_forbidden":
        keys = ", ".join(accepted_keys(Manifest, error["loc"])) or "see the README"
        return f"{source}: {loc}: unknown key; accepted keys here: {keys}"
    value = error.get("input")
    suffix = f" (got {short(value)})" if not isinstance(value, dict) else ""
    return f"{source}: {loc}: {error_message(error)}{suffix}"


def _first_error(exc: ValidationError) -> dict:
    """A misspelled key explains a missing one, so report unknown keys first."""
    errors = exc.errors()
    return next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])


def _read_yaml(path: Path) -> dict:
    data = read_yaml_file(path, what="manifest")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a capture manifest: the top level must be a mapping (optics, sensor, images …)")
    if data and not set(map(str, data)) & set(Manifest.model_fields):
        raise ConfigError(f"{path}: not a capture manifest: none of its top-level keys is a manifest key "
                          f"({', '.join(Manifest.model_fields)})")
    return data


def _read_csv_rows(path: Path, source: str) -> list[dict]:
    try:
        with open(path, newline="") as handle:
            rows = list(csv.DictReader(handle))
    except FileNotFoundError:
        raise InputError(f"{path}: image table not found (named by {source})") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read image table ({exc})") from None
    out = []
    for row in rows:
        entry = {k.strip(): v.strip() for k, v in row.items() if k is not None and v not in (None, "")}
        if "row" in entry or "col" in entry:
            entry["grid"] = [entry.pop("row", None), entry.pop("col", None)]
        out.append(entry)
    return out


def load_manifest(path: str | Path) -> Manifest:
    """Read and validate a manifest (YAML, or CSV with a sidecar ``<stem>.yaml``).

    Relative paths inside the manifest are resolved against its directory.

    Raises
    ------
    ConfigError
        A key is unknown or a value is invalid: one line naming the file and key.
    InputError
        The manifest (or its table) cannot be read.
    """
    path = Path(path)
    if path.suffix.lower() == ".csv":
        sidecar = path.with_suffix(".yaml")
        if not path.is_file():
            raise InputError(f"{path}: manifest not found; check the path")
        if not sidecar.is_file():
            raise InputError(f"{path}: a CSV manifest needs the optics in {sidecar.name} next to it; write that YAML file")
        data = _read_yaml(sidecar)
        if any(k in data for k in ("images", "images_csv", "source")):
            raise ConfigError(f"{sidecar}: a CSV manifest's sidecar must not list images; remove images/images_csv/source")
        data["images_csv"] = str(path.resolve())
        source = str(sidecar)
    else:
        data = _read_yaml(path)
        source = str(path)
    try:
        manifest = Manifest.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_describe(_first_error(exc), source)) from None
    base = path.parent
    if manifest.images_csv is not None:
        table = _resolve(base, manifest.images_csv)
        try:
            entries = [ImageEntry.model_validate(r) for r in _read_csv_rows(table, source)]
        except ValidationError as exc:
            err = _first_error(exc)
            raise ConfigError(f"{table}: {'.'.join(str(p) for p in err['loc'])}: {error_message(err)}") from None
        manifest = manifest.model_copy(update={"images": entries, "images_csv": table})
    if manifest.images is not None:
        manifest = manifest.model_copy(update={"images": [e.model_copy(update={"path": _resolve(base, e.path)})
                                                          for e in manifest.images]})
    if manifest.source is not None:
        manifest = manifest.model_copy(update={"source": manifest.source.model_copy(update={
            "mat": _resolve(base, manifest.source.mat),
            "illumination_csv": _resolve(base, manifest.source.illumination_csv)})})
    if manifest.images is not None and not manifest.images:
        raise ConfigError(f"{source}: images: the list is empty; list at least one image")
    return manifest


def _resolve(base: Path, p: Path) -> Path:
    p = Path(p).expanduser()
    return p if p.is_absolute() else base / p


def manifest_files(path: str | Path) -> list[Path]:
    """The manifest and every file it names (for provenance hashing)."""
    path = Path(path)
    manifest = load_manifest(path)
    files = [path]
    if path.suffix.lower() == ".csv":
        files.append(path.with_suffix(".yaml"))
    if manifest.images is not None:
        files += [e.path for e in manifest.images]
    if manifest.source is not None:
        files += [manifest.source.mat, manifest.source.illumination_csv]
    return files


def _fmt(v: float) -> str:
    return f"{v:g}"


def plan_captures(manifest: Manifest, path: str | Path) -> CapturePlan:
    """Group a manifest's images by position and check the exposure brackets.

    Raises
    ------
    ConfigError
        An exposure listed twice at one position, positions with different
        numbers of exposures, or grid entries without ``stage_pitch_mm``.
    """
    path = Path(path)
    if manifest.source is not None:
        rows = _read_csv_rows(manifest.source.illumination_csv, str(path))
        try:
            kx = np.array([float(r["kx_norm"]) for r in rows])
            ky = np.array([float(r["ky_norm"]) for r in rows])
        except (KeyError, ValueError) as exc:
            raise InputError(f"{manifest.source.illumination_csv}: needs numeric columns kx_norm and ky_norm ({exc})") from None
        positions = np.stack([ky, kx], axis=1)
        labels = [f"image {i + 1} (kx {a:+.4f}, ky {b:+.4f})" for i, (a, b) in enumerate(zip(kx, ky))]
        grid = None
        if rows and "led_row_abs" in rows[0] and "led_col_abs" in rows[0]:
            grid = np.array([[int(r["led_row_abs"]), int(r["led_col_abs"])] for r in rows], np.int32)
            grid -= grid.min(axis=0)
        return CapturePlan(manifest, path, [[] for _ in rows], np.ones((len(rows), 1)), positions, grid, labels)

    groups: dict[tuple, list[ImageEntry]] = {}
    for entry in manifest.images:
        if entry.stage_x_mm is not None:
            key = ("stage", entry.stage_y_mm, entry.stage_x_mm)
        elif entry.grid is not None:
            key = ("grid", *entry.grid)
        else:
            key = ("led", entry.ky_norm, entry.kx_norm)
        groups.setdefault(key, []).append(entry)
    kinds = {k[0] for k in groups}
    if len(kinds) > 1:
        raise ConfigError(f"{path}: images mix position kinds ({', '.join(sorted(kinds))}); use one kind for all images")
    kind = kinds.pop()
    if kind == "led" and manifest.illumination is None:
        raise ConfigError(f"{path}: images give kx_norm/ky_norm (LED array) but the manifest has optics, not illumination")
    if kind != "led" and manifest.optics is None:
        raise ConfigError(f"{path}: images give stage positions but the manifest has no optics section")
    if kind == "grid" and manifest.stage_pitch_mm is None:
        raise ConfigError(f"{path}: stage_pitch_mm: needed when images give grid: [row, col]")

    files, exposures, positions, grid, labels = [], [], [], [], []
    n_exp = None
    for key, entries in groups.items():
        entries = sorted(entries, key=lambda e: e.exposure_s)
        times = [e.exposure_s for e in entries]
        where = _position_text(key)
        for a, b in zip(times[:-1], times[1:]):
            if a == b:
                raise ConfigError(f"{path}: exposure {_fmt(a)} s listed twice at {where}")
        if n_exp is None:
            n_exp, first = len(times), where
        elif len(times) != n_exp:
            raise ConfigError(f"{path}: {where} has {len(times)} exposure(s) but {first} has {n_exp}; "
                              "list the same number of exposures at every position")
        files.append([e.path for e in entries])
        exposures.append(times)
        if kind == "stage":
            positions.append((key[1] * 1e-3, key[2] * 1e-3))
        elif kind == "grid":
            grid.append((key[1], key[2]))
            positions.append((key[1] * manifest.stage_pitch_mm * 1e-3, key[2] * manifest.stage_pitch_mm * 1e-3))
        else:
            positions.append((key[1], key[2]))
        labels.append(f"{where} ({entries[0].path.name})")
    pos = np.asarray(positions, np.float64)
    grid_idx = None
    if kind == "grid":
        g = np.asarray(grid, np.int32)
        grid_idx = g - g.min(axis=0)
        centre = (g.max(axis=0) + g.min(axis=0)) / 2.0
        pos = (g - centre) * manifest.stage_pitch_mm * 1e-3
    return CapturePlan(manifest, path, files, np.asarray(exposures, np.float64), pos, grid_idx, labels)


def _position_text(key: tuple) -> str:
    if key[0] == "stage":
        return f"position (x {_fmt(key[2])}, y {_fmt(key[1])}) mm"
    if key[0] == "grid":
        return f"grid position (row {key[1]}, col {key[2]})"
    return f"illumination (kx {_fmt(key[2])}, ky {_fmt(key[1])})"
