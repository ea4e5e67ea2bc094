"""What an LED array's images tell at ingest that its manifest got wrong: a board off its optical axis (from the
bright-field images' pupil circles), and a camera offset left in (from the dark-field images)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app
from cca_cli.io.images import write_image
from cca_cli.library.axis import OFF_AXIS, axis_offset

runner = CliRunner()
PITCH_M, HEIGHT_M, GRID = 4e-3, 60e-3, 9
OPTICS = dict(wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=0.9e-6)


def _board(axis_m=(0.0, 0.0), image_pixels=64):
    """Images of a resolution chart under a 9 x 9 LED board whose optical axis meets it at ``axis_m`` [x, y]
    from its middle, and the geometry that takes the axis at the middle."""
    true = cca.led_array(cca.led_grid_sines(GRID, pitch_m=PITCH_M, height_m=HEIGHT_M, axis_m=axis_m),
                         image_pixels=image_pixels, **OPTICS)
    nominal = cca.led_array(cca.led_grid_sines(GRID, pitch_m=PITCH_M, height_m=HEIGHT_M), image_pixels=image_pixels,
                            **OPTICS)
    widths = (6, 4, 3, 2) if image_pixels >= 64 else (4, 3, 2)
    images = cca.simulate(cca.resolution_chart(2 * image_pixels, widths=widths).image, true, snr_db=40, seed=1)
    return images, true, nominal


def test_the_pupil_circles_give_the_shift_of_every_led():
    images, true, nominal = _board(axis_m=(-PITCH_M / 2, 0.0))           # the axis half an LED off the middle
    found = axis_offset(images, nominal.spectrum_centres_yx_px, nominal.pupil_radius_px)
    radius = nominal.pupil_radius_px
    near = np.hypot(*nominal.spectrum_centres_yx_px.T) < 0.8 * radius          # the bright-field LEDs read
    expected = np.mean(true.spectrum_centres_yx_px[near] - nominal.spectrum_centres_yx_px[near], axis=0)
    assert np.hypot(*expected) > 0.3 * radius
    assert np.hypot(*(found.shift_yx_px - expected)) < 0.1 * radius
    assert found.off_axis and found.gain > 2 and found.images == 5
    # the positions as they are: nothing to report
    right = axis_offset(images, true.spectrum_centres_yx_px, true.pupil_radius_px)
    assert right.radii < OFF_AXIS / 3 and not right.off_axis


def test_the_circles_are_not_read_where_they_cannot_be():
    images, _, nominal = _board(image_pixels=32)       # pupil radius 5.4 px in 32: its edges within the band
    assert axis_offset(images, nominal.spectrum_centres_yx_px, nominal.pupil_radius_px) is not None
    wide = nominal.pupil_radius_px * 1.6                 # over a quarter of the frame: the edges wrap round
    assert axis_offset(images, nominal.spectrum_centres_yx_px, wide) is None
    far = nominal.spectrum_centres_yx_px + 3 * nominal.pupil_radius_px      # no capture in the bright field
    assert axis_offset(images, far, nominal.pupil_radius_px) is None
    with pytest.raises(ValueError, match="one per centre"):
        axis_offset(images[:3], nominal.spectrum_centres_yx_px, nominal.pupil_radius_px)


def _lab(tmp_path, images, *, axis_m=None, sines=None, offset=0.0, sensor=None):
    """The images as 16-bit PNGs (``offset`` counts added) with a manifest listing the LEDs by [row, col] (or by
    their ``sines``)."""
    scale = 30000 / float(images.max())
    rows = []
    for k in range(len(images)):
        codes = images[k] * scale + offset
        write_image(tmp_path / f"led{k}.png", np.clip(np.rint(codes), 0, 65535).astype(np.uint16), bit_depth=16)
        row = {"path": f"led{k}.png", "exposure_s": 0.01}
        if sines is None:
            row["grid"] = [int(k // GRID), int(k % GRID)]
        else:
            row.update(kx_norm=float(sines[k, 1]), ky_norm=float(sines[k, 0]))
        rows.append(row)
    illumination = dict(OPTICS)
    if sines is None:
        illumination.update(led_pitch_m=PITCH_M, led_distance_m=HEIGHT_M)
    if axis_m is not None:
        illumination["led_axis_m"] = list(axis_m)
    manifest = {"illumination": illumination, "images": rows, **({"sensor": sensor} if sensor else {})}
    (tmp_path / "lab.yaml").write_text(yaml.safe_dump(manifest))
    result = runner.invoke(app, ["ingest", str(tmp_path / "lab.yaml"), "-o", str(tmp_path / "raw.h5"), "-q", "--force"])
    assert result.exit_code == 0, result.output
    return " ".join(result.output.split())


def test_ingest_names_an_off_axis_board_and_the_led_axis_that_puts_it_right(tmp_path):
    images, _, _ = _board(axis_m=(-PITCH_M / 2, 0.0))
    said = _lab(tmp_path, images)
    assert "warning:" in said and "the bright-field images put the optical axis" in said
    assert "did its LED fire?" not in said       # the captures that look unlit are the board's doing
    told = said.split("Set illumination.led_axis_m: [")[1].split("]")[0]
    x, y = (float(v) for v in told.split(","))
    assert x == pytest.approx(-PITCH_M / 2, rel=0.2) and abs(y) < 0.05 * PITCH_M   # 64-px images: about 0.4 px
    assert "the bright-field images put" not in _lab(tmp_path, images, axis_m=(x, y))   # as told: nothing to say
    assert "the bright-field images put" not in _lab(tmp_path, _board()[0])             # a board on its axis


def test_a_table_of_sines_off_the_axis_is_told_what_to_add(tmp_path):
    images, true, _ = _board(axis_m=(0.0, PITCH_M / 2))
    listed = cca.led_grid_sines(GRID, pitch_m=PITCH_M, height_m=HEIGHT_M)
    said = _lab(tmp_path, images, sines=listed)
    add = said.split("Add [")[1].split("]")[0]
    kx, ky = (float(v) for v in add.split(","))
    lacking = (cca.led_grid_sines(GRID, pitch_m=PITCH_M, height_m=HEIGHT_M, axis_m=(0.0, PITCH_M / 2))
               - listed)[GRID * GRID // 2]                                       # [sin θy, sin θx] at the axis
    assert ky == pytest.approx(lacking[0], rel=0.2) and abs(kx) < 0.1 * abs(lacking[0])
    assert "the bright-field images put" not in _lab(tmp_path, images, sines=listed + [ky, kx])   # added: nothing


def test_a_camera_offset_left_in_the_dark_field_is_noted(tmp_path):
    images, _, nominal = _board()
    dark = np.hypot(*nominal.spectrum_centres_yx_px.T) > 1.2 * nominal.pupil_radius_px
    offset = float(np.median(images[dark].mean(axis=(1, 2)))) * 30000 / float(images.max())   # as bright as them
    note = "the dark-field images never fall near zero"
    said = _lab(tmp_path, images, offset=offset)
    assert note in said and "Set sensor.black_level" in said
    assert note not in _lab(tmp_path, images, offset=offset, sensor={"black_level": round(offset)})
    assert note not in _lab(tmp_path, images)
    # a black level stated, and light beyond it: stray light
    said = _lab(tmp_path, images, offset=2 * offset, sensor={"black_level": round(offset)})
    assert note in said and "stray light" in said and "Set sensor.black_level" not in said


def test_a_ptylab_file_off_the_axis_is_told_how_far_its_encoder_is_off(tmp_path):
    import h5py

    images, _, nominal = _board(axis_m=(-PITCH_M / 2, 0.0))
    sines = cca.led_grid_sines(GRID, pitch_m=PITCH_M, height_m=HEIGHT_M)

    def ingest(encoder):
        with h5py.File(tmp_path / "fpm.hdf5", "w") as f:
            f["ptychogram"], f["encoder"], f["zled"] = images, encoder, HEIGHT_M
            f["wavelength"], f["dxd"], f["magnification"] = OPTICS["wavelength_m"], OPTICS["pixel_pitch_object_m"], 1.0
            f["NA"] = OPTICS["numerical_aperture"]
        result = runner.invoke(app, ["ingest", str(tmp_path / "fpm.hdf5"), "-o", str(tmp_path / "raw.h5"), "-q",
                                     "--force"])
        assert result.exit_code == 0, result.output
        return " ".join(result.output.split())

    encoder = sines * HEIGHT_M / np.sqrt(1 - np.sum(sines ** 2, axis=1, keepdims=True))     # [y, x] in the LED plane
    said = ingest(encoder)
    told = said.split("Add [")[1].split("]")[0]
    y, x = (float(v) for v in told.split(","))
    assert x == pytest.approx(PITCH_M / 2, rel=0.2) and abs(y) < 0.05 * PITCH_M and "fpm.hdf5's encoder" in said
    assert "the bright-field images put" not in ingest(encoder + [y, x])      # as told: nothing to say


def test_a_phase_object_s_rings_do_not_pass_for_an_off_axis_board():
    """Round cells of phase scatter rings into the bright-field spectra that the circles' edges can lock onto; the
    captures' brightness, which the given positions explain, keeps such a shift from being reported."""
    rng = np.random.default_rng(3)
    size = 128
    y, x = np.mgrid[:size, :size]
    phase = np.zeros((size, size))
    for cy, cx in rng.uniform(8, size - 8, (40, 2)):
        phase += 1.5 * (np.hypot(y - cy, x - cx) < rng.uniform(4, 7))
    cells = (0.95 * np.exp(1j * np.clip(phase, 0, 2))).astype(np.complex64)
    geometry = cca.led_array(cca.led_grid_sines(GRID, pitch_m=PITCH_M, height_m=HEIGHT_M), image_pixels=64, **OPTICS)
    images = cca.simulate(cells, geometry, snr_db=40, seed=1)
    found = axis_offset(images, geometry.spectrum_centres_yx_px, geometry.pupil_radius_px)
    assert not found.off_axis
    assert found.radii < OFF_AXIS or found.misplaced_shifted >= found.misplaced_given
