"""The catalogue of bad input for the Python interface: what ``cca reconstruct`` refuses in a file, the API refuses
in arrays, with a ValueError whose message names the argument; dead captures are left out or refused alike."""

from __future__ import annotations

import ast
import re
import logging
import math
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app

PACKAGE = Path(cca.__file__).resolve().parent
CAMERA = dict(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6, distance_m=50,
              field_width_m=8e-3)


@pytest.fixture(scope="module")
def scan():
    """A 5 x 5 camera scan of a 64-px chart and its captures (centre image 12)."""
    geometry = cca.camera_scan(**CAMERA, grid=5, overlap=0.61)
    chart = cca.resolution_chart(64, widths=(4, 3, 2))
    return geometry, chart, cca.simulate(chart.image, geometry, snr_db=40, seed=1)


def _with(images, index, value):
    images = images.copy()
    images[index] = value
    return images


# --- intensities and weights: as the CLI reads /measurements -----------------------------------------------------------
def test_an_unlit_image_whose_mean_noise_puts_a_hair_under_zero_is_kept(scan):
    """A dark-field capture that recorded no light, black level subtracted: zero mean up to its noise."""
    geometry, _, images = scan
    unlit = np.random.default_rng(1).normal(0, 1, images[7].shape).astype(np.float32)
    unlit -= unlit.mean() + 0.5 * unlit.std() / np.sqrt(unlit.size)   # half a standard error below zero
    assert cca.reconstruct(_with(images, 7, unlit), geometry, iterations=2).iterations == 2
    with pytest.raises(ValueError, match=r"^image 7 of intensities has a negative mean \(-1.0\d, [\d.]+ times its noise\)"):
        cca.reconstruct(_with(images, 7, unlit - 1), geometry, iterations=2)   # a black level one count too high


@pytest.mark.parametrize("case, match", [
    ("complex", r"^intensities holds complex values"),
    ("text", r"^intensities must be real numbers"),
    ("nan-pixel", r"^image 3 of intensities contains NaN or Inf"),
    ("inf-pixel", r"^image 3 of intensities contains NaN or Inf"),
    ("negated", r"^image \d+ \(and \d+ more\) of intensities has a negative mean"),
    ("one-negated", r"^image 7 of intensities has a negative mean"),
    ("zero", r"^every image of intensities is zero"),
    ("flat", r"^every image of intensities is flat"),
])
def test_reconstruct_refuses_what_the_cli_refuses(scan, case, match):
    geometry, _, images = scan
    bad = {"complex": lambda: images.astype(np.complex64) * 1j, "text": lambda: images.astype(str),
           "nan-pixel": lambda: _with(images, (3, 5, 5), np.nan), "inf-pixel": lambda: _with(images, (3, 0, 0), np.inf),
           "negated": lambda: -images, "one-negated": lambda: _with(images, 7, -images[7]),
           "zero": lambda: np.zeros_like(images), "flat": lambda: np.ones_like(images)}[case]()
    with pytest.raises(ValueError, match=match):
        cca.reconstruct(bad, geometry, iterations=2)


def test_images_of_different_shapes_are_named_not_left_to_numpy(scan):
    geometry, _, images = scan
    ragged = [image for image in images[:-1]] + [images[-1][:, :-1]]
    with pytest.raises(ValueError, match=r"^intensities: the images differ in shape \(64x63, 64x64\); give images of "
                                         r"one shape, as one \(K, H, W\) array"):
        cca.reconstruct(ragged, geometry, iterations=2)


def test_complex_intensities_are_refused_not_truncated_with_a_warning(scan):
    geometry, _, images = scan
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # NumPy's ComplexWarning would be one
        with pytest.raises(ValueError, match="intensities holds complex values"):
            cca.reconstruct(images + 0j, geometry, iterations=2)


def test_slightly_negative_pixels_are_recorded_noise(scan):
    """Dark-subtracted data dip below zero about the dark level: such pixels are kept, as the CLI keeps them."""
    geometry, chart, images = scan
    noisy = images + np.random.default_rng(0).normal(0, 1e-3, images.shape).astype(np.float32)
    assert (noisy < 0).any() and (noisy.mean(axis=(1, 2)) > 0).all()
    result = cca.reconstruct(noisy, geometry, engine="momentum", iterations=10)
    assert np.isfinite(result.object).all()
    assert cca.mtf20(result.intensity, chart) == 2


@pytest.mark.parametrize("bad, match", [(np.nan, r"^image 0 of captures contains NaN or Inf"),
                                        (1j, r"^captures holds complex values")])
def test_reconstruct_tiles_refuses_what_the_cli_refuses(scan, bad, match):
    from cca_cli.api import reconstruct_tiles

    geometry, _, images = scan
    with pytest.raises(ValueError, match=match):
        reconstruct_tiles(images + np.full(images.shape, bad), geometry, size_px=32, overlap_px=8)


@pytest.mark.parametrize("weight, match", [
    (np.nan, r"^weight contains NaN or Inf"), (2.0, r"^weight spans \[2, 2\]"), (-1.0, r"^weight spans \[-1, -1\]"),
    (0.0, r"^weight is 0 everywhere"), (1j, r"^weight holds complex values"),
])
def test_reconstruct_refuses_weights_the_cli_refuses(scan, weight, match):
    geometry, _, images = scan
    with pytest.raises(ValueError, match=match):
        cca.reconstruct(images, geometry, weight=np.full(images.shape, weight), iterations=2)
    with pytest.raises(ValueError, match=r"^weight has shape \(2, 2\)"):
        cca.reconstruct(images, geometry, weight=np.ones((2, 2)), iterations=2)


@pytest.mark.parametrize("options, name", [({"tau": np.nan}, "tau"), ({"tau": np.inf}, "tau"), ({"tol": np.inf}, "tol")])
def test_reconstruct_refuses_non_finite_options(scan, options, name):
    geometry, _, images = scan
    with pytest.raises(ValueError, match=rf"^{name}: .*finite number"):
        cca.reconstruct(images, geometry, iterations=2, **options)


# --- simulate ------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, match", [
    ({"obj": "nan-pixel"}, r"^obj holds 1 NaN or infinite pixel"),
    ({"obj": "text"}, r"^obj must be numbers"),
    ({"snr_db": np.nan}, r"^snr_db must be a finite number"),
    ({"snr_db": np.inf}, r"^snr_db must be a finite number"),
    ({"snr_db": -100}, r"^snr_db -100: the noise would swamp the signal"),
    ({"snr_db": None, "photons_per_unit": 0}, r"^photons_per_unit must be in \(0, 1e12\]"),
    ({"snr_db": None, "photons_per_unit": np.nan}, r"^photons_per_unit must be a finite number"),
    ({"snr_db": None, "photons_per_unit": 100, "read_noise_e": -1}, r"^read_noise_e must be a finite number ≥ 0"),
    ({"seed": -1}, r"^seed must be a whole number ≥ 0"),
    ({"seed": 1.5}, r"^seed must be a whole number ≥ 0"),
])
def test_simulate_refuses_what_would_give_nan_images(scan, kwargs, match):
    geometry, chart, _ = scan
    obj = chart.image.copy()
    if kwargs.get("obj") == "nan-pixel":
        obj[10, 20] = np.nan
    elif kwargs.get("obj") == "text":
        obj = obj.astype(str)
    kwargs = {k: v for k, v in kwargs.items() if k != "obj"}
    with pytest.raises(ValueError, match=match):
        cca.simulate(obj, geometry, **kwargs)


def test_simulate_takes_the_lowest_snr_the_config_takes(scan):
    geometry, chart, _ = scan
    images = cca.simulate(chart.image, geometry, snr_db=-10, seed=2)
    assert np.isfinite(images).all() and (images.mean(axis=(1, 2)) > 0).all()


# --- geometry constructors ----------------------------------------------------------------------------------------------
BAD_SI = [-5e-7, 0, math.nan, math.inf, "red", True]
LED = dict(wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6, image_pixels=48)
STAGE = dict(wavelength_m=633e-9, focal_length_m=75e-3, aperture_diameter_m=2.5e-3, pixel_pitch_m=3.75e-6,
             distance_m=1.5, image_pixels=64)


def _camera_scan(**change):
    return cca.camera_scan(**{**CAMERA, "grid": 3, **change})


def _stage_scan(**change):
    return cca.stage_scan(np.zeros((3, 2)) + [[0, -1e-3], [0, 0], [0, 1e-3]], **{**STAGE, **change})


def _led_array(**change):
    return cca.led_array(cca.led_grid_sines(3, pitch_m=4e-3, height_m=90e-3), **{**LED, **change})


def _led_grid_sines(**change):
    return cca.led_grid_sines(**{"grid": 3, "pitch_m": 4e-3, "height_m": 90e-3, **change})


SI_ARGUMENTS = [(_camera_scan, name) for name in CAMERA] + [(_stage_scan, name) for name in STAGE if name != "image_pixels"] \
    + [(_led_array, name) for name in ("wavelength_m", "pixel_pitch_object_m")] \
    + [(_led_grid_sines, name) for name in ("pitch_m", "height_m")]


@pytest.mark.parametrize("make, name", SI_ARGUMENTS, ids=[f"{m.__name__[1:]}-{n}" for m, n in SI_ARGUMENTS])
@pytest.mark.parametrize("value", BAD_SI, ids=repr)
def test_geometry_refuses_a_bad_si_value_by_name(make, name, value):
    with pytest.raises(ValueError, match=rf"^{name} must be a positive, finite number"):
        make(**{name: value})


@pytest.mark.parametrize("make, change, match", [
    (_camera_scan, {"grid": 0}, r"^grid must be a whole number ≥ 1"),
    (_camera_scan, {"grid": 2.5}, r"^grid must be a whole number ≥ 1"),
    (_camera_scan, {"overlap": math.nan}, r"^overlap must be a finite number"),
    (_camera_scan, {"overlap": 1.0}, r"^overlap must be in \[0, 1\)"),
    (_camera_scan, {"grid": None, "sar": math.nan}, r"^sar must be a finite number ≥ 1"),
    (_camera_scan, {"grid": None, "sar": 0.5}, r"^sar must be a finite number ≥ 1"),
    (_stage_scan, {"image_pixels": 0}, r"^image_pixels must be a whole number ≥ 1"),
    (_led_array, {"image_pixels": -48}, r"^image_pixels must be a whole number ≥ 1"),
    (_led_array, {"numerical_aperture": 1.5}, r"^numerical_aperture must be a number in \(0, 1\)"),
    (_led_array, {"numerical_aperture": -0.1}, r"^numerical_aperture must be a number in \(0, 1\)"),
    (_led_array, {"numerical_aperture": math.nan}, r"^numerical_aperture must be a number in \(0, 1\)"),
    (_led_grid_sines, {"grid": 0}, r"^grid must be a whole number ≥ 1"),
    (_led_grid_sines, {"pitch_m": 4}, r"^pitch_m: 4 m is not a plausible LED pitch: give it in metres \(4e-3 for 4 mm\)"),
    (_led_grid_sines, {"height_m": 90}, r"^height_m: 90 m is not a plausible LED distance: give it in metres"),
])
def test_geometry_refuses_counts_and_ratios_by_name(make, change, match):
    with pytest.raises(ValueError, match=match):
        make(**change)


@pytest.mark.parametrize("positions, match", [
    (np.full((3, 2), np.nan), r"^positions_yx_m holds NaN or infinite values"),
    (np.zeros((3, 3)), r"^positions_yx_m must have shape \(K, 2\)"),
])
def test_stage_scan_refuses_bad_positions(positions, match):
    with pytest.raises(ValueError, match=match):
        cca.stage_scan(positions, **STAGE)


def test_led_array_refuses_sines_beyond_one():
    with pytest.raises(ValueError, match=r"^sin_yx holds sines beyond ±1"):
        cca.led_array(np.array([[0.0, 0.0], [0.0, 30.0]]), **LED)


def test_no_assert_guards_anything_in_the_package():
    """``assert`` vanishes under ``python -O`` and says nothing: every check raises a named error instead."""
    found = [f"{path.relative_to(PACKAGE.parent)}:{node.lineno}" for path in sorted(PACKAGE.rglob("*.py"))
             for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.Assert)]
    assert found == []


# --- dead captures ----------------------------------------------------------------------------------------------------------
def test_a_dead_capture_is_left_out_with_a_warning(scan, caplog):
    geometry, chart, images = scan
    dead = _with(images, 3, 0.0)
    with caplog.at_level(logging.WARNING, logger="cca"):
        result = cca.reconstruct(dead, geometry, engine="momentum", iterations=10)
    messages = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
    assert messages == ["left out 1 of 25 images of intensities: image 3 (row 0, col 3) holds one value (0), nothing "
                        "was recorded there; the recovery uses the other 24"]
    assert result.geometry.n_images == 24
    assert result.geometry.centre_index == 11 and result.geometry.grid_indices[11].tolist() == [2, 2]
    assert result.geometry.grid_indices[3].tolist() == [0, 4]
    assert np.array_equal(result.observed, images[12])
    live = cca.reconstruct(np.delete(images, 3, axis=0),
                           replace(geometry, **_without(geometry, 3)),
                           engine="momentum", iterations=10)
    np.testing.assert_array_equal(result.spectrum, live.spectrum)
    assert cca.mtf20(result.intensity, chart) == 2


def test_a_dead_capture_less_its_black_level_is_dead_not_negative(scan, caplog):
    """A dead frame minus a scalar black level holds one negative value: it is left out as dead, not blamed on the
    black level (which the live captures show is right)."""
    geometry, _, images = scan
    with caplog.at_level(logging.WARNING, logger="cca"):
        result = cca.reconstruct(_with(images, 20, -0.5), geometry, engine="momentum", iterations=3)
    assert result.geometry.n_images == 24
    assert "image 20 (row 4, col 0) holds one value (-0.5)" in caplog.text


def test_a_dead_led_capture_is_named_by_its_sines_whatever_the_layout(caplog):
    """An LED array need not be a grid (rings, a hexagonal board): its captures are named by their sines."""
    rings = [(0.07, 8), (0.14, 16)]    # 25 LEDs: a centre and two rings
    sines = np.concatenate([[[0.0, 0.0]]] + [radius * np.stack([np.sin(a), np.cos(a)], axis=1)
                                             for radius, n in rings for a in [np.arange(n) * 2 * np.pi / n]])
    geometry = cca.led_array(sines, wavelength_m=5e-7, numerical_aperture=0.1, pixel_pitch_object_m=1e-6,
                             image_pixels=32)
    images = np.random.default_rng(0).uniform(0.5, 1.5, (25, 32, 32)).astype(np.float32)
    images[2] = 0.0
    with caplog.at_level(logging.WARNING, logger="cca"):
        cca.reconstruct(images, geometry, engine="momentum", iterations=2)
    y, x = -sines[2]                   # the pupil sits at −sin θ (sign −1), named in sin_yx's [y, x] order
    assert f"image 2 (its pupil at [y, x] = [{y:+.4f}, {x:+.4f}] in sines) holds one value (0)" in caplog.text


def _without(geometry, index):
    return {name: np.delete(getattr(geometry, name), index, axis=0)
            for name in ("aperture_centres_yx_m", "spectrum_centres_yx_px", "grid_indices")}


def test_dead_captures_left_out_keep_their_weights_in_step(scan):
    geometry, _, images = scan
    weight = np.ones(images.shape, np.float32)
    weight[5, :8] = 0
    result = cca.reconstruct(_with(images, 3, 0.0), geometry, weight=weight, engine="momentum", iterations=5)
    expected = cca.reconstruct(np.delete(images, 3, axis=0),
                               replace(geometry, **_without(geometry, 3)),
                               weight=np.delete(weight, 3, axis=0), engine="momentum", iterations=5)
    np.testing.assert_array_equal(result.spectrum, expected.spectrum)


@pytest.mark.parametrize("dead, match", [
    ([12], r"^image 12 of intensities, the centre capture \(row 2, col 2\), holds one value \(every pixel 0\)"),
    ([0, 24], r"^2 of 25 images of intensities hold one value each, .*image 0 \(row 0, col 0\), image 24 \(row 4, "
              r"col 4\).*at most 5% of the captures \(1 here\)"),
])
def test_a_dead_centre_or_many_dead_captures_are_refused(scan, dead, match):
    geometry, _, images = scan
    with pytest.raises(ValueError, match=match):
        cca.reconstruct(_with(images, dead, 0.0), geometry, iterations=2)


def test_the_api_and_the_cli_leave_out_the_same_dead_capture(scan, tmp_path):
    geometry, _, images = scan
    path = cca.save(cca.CaptureSet(_with(images, 20, 0.7), geometry), tmp_path / "captures.h5")
    config = tmp_path / "c.yaml"
    config.write_text("reconstruct: {engine: momentum, iterations: 5, options: {threads: 1}}\n")
    result = CliRunner().invoke(app, ["reconstruct", str(path), "-o", str(tmp_path / "recon.h5"), "-c", str(config),
                                      "-q"])
    assert result.exit_code == 0, result.output
    assert "image 20 (row 4, col 0) holds one value (0.7)" in " ".join(result.stderr.split())
    cli = cca.load(tmp_path / "recon.h5")
    api = cca.reconstruct(cca.load(path), engine="momentum", iterations=5, threads=1)
    assert cli.geometry.n_images == api.geometry.n_images == 24
    np.testing.assert_allclose(api.spectrum, cli.spectrum, rtol=0, atol=1e-5 * np.abs(cli.spectrum).max())


def test_images_of_another_width_than_the_geometry_s_field_are_refused(tmp_path):
    """A crop passed with the geometry of the whole frame would come back at the wrong pixel size."""
    g = _camera_scan()
    width = round(g.field_width_m / (g.pixel_pitch_m * g.distance_m / g.focal_length_m))
    images = np.ones((g.n_images, width, width), np.float32)
    with pytest.raises(ValueError, match=rf"^intensities are {width - 16} px wide but the geometry's field .* is "
                                         rf"{width} px: build the geometry with field_width_m"):
        cca.reconstruct(images[:, 8:-8, 8:-8], g)
    with pytest.raises(ValueError, match="describes 9 captures"):
        cca.save(cca.CaptureSet(images[:4], g), tmp_path / "c.h5")
    with pytest.raises(ValueError, match="the CaptureSet's intensities are"):
        cca.save(cca.CaptureSet(images[:, 8:-8, 8:-8], g), tmp_path / "c.h5")
    assert not (tmp_path / "c.h5").exists()


def test_a_wavelength_in_nanometres_or_as_text_is_named():
    with pytest.raises(ValueError, match=r"^wavelength_m is 550 m, not a wavelength of light .*550e-9 for 550 nm"):
        _camera_scan(wavelength_m=550)
    with pytest.raises(ValueError, match=r"^wavelength_m is 0.55 m, .*0.55e-6 for 0.55 µm"):
        _camera_scan(wavelength_m=0.55)
    with pytest.raises(ValueError, match=r"^wavelength_m must be a positive, finite number .* the text '550e-9'"):
        _camera_scan(wavelength_m="550e-9")


def test_simulate_needs_a_geometry_and_export_a_known_quantity(tmp_path):
    with pytest.raises(TypeError, match="^geometry: give a CaptureGeometry"):
        cca.simulate(np.ones((96, 96)), None)
    with pytest.raises(ValueError, match="quantity 'foo': choose one of"):
        cca.export(np.ones((4, 4)), tmp_path / "x.tif", quantity="foo", pixel_size_m=1e-6)
    assert not (tmp_path / "x.tif").exists()


def test_a_camera_array_names_each_capture_s_camera():
    steps = np.array([[0.0, x] for x in (-1e-3, 0.0, 1e-3)])
    common = dict(wavelength_m=633e-9, focal_length_m=75e-3, aperture_diameter_m=2.5e-3, pixel_pitch_m=3.75e-6,
                  distance_m=1.5, image_pixels=64)
    g = cca.stage_scan(steps, camera_index=[0, 1, 1], **common)
    assert g.camera_index.tolist() == [0, 1, 1]
    from cca_cli.sampling.capture import with_field_width

    kept = with_field_width(g, g.field_width_m / 2, keep=[0, 2])     # register dropping a view keeps them paired
    assert kept.camera_index.tolist() == [0, 1] and kept.n_images == 2
    with pytest.raises(ValueError, match="^camera_index must hold one camera number"):
        cca.stage_scan(steps, camera_index=[0, 1], **common)


def test_a_chart_too_small_for_its_widths_names_size_px():
    with pytest.raises(ValueError, match=r"^size_px: a chart with widths .* does not fit in 256x256"):
        cca.resolution_chart(256)
    with pytest.raises(ValueError, match=r"^size_px must be a whole number ≥ 1, got 64.5"):
        cca.resolution_chart(64.5, widths=(4, 2))
    assert cca.resolution_chart(64.0, widths=(4, 2)).image.shape == (64, 64)   # a whole float is a size
    assert cca.resolution_chart(64, widths=np.array([4, 2])).widths == (4, 2)   # any sequence of widths


@pytest.mark.parametrize("change, message", [
    ({"focal_length_m": 800}, "focal_length_m: 800 m is not a plausible focal length: give it in metres (800e-3"),
    ({"aperture_diameter_m": 18}, "aperture_diameter_m: 18 m is not a plausible aperture diameter"),
    ({"pixel_pitch_m": 2}, "pixel_pitch_m: 2 m is not a plausible pixel pitch: give it in metres (2e-6 for 2 µm)")])
def test_lengths_typed_in_millimetres_or_micrometres_are_named_before_anything_is_allocated(change, message):
    """800 for a 0.8 m lens made simulate ask numpy for 275 GiB (a MemoryError); the API, a config and a manifest
    now refuse such a length by name, with the figure in metres to give."""
    base = dict(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3, pixel_pitch_m=2e-6,
                distance_m=50, field_width_m=64e-3, grid=5, overlap=0.61)
    with pytest.raises(ValueError, match=re.escape(message)):
        cca.camera_scan(**{**base, **change})


def test_a_file_s_image_with_a_negative_mean_is_named_by_its_capture():
    from cca_cli.errors import InputError
    from cca_cli.library.data import check_intensity

    images = np.abs(np.random.default_rng(2).normal(5, 1, (4, 16, 16))).astype(np.float32)
    images[2] -= 20
    with pytest.raises(InputError, match=r"^raw.h5: image 2 \(LED 3 \(img_002.tif\)\) of /measurements/intensity has"):
        check_intensity(images, "/measurements/intensity", source="raw.h5", error=InputError,
                        labels=[f"LED {i + 1} (img_00{i}.tif)" for i in range(4)])
