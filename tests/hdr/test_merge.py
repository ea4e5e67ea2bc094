"""Tests for cca_cli.hdr.merge_exposures on synthetic 12-bit brackets."""

import numpy as np
import pytest

from cca_cli.hdr import HdrResult, merge_exposures

EXPOSURES = np.array([0.001, 0.004, 0.016])  # 1, 4, 16 ms
FULL = 4095.0
NOISE = 64.0


def capture(radiance, exposures=EXPOSURES):
    """12-bit quantised, clipped captures (..., E, H, W) of a radiance map (counts/s)."""
    t = np.asarray(exposures, dtype=np.float64)[..., :, None, None]
    counts = np.rint(np.asarray(radiance, dtype=np.float64)[..., None, :, :] * t)
    return np.clip(counts, 0, FULL).astype(np.float32)


@pytest.fixture(scope="module")
def scene():
    # Log ramp from 2e3 to 2e7 counts/s (1e4 range): the darkest part is
    # under the noise floor even at 16 ms, the brightest clips even at 1 ms,
    # and the middle spans more than 1e3.
    h, w = 48, 256
    ramp = np.logspace(np.log10(2e3), np.log10(2e7), w)
    rng = np.random.default_rng(1)
    radiance = ramp[None, :] * rng.uniform(0.97, 1.03, size=(h, w))
    return radiance


def test_merge_recovers_radiance_within_one_percent(scene):
    stack = capture(scene)
    res = merge_exposures(stack, EXPOSURES, saturation_level=FULL, noise_floor=NOISE)
    assert isinstance(res, HdrResult)
    assert res.radiance.dtype == np.float32 and res.weight.dtype == np.float32
    assert res.radiance.shape == scene.shape and res.valid.shape == scene.shape

    sat = stack >= FULL * 0.99
    usable = (~sat & (stack > NOISE)).any(axis=0)
    assert usable.sum() > 0.5 * usable.size
    rel = np.abs(res.radiance / scene - 1)
    assert rel[usable].max() < 0.01
    np.testing.assert_array_equal(res.valid, usable)

    # the usable part covers more than 1e3 of dynamic range
    assert scene[usable].max() / scene[usable].min() > 1e3


def test_saturated_and_dark_pixels_are_flagged(scene):
    stack = capture(scene)
    res = merge_exposures(stack, EXPOSURES, saturation_level=FULL, noise_floor=NOISE)
    all_sat = (stack >= FULL * 0.99).all(axis=0)
    all_dark = (stack <= NOISE).all(axis=0)
    assert all_sat.any() and all_dark.any()
    assert not res.valid[all_sat].any() and not res.valid[all_dark].any()
    assert np.all(res.weight[~res.valid] == 0)
    assert np.all(res.weight[res.valid] > 0) and res.weight.max() <= 1
    assert res.saturated_fraction == pytest.approx(all_sat.mean())
    assert res.underexposed_fraction == pytest.approx(all_dark.mean())
    # fallbacks: shortest exposure's value for clipped pixels, longest for dark ones
    np.testing.assert_allclose(res.radiance[all_sat], stack[0][all_sat] / EXPOSURES[0], rtol=1e-6)
    np.testing.assert_allclose(res.radiance[all_dark], stack[2][all_dark] / EXPOSURES[2], rtol=1e-6)


def test_dynamic_range_gain(scene):
    res = merge_exposures(capture(scene), EXPOSURES, saturation_level=FULL, noise_floor=NOISE)
    assert res.exposure_ratio == pytest.approx(16.0)
    # the merged map spans about the exposure ratio more than one exposure
    assert 8.0 < res.dynamic_range_gain < 20.0


def test_weights_are_exposure_times():
    # Documented estimator: sum of usable counts over sum of their exposure
    # times (w_e = t_e). Equal weights would give the mean of x/t instead.
    x = np.array([100.0, 500.0, 1500.0, 4095.0], np.float32).reshape(4, 1, 1)
    t = np.array([0.001, 0.004, 0.016, 0.064])
    res = merge_exposures(x, t, saturation_level=FULL)
    assert res.radiance[0, 0] == pytest.approx(2100.0 / 0.021, rel=1e-6)
    assert res.weight[0, 0] == pytest.approx(2100.0 / FULL, rel=1e-6)


def test_single_exposure_has_no_gain():
    radiance = np.linspace(1e5, 3e6, 400).reshape(20, 20)
    res = merge_exposures(capture(radiance, [0.001]), [0.001], saturation_level=FULL)
    assert res.dynamic_range_gain == pytest.approx(1.0, abs=1e-3)
    assert res.valid.all()


def test_batch_axis_matches_individual_merges(scene):
    scenes = np.stack([scene, scene[:, ::-1] * 0.5])
    exposures = np.array([[0.001, 0.004, 0.016], [0.016, 0.002, 0.008]])  # any order
    stack = capture(scenes, exposures)
    assert stack.shape == (2, 3) + scene.shape
    res = merge_exposures(stack, exposures, saturation_level=FULL, noise_floor=NOISE)
    assert res.radiance.shape == (2,) + scene.shape
    for k in range(2):
        single = merge_exposures(stack[k], exposures[k], saturation_level=FULL, noise_floor=NOISE)
        np.testing.assert_array_equal(res.radiance[k], single.radiance)
        np.testing.assert_array_equal(res.valid[k], single.valid)
        np.testing.assert_array_equal(res.weight[k], single.weight)
    # a shared (E,) bracket broadcasts over the batch
    shared = merge_exposures(capture(scenes), EXPOSURES, saturation_level=FULL, noise_floor=NOISE)
    assert shared.radiance.shape == (2,) + scene.shape


def test_duplicate_exposure_time_rejected():
    stack = np.ones((3, 4, 4), np.float32) * 100
    with pytest.raises(ValueError, match=r"exposure 0\.004 s listed twice"):
        merge_exposures(stack, [0.001, 0.004, 0.004], saturation_level=FULL)


def test_nan_rejected():
    stack = np.ones((3, 4, 4), np.float32) * 100
    stack[1, 2, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        merge_exposures(stack, EXPOSURES, saturation_level=FULL)


@pytest.mark.parametrize(
    "exposures, message",
    [([0.001, 0.004], "shape"), ([0.001, -0.004, 0.016], "not positive"), ([0.001, np.nan, 0.016], "NaN")],
)
def test_bad_exposures_rejected(exposures, message):
    stack = np.ones((3, 4, 4), np.float32) * 100
    with pytest.raises(ValueError, match=message):
        merge_exposures(stack, exposures, saturation_level=FULL)


def test_empty_bracket_rejected():
    with pytest.raises(ValueError):
        merge_exposures(np.ones((0, 4, 4), np.float32), np.zeros(0), saturation_level=FULL)
