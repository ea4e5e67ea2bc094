"""A sensor's hot pixels and dead lines: found in every capture, filled from their neighbours at ingest."""

from __future__ import annotations

import numpy as np
import yaml
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app
from cca_cli.io.captures import read_captures
from cca_cli.io.images import write_image
from cca_cli.library.defects import dead_lines, fill_pixels, hot_pixels

runner = CliRunner()
OPTICS = dict(wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=0.9e-6)
SINES = cca.led_grid_sines(9, pitch_m=4e-3, height_m=60e-3)
RNG = np.random.default_rng(5)


def _captures():
    geometry = cca.led_array(SINES, image_pixels=64, **OPTICS)
    images = cca.simulate(cca.resolution_chart(128, widths=(6, 4, 3, 2)).image, geometry, snr_db=40, seed=2)
    bright = np.hypot(*geometry.spectrum_centres_yx_px.T) < 0.9 * geometry.pupil_radius_px
    return np.asarray(images, np.float32), geometry, bright


HOT = [(5, 40), (30, 12), (50, 50)]


def _with_defects(images):
    """Three hot pixels: a fixed excess in every capture."""
    spoilt = images.copy()
    for y, x in HOT:
        spoilt[:, y, x] += 0.05 * images.max()
    return spoilt


def test_hot_pixels_are_found_and_a_chart_s_own_bars_are_not():
    images, _, _ = _captures()
    assert not hot_pixels(images).any()            # bars, edges and noise: the object's, not the sensor's
    assert sorted(map(tuple, np.argwhere(hot_pixels(_with_defects(images))).tolist())) == HOT


DEAD_COLUMN, STUCK_ROW = 21, 14


def test_dead_lines_are_found_and_a_chart_s_own_bars_are_not():
    images, _, _ = _captures()
    assert not dead_lines(images).any()            # vertical and horizontal bars: the object's lines
    dead = images.copy()
    dead[:, :, DEAD_COLUMN] = RNG.normal(0, 1e-3 * images.max(), dead[:, :, DEAD_COLUMN].shape)   # noise only
    stuck = images.copy()
    stuck[:, STUCK_ROW, :] = 0.2 * images.max()    # a row stuck at a fifth of the peak
    for spoilt, line in ((dead, np.s_[:, DEAD_COLUMN]), (stuck, np.s_[STUCK_ROW, :])):
        expected = np.zeros(images.shape[1:], bool)
        expected[line] = True
        assert np.array_equal(dead_lines(spoilt), expected)
    pair = images.copy()
    pair[:, :, DEAD_COLUMN:DEAD_COLUMN + 2] = 0     # two dead columns side by side: each has a dead neighbour
    expected = np.zeros(images.shape[1:], bool)
    expected[:, DEAD_COLUMN:DEAD_COLUMN + 2] = True
    assert np.array_equal(dead_lines(pair), expected)
    dark = images.copy()
    dark[:, :, :20] = 0                             # a dark, featureless band: its lines follow nothing, judged not
    assert not dead_lines(dark).any()
    flat = RNG.poisson(1000.0, (25, 64, 64)).astype(np.float32)   # a flat field: lines follow nothing
    assert not dead_lines(flat).any()


def test_a_filled_pixel_reads_as_its_neighbours_do():
    images, _, _ = _captures()
    spoilt = _with_defects(images)
    mask = hot_pixels(spoilt)
    fill_pixels(spoilt, mask)
    # each filled pixel is far nearer the clean image than the hot one was (its excess: 5% of the peak)
    error = max(float(np.abs(spoilt[:, y, x] - images[:, y, x]).mean()) for y, x in HOT) / images.max()
    assert error < 0.01, error
    assert np.array_equal(spoilt[:, ~mask], images[:, ~mask])     # every other pixel as it was


def test_ingest_fills_the_sensor_s_defects_and_says_so(tmp_path):
    images, _, _ = _captures()
    spoilt = _with_defects(images)
    spoilt[:, :, DEAD_COLUMN] = 0                      # a dead column: the black level in every file
    scale = 30000 / float(spoilt.max())
    rows = []
    for k, (ky, kx) in enumerate(SINES):
        codes = np.clip(np.rint(spoilt[k] * scale) + 100, 0, 65535).astype(np.uint16)
        write_image(tmp_path / f"led{k}.png", codes, bit_depth=16)
        rows.append({"path": f"led{k}.png", "exposure_s": 0.01, "kx_norm": float(kx), "ky_norm": float(ky)})
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump({"illumination": OPTICS, "sensor": {"black_level": 100},
                                                       "images": rows}))
    result = runner.invoke(app, ["ingest", str(tmp_path / "lab.yaml"), "-o", str(tmp_path / "raw.h5"), "-q"])
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())
    assert "3 pixel(s) stand far above their neighbours by the same amount in every capture" in said
    assert "hot pixels of the sensor; each now reads the mean of its good neighbours" in said
    assert f"column x {DEAD_COLUMN} does not follow its neighbours over the bright captures: a dead or stuck line" in said
    intensity = np.asarray(read_captures(tmp_path / "raw.h5").intensity)
    clean = images * scale / 0.01                     # the files' counts per second without the hot pixels
    for y, x in HOT:   # far nearer the clean image than the hot pixel (5% of the peak above it)
        error = np.abs(intensity[:, y, x] - clean[:, y, x]).mean() / clean.max()
        assert error < 0.01, error
    bright = clean.mean(axis=(1, 2)) > 0.1 * clean.mean(axis=(1, 2)).max()
    column = intensity[bright][:, :, DEAD_COLUMN]      # reads as the clean image would, where it had read nothing
    # (it had read nothing: an error of 100%; the chart's 1–2 px bars are what the neighbours cannot tell)
    assert np.abs(column - clean[bright][:, :, DEAD_COLUMN]).mean() < 0.25 * clean[bright][:, :, DEAD_COLUMN].mean()
