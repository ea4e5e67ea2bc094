"""PtyLab's FPM datasets ingested as they are: `cca ingest data.hdf5`, or a manifest's `source: {ptylab: …}`."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app
from cca_cli.io.captures import read_captures

runner = CliRunner()
WAVELENGTH, NA, PIXEL, MAGNIFICATION, ZLED = 532e-9, 0.1, 1.845e-6, 4.0, 60e-3


@pytest.fixture(scope="module")
def simulated():
    sines = cca.led_grid_sines(5, pitch_m=4e-3, height_m=ZLED, axis_m=(1e-3, 0.0))
    geometry = cca.led_array(sines, wavelength_m=WAVELENGTH, numerical_aperture=NA, pixel_pitch_object_m=PIXEL,
                             image_pixels=32)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, geometry, snr_db=None)
    return sines, geometry, np.asarray(images, np.float32)


def _write(path, sines, images, *, na=True, matlab=False):
    """A PtyLab FPM file: LED positions [y, x] in their plane at ZLED, the camera's pixel and magnification."""
    encoder = sines * ZLED / np.sqrt(1 - np.sum(sines ** 2, axis=1, keepdims=True))
    with h5py.File(path, "w") as f:
        f["ptychogram"] = np.moveaxis(images, 0, -1) if matlab else images
        f["encoder"] = encoder.T if matlab else encoder
        f["zled"], f["wavelength"], f["dxd"], f["magnification"] = ZLED, WAVELENGTH, PIXEL * MAGNIFICATION, MAGNIFICATION
        if na:
            f["NA"] = NA
    return path


def _ingest(source, out):
    return runner.invoke(app, ["ingest", str(source), "-o", str(out), "-q"])


def test_a_ptylab_file_ingests_as_the_led_array_it_describes_and_reconstructs(tmp_path, simulated):
    sines, geometry, images = simulated
    result = _ingest(_write(tmp_path / "fpm.hdf5", sines, images), tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    captures = read_captures(tmp_path / "raw.h5")
    assert np.allclose(captures.geometry.spectrum_centres_yx_px, geometry.spectrum_centres_yx_px, atol=1e-9)
    assert captures.geometry.pupil_radius_px == pytest.approx(geometry.pupil_radius_px)
    assert np.array_equal(np.asarray(captures.intensity), images)
    assert captures.geometry.led_distance_m == pytest.approx(ZLED)
    result = runner.invoke(app, ["reconstruct", str(tmp_path / "raw.h5"), "-o", str(tmp_path / "recon.h5"),
                                 "--iterations", "3", "-q"])
    assert result.exit_code == 0, result.output


def test_a_matlab_ordered_ptylab_file_is_read_as_ptylab_reads_it(tmp_path, simulated):
    sines, geometry, images = simulated
    result = _ingest(_write(tmp_path / "fpm.h5", sines, images, matlab=True), tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert "read transposed and centred on its mean" in " ".join(result.output.split())
    captures = read_captures(tmp_path / "raw.h5")
    assert np.array_equal(np.asarray(captures.intensity), images)
    # the positions centred on their mean, as PtyLab does: the 1 mm axis offset is gone
    centred = cca.led_array(cca.led_grid_sines(5, pitch_m=4e-3, height_m=ZLED), wavelength_m=WAVELENGTH,
                            numerical_aperture=NA, pixel_pitch_object_m=PIXEL, image_pixels=32)
    assert np.allclose(captures.geometry.spectrum_centres_yx_px, centred.spectrum_centres_yx_px, atol=1e-9)


def test_a_ptylab_file_without_na_takes_it_from_a_manifest(tmp_path, simulated):
    sines, geometry, images = simulated
    data = _write(tmp_path / "fpm.hdf5", sines, images, na=False)
    result = _ingest(data, tmp_path / "raw.h5")
    assert result.exit_code != 0
    said = " ".join(result.output.split())
    assert "fpm.hdf5: has no NA" in said and "illumination: {numerical_aperture: …}" in said
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"source": {"ptylab": "fpm.hdf5"},
                                                       "illumination": {"numerical_aperture": NA}}))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code == 0, result.output
    assert read_captures(tmp_path / "raw.h5").geometry.pupil_radius_px == pytest.approx(geometry.pupil_radius_px)


def test_an_hdf5_file_that_is_not_an_fpm_dataset_is_refused_in_one_line(tmp_path, simulated):
    sines, _, images = simulated
    with h5py.File(tmp_path / "partial.hdf5", "w") as f:
        f["ptychogram"] = images
        f["wavelength"] = WAVELENGTH
    result = _ingest(tmp_path / "partial.hdf5", tmp_path / "raw.h5")
    assert result.exit_code != 0
    said = " ".join(result.output.split())
    assert "partial.hdf5: not a PtyLab FPM dataset: it lacks encoder, zled, dxd, magnification" in said
    _write(tmp_path / "fpm.hdf5", sines, images)
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"source": {"ptylab": "fpm.hdf5", "illumination_csv": "t.csv"}}))
    result = _ingest(tmp_path / "lab.yaml", tmp_path / "raw.h5")
    assert result.exit_code != 0 and "remove illumination_csv" in " ".join(result.output.split())
