"""Every dataset of every HDF5 file the pipeline writes carries `units` and `description`."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from cca_cli.config.load import apply_overrides, load_config, parse_config
from cca_cli.config.model import SweepSection
from cca_cli.stages.runner import run_pipeline
from cca_cli.stages.sweep import TABLE_COLUMNS, read_table, write_table

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "data_samples" / "sample_capture"


def _undescribed(path: Path) -> list[str]:
    missing = []

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            for key in ("units", "description"):
                value = obj.attrs.get(key)
                if value is None or (key == "description" and not str(value).strip()):
                    missing.append(f"{path.name}:/{name} lacks {key}")

    with h5py.File(path, "r") as handle:
        handle.visititems(visit)
    return missing


def _datasets(path: Path) -> set[str]:
    names = set()
    with h5py.File(path, "r") as handle:
        handle.visititems(lambda name, obj: names.add("/" + name) if isinstance(obj, h5py.Dataset) else None)
    return names


@pytest.fixture(scope="module")
def simulated(tiny_run_config, tmp_path_factory):
    """captures.h5 and recon.h5 of the tiny chart, of a tiny USAF scene and of a tiny multiplexed design."""
    out = tmp_path_factory.mktemp("described")
    files = []
    runs = {
        "chart": {"reconstruct.iterations": 2},
        "usaf": {"reconstruct.iterations": 2, "scene.kind": "usaf", "scene.size_px": 192,
                 "scene.usaf_groups": [1, 2, 3]},
    }
    for name, overrides in runs.items():
        config = apply_overrides(tiny_run_config, {**overrides, "run.stages": ["simulate", "reconstruct"]})
        run_pipeline(config, out / name)
        files += [out / name / "captures.h5", out / name / "recon.h5"]
    mux = parse_config({
        "run": {"stages": ["simulate", "reconstruct"]}, "optics": {"aperture_diameter_m": 25e-3},
        "scene": {"kind": "resolution_chart", "size_px": 64, "field_width_m": 8e-3, "widths_px": [4, 2]},
        "reconstruct": {"iterations": 2, "tol": 0.0},
        "multiplex": {"camera_grid": [2, 2], "source_grid": [2, 2], "source_overlap": 0.66, "n_mux": 2, "patterns": 1},
    }, source="mux")
    run_pipeline(mux, out / "mux")
    return files + [out / "mux" / "captures.h5", out / "mux" / "recon.h5"]


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """raw.h5, hdr.h5, registered.h5 and recon.h5 of the shipped sample capture set (centre 3 x 3 positions)."""
    out = tmp_path_factory.mktemp("captured")
    manifest = yaml.safe_load((SAMPLE / "manifest.yaml").read_text())
    keep = {f"r{r}c{c}" for r in (1, 2, 3) for c in (1, 2, 3)}
    manifest["images"] = [dict(entry, path=str(SAMPLE / entry["path"])) for entry in manifest["images"]
                          if entry["path"].split("_")[1] in keep]
    (out / "manifest.yaml").write_text(yaml.safe_dump(manifest))
    config = load_config(ROOT / "configs" / "sample_capture.yaml")
    config = apply_overrides(config, {"ingest.manifest": str(out / "manifest.yaml"), "reconstruct.iterations": 2,
                                      "run.stages": ["ingest", "hdr", "register", "reconstruct"]})
    run_pipeline(config, out / "run")
    return [out / "run" / name for name in ("raw.h5", "hdr.h5", "registered.h5", "recon.h5")]


def _rows():
    """Sweep table rows as run_sweep makes them: one point failed (metrics missing)."""
    base = {"status": "ok", "error": "", "wall_s": 1.5, "out_dir": "points/x", "sar": 2.56, "grid_n": 5,
            "n_images": 25, "iterations": 30, "recon_seconds": 0.4, "mtf20_observed_px": 6, "mtf20_recovered_px": 2,
            "resolution_gain": 3.0, "rmse_observed": 0.2, "rmse_recovered": 0.05, "rmse_observed_band": 0.1,
            "rmse_recovered_band": 0.01}
    rows = []
    for index, overlap in enumerate((0.5, 0.61)):
        rows.append({"point_id": f"p{index}", "index": index, **base, "param:array.overlap": overlap,
                     "param:noise.seed": 10 + index, "param:optics.distance_m": 50.0})
    rows[1].update(status="failed", error="boom", mtf20_observed_px=None, mtf20_recovered_px=None, sar=None)
    return rows


def test_simulated_and_reconstructed_files_describe_every_dataset(simulated):
    missing = [m for path in simulated for m in _undescribed(path)]
    assert missing == []
    names = set().union(*(_datasets(p) for p in simulated))
    assert {"/truth/usaf", "/truth/bars", "/multiplex/virtual_group", "/recon/object"} <= names


def test_recorded_capture_files_describe_every_dataset(captured):
    missing = [m for path in captured for m in _undescribed(path)]
    assert missing == []
    raw, _, registered, recon = captured
    assert "/capture/labels" in _datasets(raw) and "/registration/dropped" in _datasets(registered)
    with h5py.File(recon) as handle:
        # the copies carried into recon.h5 for the report keep their meaning
        assert handle["/registration/rms_px"].attrs["units"] == "px"
        assert handle["/hdr/dynamic_range_gain"].attrs["units"] == "1"
        assert handle["/observed/centre"].attrs["units"] == "counts/s"
        assert handle["/recon/object"].attrs["units"] == "√(counts/s)"


def test_api_files_describe_every_dataset(tmp_path):
    import cca_cli as cca

    geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
                               pixel_pitch_m=2e-6, distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    images = cca.simulate(np.random.default_rng(0).random((64, 64)), geometry, snr_db=None)
    captures = cca.save(cca.CaptureSet(images, geometry), tmp_path / "captures.h5")
    result = cca.reconstruct(cca.load(captures), iterations=2)
    recon = cca.save(result, tmp_path / "recon.h5")
    assert _undescribed(captures) == [] and _undescribed(recon) == []


def test_sweep_table_describes_every_column_and_keeps_integers(tmp_path, tiny_run_config):
    rows = _rows()
    _, h5_path = write_table(rows, tmp_path, spec=SweepSection(parameters={"array.overlap": [0.5, 0.61]}),
                             base=tiny_run_config)
    assert _undescribed(h5_path) == []
    with h5py.File(h5_path) as handle:
        table = handle["table"]
        for name in ("index", "grid_n", "n_images", "iterations", "mtf20_observed_px", "noise.seed"):
            assert table[name].dtype == np.int64, name
        assert table["mtf20_recovered_px"].attrs["missing_value"] == -1
        assert table["sar"].dtype == np.float64 and np.isnan(table["sar"][1])
        assert table["array.overlap"].attrs["units"] == "1"
        assert table["optics.distance_m"].attrs["units"] == "m"
        assert table["wall_s"].attrs["units"] == "s"
        assert table["mtf20_recovered_px"].attrs["units"] == "px"
        assert table["point_id"].attrs["units"] == "text"
    back = read_table(h5_path)
    assert [r["mtf20_recovered_px"] for r in back] == [2, None]
    assert [r["grid_n"] for r in back] == [5, 5] and isinstance(back[0]["grid_n"], int)
    assert back[1]["sar"] is None and back[0]["noise.seed"] == 10
    assert {c for c in rows[0] if not c.startswith("param:")} <= set(TABLE_COLUMNS)


def test_report_of_recorded_captures_speaks_counts_per_second(captured, tmp_path):
    from cca_cli.config.model import ReportSection
    from cca_cli.io.h5 import Provenance
    from cca_cli.stages import report

    summary = report.run(captured[-1], ReportSection(figures=False), tmp_path / "report",
                         provenance=Provenance.make("report", "", ""))
    assert summary["intensity_units"] == "counts/s"
    assert summary["zoom_region"]["label"] == "most detail beyond the single-camera band"
    assert summary["stopped_by"] == "cap" and summary["registration_rms_px_max"] < 1.0
