"""HDF5 plumbing: atomic writes, no silent overwrite, provenance, checked reads."""

import json

import h5py
import numpy as np
import pytest

from cca_cli.errors import InputError, OutputExistsError
from cca_cli.io.geometry import read_geometry, write_geometry
from cca_cli.io.h5 import (
    Provenance,
    atomic_h5,
    atomic_path,
    check_output,
    file_sha256,
    open_input,
    read_provenance,
    require,
    write_dataset,
)
from cca_cli.io.schema import DATASETS, SCHEMA_VERSION, spec_for
from cca_cli.sampling.geometry import camera_scan_geometry

PROVENANCE_KEYS = {"cca_schema", "stage", "cca_version", "created_utc", "config", "config_hash", "inputs"}


def _provenance(stage="simulate", inputs=()):
    return Provenance.make(stage, "optics: {}\n", "abc123", list(inputs))


def _write_ok(path, value=1.0, **kwargs):
    with atomic_h5(path, _provenance(), **kwargs) as handle:
        write_dataset(handle, "/measurements/intensity", np.full((2, 4, 4), value, np.float32))


def _siblings(path):
    return sorted(p.name for p in path.parent.iterdir())


def test_atomic_h5_writes_provenance_and_units(tmp_path):
    path = tmp_path / "captures.h5"
    _write_ok(path)
    assert _siblings(path) == ["captures.h5"]
    with h5py.File(path, "r") as handle:
        assert PROVENANCE_KEYS <= set(handle.attrs)
        assert handle.attrs["cca_schema"] == SCHEMA_VERSION
        dataset = handle["/measurements/intensity"]
        assert dataset.attrs["units"] == spec_for("/measurements/intensity").units
        assert "description" in dataset.attrs
    assert read_provenance(path)["stage"] == "simulate"


def test_writer_that_raises_leaves_no_file_and_no_temp_file(tmp_path):
    path = tmp_path / "captures.h5"
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_h5(path, _provenance()) as handle:
            write_dataset(handle, "/measurements/intensity", np.ones((2, 4, 4), np.float32))
            raise RuntimeError("boom")
    assert _siblings(path) == []


def test_writer_that_raises_keeps_the_previous_file(tmp_path):
    path = tmp_path / "captures.h5"
    _write_ok(path)
    before = path.read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with atomic_h5(path, _provenance(), force=True) as handle:
            write_dataset(handle, "/measurements/intensity", np.zeros((2, 4, 4), np.float32))
            raise KeyboardInterrupt
    assert path.read_bytes() == before
    assert _siblings(path) == ["captures.h5"]


def test_atomic_path_cleans_up_a_temporary_directory(tmp_path):
    target = tmp_path / "report"
    with pytest.raises(ValueError):
        with atomic_path(target) as tmp:
            tmp.mkdir()
            (tmp / "a.json").write_text("{}")
            raise ValueError
    assert list(tmp_path.iterdir()) == []
    with atomic_path(target) as tmp:
        tmp.mkdir()
        (tmp / "a.json").write_text("{}")
    assert (target / "a.json").is_file() and _siblings(target) == ["report"]


def test_existing_output_without_force_is_refused_and_untouched(tmp_path):
    path = tmp_path / "captures.h5"
    _write_ok(path)
    before = path.read_bytes()
    with pytest.raises(OutputExistsError, match="--force") as excinfo:
        _write_ok(path, 2.0)
    assert str(path) in str(excinfo.value)
    assert path.read_bytes() == before
    with pytest.raises(OutputExistsError):
        check_output(path, force=False)
    check_output(path, force=True)
    _write_ok(path, 2.0, force=True)
    with h5py.File(path, "r") as handle:
        assert np.all(handle["/measurements/intensity"][()] == 2.0)


def test_open_input_errors(tmp_path):
    with pytest.raises(InputError, match="not found") as excinfo:
        open_input(tmp_path / "missing.h5")
    assert "missing.h5" in str(excinfo.value)
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(InputError, match="not an HDF5 file"):
        open_input(text)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as handle:
        handle["x"] = np.zeros(3)
    with pytest.raises(InputError, match="not a cca file"):
        open_input(foreign)
    good = tmp_path / "captures.h5"
    _write_ok(good)
    with pytest.raises(InputError, match="expected 'reconstruct'"):
        open_input(good, stage="reconstruct")
    with open_input(good, stage="simulate") as handle:
        assert require(handle, "/measurements/intensity", ndim=3).shape == (2, 4, 4)
        with pytest.raises(InputError, match="missing dataset /recon/object"):
            require(handle, "/recon/object")
        with pytest.raises(InputError, match="expected 2 dimensions"):
            require(handle, "/measurements/intensity", ndim=2)


def test_provenance_hashes_inputs_and_rejects_missing_ones(tmp_path):
    source = tmp_path / "in.bin"
    source.write_bytes(b"abc")
    provenance = _provenance("reconstruct", [source])
    inputs = json.loads(provenance["inputs"])
    assert inputs == [{"path": str(source), "sha256": file_sha256(source)}]
    assert file_sha256(source) == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    with pytest.raises(InputError, match="input file not found"):
        _provenance("reconstruct", [tmp_path / "gone.h5"])


def test_geometry_round_trip(tmp_path):
    geometry, _ = camera_scan_geometry(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
                                       pixel_pitch_m=2e-6, distance_m=50.0, field_width_m=12e-3, grid=3,
                                       overlap=0.5)
    path = tmp_path / "g.h5"
    with atomic_h5(path, _provenance()) as handle:
        write_geometry(handle, geometry)
    with open_input(path) as handle:
        back = read_geometry(handle)
        assert handle["geometry"].attrs["synthetic_aperture_ratio"] == pytest.approx(2.0)
        assert handle["/geometry/aperture_centres_yx_m"].attrs["units"] == "m"
    for name in ("wavelength_m", "focal_length_m", "aperture_diameter_m", "pixel_pitch_m", "distance_m",
                 "field_width_m", "pupil_radius_px", "overlap"):
        assert getattr(back, name) == pytest.approx(getattr(geometry, name), rel=1e-15)
    np.testing.assert_array_equal(back.spectrum_centres_yx_px, geometry.spectrum_centres_yx_px)
    np.testing.assert_array_equal(back.grid_indices, geometry.grid_indices)
    empty = tmp_path / "empty.h5"
    with atomic_h5(empty, _provenance()):
        pass
    with open_input(empty) as handle, pytest.raises(InputError, match="no /geometry"):
        read_geometry(handle)


def test_schema_names_units_for_every_dataset():
    paths = [spec.path for spec in DATASETS]
    assert len(paths) == len(set(paths))
    # Numbers carry a unit ("1" for dimensionless); only text datasets may leave it empty.
    assert [s.path for s in DATASETS if s.units == "" and not s.dtype.startswith(("str", "bytes", "S", "U"))] == []
    assert spec_for("/nope") is None
