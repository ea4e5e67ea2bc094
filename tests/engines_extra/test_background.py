"""Background light the object did not scatter: fitted as a plane per dark-field capture and taken off."""

import functools

import numpy as np
import pytest

import cca_cli as cca
from cca_cli.engines.background import background_images, background_planes, dark_field_captures, less_background
from cca_cli.engines.batched import unsupported_options
from cca_cli.engines import calibration as cal
from cca_cli.engines.momentum import MomentumOptions
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel, to_model_layout
from cca_cli.sampling.grid import band_layout, square_scan
from cca_cli.targets import resolution_chart

OPTICS = dict(wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=0.9e-6)


@functools.lru_cache(maxsize=1)
def _board():
    """A 9 x 9 board's captures of a chart (40 dB), their geometry, and which captures are bright-field."""
    geometry = cca.led_array(cca.led_grid_sines(9, pitch_m=4e-3, height_m=60e-3), image_pixels=64, **OPTICS)
    images = np.asarray(cca.simulate(cca.resolution_chart(128, widths=(6, 4, 3, 2)).image, geometry, snr_db=40,
                                     seed=2), np.float32)
    images.setflags(write=False)
    bright = np.hypot(*geometry.spectrum_centres_yx_px.T) < geometry.pupil_radius_px
    return geometry, images, bright


def test_the_planes_of_the_dark_field_captures_are_found_and_taken_off():
    layout = band_layout(square_scan(5, 9.0).centres_yx_m, 8.0, hires_size=96)
    model = ForwardModel(layout, cal.pupil_functions(layout))
    spectrum = fft.fft2c(resolution_chart(96, widths=(6, 4, 3, 2)).image.astype(np.complex64)).astype(np.complex64)
    clean = model.sensor_intensity(spectrum)
    m = clean.shape[-1]
    dark = dark_field_captures(layout.centres_px, layout.pupil_radius_px)
    assert 0 < dark.sum() < len(dark)
    y, x = np.mgrid[:m, :m] - m // 2
    planes = np.zeros((len(dark), 3))
    planes[dark] = np.array([0.02, 1e-4, -2e-4]) * clean.max() * np.linspace(0.5, 1.5, dark.sum())[:, None]
    added = planes[:, 0, None, None] + planes[:, 1, None, None] * y + planes[:, 2, None, None] * x
    problem = PhaseRetrievalProblem.from_sensor_images(model, clean + added)
    found = background_planes(model, spectrum, problem.amplitudes, None, np.ones(len(dark)), dark)
    np.testing.assert_allclose(found, planes * model.intensity_scale, rtol=1e-3, atol=1e-6 * np.abs(found).max())
    images = background_images(found, m)
    np.testing.assert_allclose(images, to_model_layout(added) * model.intensity_scale, atol=1e-3 * images.max())
    taken_off = less_background(problem.amplitudes, found)
    truth = PhaseRetrievalProblem.from_sensor_images(model, clean).amplitudes
    assert np.abs(taken_off - truth).max() < 2e-3 * truth.max()
    assert less_background(problem.amplitudes, np.zeros_like(found)) is problem.amplitudes   # nothing to take off


def test_stray_light_is_fitted_and_the_object_recovered_as_without_it():
    # A 9 x 9 board's captures of a chart with stray light of 0.5% of the bright-field mean in every capture:
    # fitted, the dark-field backgrounds come out at the light added, and the image is far nearer the one
    # recovered without stray light than when the light is left in (the recovery takes it for the object's).
    geometry, images, bright = _board()
    stray = 0.005 * float(images[bright].mean())
    options = dict(engine="momentum", iterations=60, tol=0)
    clean = cca.reconstruct(images, geometry, **options)
    left = cca.reconstruct(images + stray, geometry, background=False, **options)
    fitted = cca.reconstruct(images + stray, geometry, background=True, **options)
    away = {name: cca.rmse(result.intensity, clean.intensity) for name, result in (("left", left), ("fitted", fitted))}
    assert away["fitted"] < 0.6 * away["left"], away
    found = fitted.calibration.background
    dim = ~bright & (images.mean(axis=(1, 2)) < 2 * stray)   # dark-field captures the stray light outshines
    assert dim.sum() >= 10
    np.testing.assert_allclose(found[dim], stray, rtol=0.2)
    assert np.all(found[bright] == 0) and np.all(found >= 0)
    # without stray light nothing is fitted: the dark field falls to zero between the bars
    assert not np.any(cca.reconstruct(images, geometry, background=True, **options).calibration.background)


def test_the_gpu_engines_say_they_fit_no_background():
    assert any("background" in line for line in unsupported_options(MomentumOptions(background=True)))
    assert not MomentumOptions().background


def test_held_back_captures_get_no_plane_and_a_dipping_plane_adds_no_light():
    geometry, images, bright = _board()
    stray = 0.005 * float(images[bright].mean())
    result = cca.reconstruct(images + stray, geometry, engine="momentum", background=True, hold_back=0.1,
                             iterations=20, tol=0)
    held = np.asarray(result.held_back)
    assert held.size and not np.any(result.calibration.background[held])
    assert np.any(result.calibration.background)
    # a plane steep enough to dip under zero in part of the frame takes nothing off there, and adds nothing
    ones = np.ones((1, 32, 32), np.float32)
    taken = less_background(ones, np.array([[0.1, 0.02, 0.0]]))
    assert taken.max() <= 1.0 and taken.min() < 1.0


def test_dark_field_images_that_never_fall_near_zero_turn_the_fit_on_by_themselves(caplog):
    # The captures decide, as a frame scale does: with stray light under every dark-field image, engine auto
    # fits it (and says so); an option the user sets wins; without stray light nothing changes.
    from cca_cli.engines.registry import resolve
    from cca_cli.library.stray_light import dark_field_floor, holds_stray_light

    geometry, images, bright = _board()
    lit = images + 0.02 * float(images[bright].mean())
    centres, radius = geometry.spectrum_centres_yx_px, geometry.pupil_radius_px
    assert holds_stray_light(lit, centres, radius) and not holds_stray_light(images, centres, radius)
    assert dark_field_floor(images[:4], centres[:4], radius) is None           # too few dark-field images to read
    assert resolve("auto", "led_array", {}, stray_light=True)[1].background
    assert not resolve("auto", "led_array", {"background": False}, stray_light=True)[1].background
    assert not resolve("auto", "led_array", {})[1].background
    assert resolve("auto", "simulation", {}, stray_light=True)[0] == "altmin"   # no background to fit there
    options = dict(iterations=12, tol=0)
    with caplog.at_level("WARNING"):
        fitted = cca.reconstruct(lit, geometry, **options)
    assert fitted.options["background"] and "never fall near zero" in caplog.text
    assert not cca.reconstruct(lit, geometry, background=False, **options).options["background"]
    assert not cca.reconstruct(images, geometry, **options).options["background"]


def test_the_stage_s_recipe_reads_the_switch_as_the_run_does(tmp_path):
    # A recon.h5 or checkpoint made without the background fit must not pass for one made with it.
    from cca_cli.config.model import ReconstructSection
    from cca_cli.stages.reconstruct import engine_recipe

    geometry, images, bright = _board()
    recipes = {}
    for name, stack in (("clean", images), ("lit", images + 0.02 * float(images[bright].mean()))):
        path = cca.save(cca.CaptureSet(stack, geometry, boundary="open"), tmp_path / f"{name}.h5")
        recipes[name] = (engine_recipe(path, ReconstructSection()),
                         engine_recipe(path, ReconstructSection(options={"background": False})))
    assert recipes["clean"][0] == recipes["clean"][1] == recipes["lit"][1]   # off: the same recipe
    assert recipes["lit"][0] not in ("", recipes["lit"][1])                  # on by itself: another one
    # tiles: decided once on the whole frames, every tile alike
    from cca_cli.io.tiles import read_stray_light
    from cca_cli.workflows.tiled import tile_engine, tile_recipe

    assert read_stray_light(tmp_path / "lit.h5") and not read_stray_light(tmp_path / "clean.h5")
    tiled = ReconstructSection(tiles={"size_px": 32, "overlap_px": 8})
    assert tile_engine(tiled, "led_array", stray_light=True)[1].background
    assert not tile_engine(tiled, "led_array")[1].background
    assert tile_recipe(tiled, tmp_path / "lit.h5") != tile_recipe(tiled, tmp_path / "clean.h5")
