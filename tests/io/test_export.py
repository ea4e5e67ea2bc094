"""`cca export` and cca_cli.io.export: full-resolution float32 TIFF, 16-bit PNG and .npy with the pixel size."""

from __future__ import annotations

import json

import h5py
import numpy as np
import OpenImageIO as oiio
import pytest
import tifffile
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app
from cca_cli.io import export as export_module
from cca_cli.io.export import read_exported

runner = CliRunner()


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    """A recon.h5 holding a random complex object (no engine run needed)."""
    rng = np.random.default_rng(3)
    geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
                               pixel_pitch_m=2e-6, distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    obj = (rng.random((64, 64)) * np.exp(2j * np.pi * rng.random((64, 64)))).astype(np.complex64)
    result = cca.Reconstruction(object=obj, spectrum=np.fft.fft2(obj).astype(np.complex64),
                                history={k: np.zeros(2) for k in ("residual", "change", "seconds")},
                                geometry=geometry, engine="altmin", options={"tol": 0.0}, seconds=0.0,
                                stopped_by="cap", band_grid_px=32)
    return cca.save(result, tmp_path_factory.mktemp("export") / "recon.h5")


def _h5(recon, quantity):
    with h5py.File(recon) as handle:
        obj = handle["/recon/object"][()]
        pixel = float(handle["recon"].attrs["pixel_pitch_object_m"])
        if quantity == "intensity":
            return handle["/recon/intensity"][()], pixel
    return (np.abs(obj) if quantity == "amplitude" else np.angle(obj)).astype(np.float32), pixel


def _oiio(path):
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    data = inp.read_image(0, 0, 0, 1, spec.format)
    attrs = {a.name: a.value for a in spec.extra_attribs}
    inp.close()
    return np.asarray(data).reshape(spec.height, spec.width), spec, attrs


@pytest.mark.parametrize("quantity", ["amplitude", "intensity", "phase"])
def test_tiff_read_back_equals_the_hdf5_data(recon, tmp_path, quantity):
    result = runner.invoke(app, ["export", str(recon), "-o", str(tmp_path / "out.tif"), "--quantity", quantity])
    assert result.exit_code == 0, result.output
    data, spec, attrs = _oiio(tmp_path / "out.tif")
    expected, pixel = _h5(recon, quantity)
    assert str(spec.format) == "float" and data.shape == expected.shape == (64, 64)
    assert np.array_equal(data, expected)
    assert attrs["ResolutionUnit"] == "cm"
    assert attrs["XResolution"] == pytest.approx(0.01 / pixel, rel=1e-6)
    meta = json.loads(attrs["ImageDescription"])
    assert meta["pixel_size_m"] == pixel and meta["quantity"] == quantity


@pytest.mark.parametrize("quantity", ["amplitude", "phase"])
def test_tiff_reads_with_plain_tifffile_with_its_pixel_size(recon, tmp_path, quantity):
    # Deflate with the floating-point predictor needs imagecodecs (and ImageJ cannot read it): stored uncompressed.
    path = cca.export(recon, tmp_path / "out.tif", quantity=quantity)
    expected, pixel = _h5(recon, quantity)
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert page.compression == tifffile.COMPRESSION.NONE and page.predictor == tifffile.PREDICTOR.NONE
        assert not page.is_tiled  # ImageJ opens strips, not tiles
        values = page.asarray()
        tags = page.tags
        x_num, x_den = tags["XResolution"].value
        y_num, y_den = tags["YResolution"].value
        unit = tags["ResolutionUnit"].value
        meta = json.loads(page.description)
    assert values.dtype == np.float32 and np.array_equal(values, expected)
    assert unit == tifffile.RESUNIT.CENTIMETER
    assert 0.01 * x_den / x_num == pytest.approx(pixel, rel=1e-6)
    assert 0.01 * y_den / y_num == pytest.approx(pixel, rel=1e-6)
    assert meta["pixel_size_m"] == pixel and meta["quantity"] == quantity


@pytest.mark.parametrize("kind, name", [("tiff", "x.dat"), ("png", "x.img"), ("npy", "x"), ("tiff", "x.jpg")])
def test_format_option_works_with_any_suffix(recon, tmp_path, kind, name):
    path = tmp_path / name
    result = runner.invoke(app, ["export", str(recon), "-o", str(path), "--format", kind])
    assert result.exit_code == 0, result.output
    assert export_module.file_format(path) == kind
    back = read_exported(path)
    expected, pixel = _h5(recon, "amplitude")
    assert np.allclose(back.values, expected, atol=2 * expected.max() / 65535)
    assert back.pixel_size_m == (None if kind == "npy" else pixel)
    if kind != "npy":  # cca recognises its own file whatever the suffix, so --force replaces it
        again = runner.invoke(app, ["export", str(recon), "-o", str(path), "--format", kind, "--quantity", "phase",
                                    "--force"])
        assert again.exit_code == 0, again.output
        assert read_exported(path).quantity == "phase"


def test_png_is_16_bit_with_its_scale_and_pixel_size(recon, tmp_path):
    path = cca.export(recon, tmp_path / "phase.png", quantity="phase")
    codes, spec, attrs = _oiio(path)
    expected, pixel = _h5(recon, "phase")
    assert str(spec.format) == "uint16" and codes.max() == 65535
    offset, scale = float(attrs["cca:offset"]), float(attrs["cca:scale"])
    assert offset == pytest.approx(-np.pi) and float(attrs["cca:pixel_size_m"]) == pixel
    assert np.max(np.abs(offset + scale * codes - expected)) <= scale / 2 + 1e-7
    back = read_exported(path)
    assert back.pixel_size_m == pixel and back.quantity == "phase" and back.units == "rad"
    assert np.allclose(back.values, expected, atol=scale)
    # the pHYs chunk holds the same pixel size (OpenImageIO reports it per inch)
    assert 0.0254 / attrs["XResolution"] == pytest.approx(pixel, rel=1e-3)


def test_png_text_chunks_are_latin_1_as_the_format_says(recon, tmp_path):
    import struct

    path = cca.export(recon, tmp_path / "amplitude.png", quantity="amplitude")
    data, chunks, at = path.read_bytes(), {}, 8
    while at < len(data):
        length, kind = struct.unpack(">I4s", data[at:at + 8])
        if kind == b"tEXt":
            key, _, value = data[at + 8:at + 8 + length].partition(b"\0")
            chunks[key.decode("latin-1")] = value.decode("latin-1")
        at += 12 + length
    units = read_exported(path).units          # the exact units, from the JSON description
    assert "√" in units and chunks["cca:units"] == units.replace("√(", "sqrt(").replace("√irradiance",
                                                                                         "sqrt(irradiance)")
    assert chunks["cca:units"].isascii()


def test_npy_and_arrays_and_results(recon, tmp_path):
    cca.export(recon, tmp_path / "a.npy", quantity="intensity")
    assert np.array_equal(np.load(tmp_path / "a.npy"), _h5(recon, "intensity")[0])
    loaded = cca.load(recon)
    cca.export(loaded, tmp_path / "b.tif")
    assert np.array_equal(read_exported(tmp_path / "b.tif").values, _h5(recon, "amplitude")[0])
    with pytest.raises(ValueError, match="pixel_size_m"):
        cca.export(np.ones((4, 4)), tmp_path / "c.tif")


def test_existing_output_is_refused_and_kept_unless_forced(recon, tmp_path):
    foreign = tmp_path / "out.tif"
    foreign.write_bytes(b"mine")
    for extra in ([], ["--force"]):  # a file cca did not write is never replaced
        result = runner.invoke(app, ["export", str(recon), "-o", str(foreign), *extra])
        assert result.exit_code == 4 and ("already exists" in result.output or "cca did not write it" in result.output)
        assert foreign.read_bytes() == b"mine"
    ours = tmp_path / "ours.tif"
    assert runner.invoke(app, ["export", str(recon), "-o", str(ours)]).exit_code == 0
    refused = runner.invoke(app, ["export", str(recon), "-o", str(ours), "--quantity", "phase"])
    assert refused.exit_code == 4 and "--force" in refused.output
    assert runner.invoke(app, ["export", str(recon), "-o", str(ours), "--quantity", "phase", "--force"]).exit_code == 0
    assert read_exported(ours).values.shape == (64, 64) and read_exported(ours).quantity == "phase"


@pytest.mark.parametrize("kind", ["npy", "tiff"])
def test_the_recovery_itself_is_never_the_output_even_forced(recon, tmp_path, kind):
    copy = tmp_path / "recon.h5"
    copy.write_bytes(recon.read_bytes())
    for extra in ([], ["--force"]):
        result = runner.invoke(app, ["export", str(copy), "-o", str(copy), "--format", kind, *extra])
        assert result.exit_code == 4 and "is the input" in result.output
        assert copy.read_bytes() == recon.read_bytes()


@pytest.mark.parametrize("args, code, needle", [
    (["-o", "{tmp}/x.jpg"], 2, "unknown image format '.jpg'"),
    (["-o", "{tmp}/x.tif", "--quantity", "real"], 2, "choose one of amplitude, intensity, phase"),
    (["-o", "{tmp}/x.tif", "--format", "png"], 2, "make them agree"),
])
def test_bad_arguments_are_one_line_errors(recon, tmp_path, args, code, needle):
    result = runner.invoke(app, ["export", str(recon)] + [a.format(tmp=tmp_path) for a in args])
    assert result.exit_code == code
    text = " ".join(result.output.split())
    assert "error:" in text and needle in text
    assert list(tmp_path.iterdir()) == []


def test_a_file_that_is_not_a_recovery_is_refused(tmp_path):
    geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
                               pixel_pitch_m=2e-6, distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    captures = cca.save(cca.CaptureSet(np.ones((9, 64, 64), np.float32), geometry), tmp_path / "captures.h5")
    result = runner.invoke(app, ["export", str(captures), "-o", str(tmp_path / "x.tif")])
    assert result.exit_code == 3 and "expected 'reconstruct'" in result.output
    assert not (tmp_path / "x.tif").exists()


def test_a_failed_write_leaves_nothing_behind(recon, tmp_path, monkeypatch):
    def broken(tmp, *args):
        tmp.write_bytes(b"half a file")
        raise OSError("disk full")

    monkeypatch.setattr(export_module, "_write_oiio", broken)
    with pytest.raises(OSError):
        cca.export(recon, tmp_path / "x.tif")
    assert list(tmp_path.iterdir()) == []
