"""Real LED-array data sets of the real-data benchmark: manifests, ingest through `cca ingest`, peer inputs.

Every method sees the same frames after the same preprocessing: the data go
through ``cca ingest`` (dark level subtracted, values read as amplitudes or
intensities as the manifest says) and the ingested ``/measurements/intensity``
is what the peers get too.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SHARED = ROOT.parent / "shared" / "datasets"
if not SHARED.is_dir():  # a worktree one level deeper than the main checkout
    SHARED = Path("/work/shared/datasets")


@dataclass(frozen=True)
class DatasetSpec:
    """How one real set enters the benchmark."""

    name: str
    manifest: Path                  # the manifest a user writes from the dataset README
    readme: Path
    peer_hires: int                 # object grid M of the peers (PtyLab No, fpm-rs reconstruction shape)
    analysis_grid: int              # grid every amplitude is resampled to for images and the bar reading
    values: str | None = None       # override the manifest's `values` (amplitude / intensity reading)
    usaf: bool = False              # read the README's three-bar table


DATASETS = {
    "usaf_aidukas32": DatasetSpec(
        "usaf_aidukas32", ROOT / "configs/usaf_aidukas32_manifest.yaml",
        SHARED / "fpm-usaf-aidukas32/README.md", peer_hires=128, analysis_grid=256, usaf=True),
    "bloodsmear_green_amplitude": DatasetSpec(
        "bloodsmear_green_amplitude", ROOT / "configs/bloodsmear_green_manifest.yaml",
        SHARED / "fpm-zheng-bloodsmear/README.md", peer_hires=512, analysis_grid=512, values="amplitude"),
    "bloodsmear_green_intensity": DatasetSpec(
        "bloodsmear_green_intensity", ROOT / "configs/bloodsmear_green_manifest.yaml",
        SHARED / "fpm-zheng-bloodsmear/README.md", peer_hires=512, analysis_grid=512, values="intensity"),
}


@dataclass
class Prepared:
    """One data set after `cca ingest`, ready for every method."""

    spec: DatasetSpec
    raw_h5: Path
    manifest_used: Path
    manifest_note: str
    intensity: np.ndarray           # (K, n, n) float32, what every method fits
    centres: np.ndarray             # (K, 2) pupil centres, spectrum px relative to DC (cca convention)
    radius: float
    wavelength: float
    field_width: float
    numerical_aperture: float
    illumination_na: np.ndarray     # (K,) |sin θ|
    centre_index: int
    peer_data: Path                 # npz for the peer workers

    @property
    def windows(self) -> np.ndarray:
        """Whole-pixel window centres (what the peers get)."""
        return np.rint(self.centres).astype(np.int64)

    @property
    def bright_field(self) -> np.ndarray:
        """Illumination NA below the objective NA."""
        return self.illumination_na < self.numerical_aperture


def cca_command() -> list[str]:
    """The `cca` console script of the current interpreter."""
    exe = Path(sys.executable).with_name("cca")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "cca_cli"]


def tool_environment(**extra: str) -> dict[str, str]:
    """The environment the real-data benchmarks run each timed tool in: this one, with Python's bytecode caches allowed.

    A shell that sets ``PYTHONDONTWRITEBYTECODE`` makes each run compile the sources it imports again
    (about 0.2 s for cca's own modules), which no installed copy of a tool pays.
    """
    env = dict(os.environ, **extra)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def run_cca(args: list[str], *, log: Path | None = None) -> subprocess.CompletedProcess:
    """Run one `cca` command; raise with its last error line on failure."""
    proc = subprocess.run(cca_command() + args, capture_output=True, text=True, cwd=ROOT,
                          env=tool_environment(COLUMNS="200"))
    if log is not None:
        log.write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        lines = [line for line in (proc.stderr + proc.stdout).splitlines() if line.strip()]
        raise RuntimeError(f"cca {' '.join(args[:1])} failed: {lines[-1] if lines else proc.returncode}")
    return proc


def _manifest_accepted(path: Path) -> tuple[bool, str]:
    from cca_cli.errors import CcaError
    from cca_cli.io.manifest import load_manifest

    try:
        load_manifest(path)
    except CcaError as exc:
        return False, str(exc)
    return True, ""


def usable_manifest(spec: DatasetSpec, workdir: Path) -> tuple[Path, str]:
    """The manifest to ingest: the shipped one, or a run-time copy the current reader accepts.

    A copy is written (under ``workdir``, never in the repository) when the
    benchmark reads the blood smear with another ``values`` than the shipped
    manifest, or when the current manifest reader refuses the data set's extra
    CSV columns: then the CSV is filtered to ``path,kx_norm,ky_norm`` with
    absolute paths.
    """
    data = yaml.safe_load(spec.manifest.read_text())
    notes = []
    changed = False
    if spec.values is not None and data.get("values", "intensity") != spec.values:
        data["values"] = spec.values
        notes.append(f"values: {spec.values} (shipped manifest: {yaml.safe_load(spec.manifest.read_text()).get('values')})")
        changed = True
    for section, key in (("source", "mat"), ("source", "illumination_csv")):
        if section in data and key in data[section]:
            data[section][key] = str((spec.manifest.parent / data[section][key]).resolve())
    if "images_csv" in data:
        table = (spec.manifest.parent / data["images_csv"]).resolve()
        data["images_csv"] = str(table)
        ok, why = _manifest_accepted(spec.manifest)
        if not ok:
            rows = list(csv.DictReader(open(table, newline="")))
            filtered = workdir / f"{spec.name}_images.csv"
            with open(filtered, "w", newline="") as handle:
                writer = csv.writer(handle)
                writer.writerow(["path", "kx_norm", "ky_norm"])
                for row in rows:
                    writer.writerow([str((table.parent / row["path"]).resolve()), row["kx_norm"], row["ky_norm"]])
            data["images_csv"] = str(filtered)
            notes.append(f"the manifest reader refused {spec.manifest.name} ({why}); ingested a run-time copy "
                         f"of its CSV with only path,kx_norm,ky_norm (absolute paths)")
            changed = True
    if not changed:
        return spec.manifest, "shipped manifest"
    out = workdir / f"{spec.name}_manifest.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out, "; ".join(notes)


def prepare(spec: DatasetSpec, workdir: Path, *, reuse_ingest: bool = False) -> Prepared:
    """Ingest one set with `cca ingest` and write the peers' input file.

    With ``reuse_ingest`` a set whose source files are no longer there (a
    dataset folder removed since) is read from the ``raw.h5`` an earlier run
    ingested into ``workdir``, with a note saying so.
    """
    workdir = workdir.resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    raw = workdir / "raw.h5"
    try:
        manifest, note = usable_manifest(spec, workdir)
        run_cca(["ingest", str(manifest), "-o", str(raw), "--force"], log=workdir / "ingest.log")
    except (FileNotFoundError, RuntimeError) as missing:
        if not (reuse_ingest and raw.is_file()):
            raise
        manifest, note = spec.manifest, f"source files missing ({missing}); read the earlier ingest {raw}"
    with h5py.File(raw, "r") as handle:
        intensity = np.asarray(handle["/measurements/intensity"], np.float32)
        g = handle["geometry"]
        centres = np.asarray(g["spectrum_centres_yx_px"], np.float64)
        sin_yx = np.asarray(g["aperture_centres_yx_m"], np.float64)  # sign · sin θ for LED arrays
        attrs = dict(g.attrs)
    prepared = Prepared(
        spec=spec, raw_h5=raw, manifest_used=manifest, manifest_note=note, intensity=intensity, centres=centres,
        radius=float(attrs["pupil_radius_px"]), wavelength=float(attrs["wavelength_m"]),
        field_width=float(attrs["field_width_m"]), numerical_aperture=float(attrs["numerical_aperture"]),
        illumination_na=np.hypot(sin_yx[:, 0], sin_yx[:, 1]), centre_index=int(attrs["centre_index"]),
        peer_data=workdir / "peer_data.npz")
    np.savez(prepared.peer_data, images=intensity, windows=prepared.windows, radius=prepared.radius,
             wavelength=prepared.wavelength, field_width=prepared.field_width, hires=spec.peer_hires)
    return prepared
