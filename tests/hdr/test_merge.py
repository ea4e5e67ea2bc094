"""Tests for cca_cli.hdr: the noise-model merge, its checks, and the noise estimate from brackets."""

import numpy as np
import pytest

from cca_cli.hdr import HdrResult, NoiseModel, estimate_noise, merge_exposures

EXPOSURES = np.array([0.001, 0.004, 0.016])  # 1, 4, 16 ms
FULL, BLACK = 4095.0, 64.0
READ_NOISE, GAIN = 2.0, 1.5                  # codes RMS, electrons per code
NOISE = NoiseModel(READ_NOISE, GAIN)


def capture(radiance, exposures=EXPOSURES, *, seed=0, noise=True):
    """12-bit quantised, clipped, black-subtracted frames (..., E, H, W) of a radiance map (codes/s)."""
    rng = np.random.default_rng(seed)
    t = np.asarray(exposures, dtype=np.float64)[..., :, None, None]
    mean = np.asarray(radiance, dtype=np.float64)[..., None, :, :] * t
    if noise:
        signal = rng.poisson(mean * GAIN) / GAIN + rng.normal(0, READ_NOISE, mean.shape)
    else:
        signal = mean
    codes = np.clip(np.rint(signal + BLACK), 0, FULL)
    return (codes - BLACK).astype(np.float32)


def test_dark_pixels_are_unbiased():
    # 0.5 codes per pixel at 16 ms, four times below the read noise: half the readings are <= 0.
    radiance = np.full((200, 200), 30.0)
    stack = capture(radiance)
    assert (stack[2] <= 0).mean() > 0.3
    res = merge_exposures(stack, EXPOSURES, saturation_level=FULL - BLACK, noise=NOISE)
    assert res.valid.all() and (res.weight > 0).all()  # zeros and negatives count
    sigma_mean = np.sqrt(np.mean(res.variance)) / np.sqrt(radiance.size)
    assert abs(res.radiance.mean() - 30.0) < 4 * sigma_mean, (res.radiance.mean(), sigma_mean)
    # Dropping the non-positive readings (the old merge) is far off.
    kept = np.where(stack > 0, stack, np.nan)
    assert np.nanmean(kept[2] / EXPOSURES[2]) > 3 * 30.0


def test_flux_of_a_bright_and_dark_scene_is_within_a_fraction_of_a_percent():
    rng = np.random.default_rng(3)
    radiance = np.exp(rng.uniform(np.log(20.0), np.log(3.5e6), (64, 64)))
    stack = capture(radiance, seed=4)
    res = merge_exposures(stack, EXPOSURES, saturation_level=FULL - BLACK, noise=NOISE)
    assert res.valid.all()
    assert abs(res.radiance.sum() / radiance.sum() - 1) < 0.003
    # Pixels bright enough to saturate the longest exposure are not biased low by clipping.
    bright = radiance * EXPOSURES[-1] > 0.8 * (FULL - BLACK)
    assert abs(np.mean(res.radiance[bright] / radiance[bright]) - 1) < 0.003


def test_noise_free_bracket_is_exact_to_quantisation():
    radiance = np.logspace(np.log10(2e3), np.log10(3.9e6), 400).reshape(20, 20)
    res = merge_exposures(capture(radiance, noise=False), EXPOSURES, saturation_level=FULL - BLACK, noise=NOISE)
    # About a code of rounding in the longest exposure that is not near clipping (shorter ones weigh little).
    longest = np.where(radiance * EXPOSURES[-1] < 0.9 * (FULL - BLACK), EXPOSURES[-1],
                       np.where(radiance * EXPOSURES[1] < 0.9 * (FULL - BLACK), EXPOSURES[1], EXPOSURES[0]))
    assert np.all(np.abs(res.radiance / radiance - 1) <= 1.0 / (radiance * longest) + 1e-4)


def test_saturated_everywhere_is_invalid_with_a_lower_bound():
    radiance = np.full((8, 8), 1e5)
    radiance[:2] = 1e7  # clips even at 1 ms
    res = merge_exposures(capture(radiance), EXPOSURES, saturation_level=FULL - BLACK, noise=NOISE)
    assert not res.valid[:2].any() and res.valid[2:].all()
    assert np.all(res.weight[:2] == 0) and np.all(res.weight[2:] > 0)
    level = (FULL - BLACK) * 0.99
    np.testing.assert_allclose(res.radiance[:2], level / EXPOSURES[0], rtol=1e-6)
    assert res.saturated_fraction == pytest.approx(0.25)


def test_inverse_variance_weights():
    # Read-noise limited: weights ∝ t², so the longest exposure dominates far more than with weights ∝ t.
    x = np.array([1.0, 10.0, 50.0], np.float32).reshape(3, 1, 1)
    read_only = NoiseModel(2.0, 1e12)
    res = merge_exposures(x, EXPOSURES, saturation_level=FULL, noise=read_only, smoothing_px=0)
    w = EXPOSURES**2
    expected = np.sum(w * x.ravel() / EXPOSURES) / w.sum()
    assert res.radiance[0, 0] == pytest.approx(expected, rel=1e-5)
    assert res.variance[0, 0] == pytest.approx(4.0 / w.sum(), rel=1e-5)


def test_flux_ratios_follow_exposure_ratios_and_catch_a_wrong_exposure():
    radiance = np.random.default_rng(5).uniform(2e3, 2e5, (64, 64))
    stack = capture(radiance, seed=6)
    good = merge_exposures(stack, EXPOSURES, saturation_level=FULL - BLACK, noise=NOISE)
    assert np.all(np.abs(good.flux_ratio - 1) < 4 * good.flux_ratio_sigma + 1e-3)
    wrong = EXPOSURES.copy()
    wrong[1] = 0.005  # the 4 ms frame listed as 5 ms
    bad = merge_exposures(stack, wrong, saturation_level=FULL - BLACK, noise=NOISE)
    assert abs(bad.flux_ratio[1] - 0.8) < 0.05
    assert abs(bad.flux_ratio[1] - 1) > 10 * bad.flux_ratio_sigma[1]


def test_dynamic_range_gain_means_what_it_says():
    ramp = np.logspace(np.log10(1e3), np.log10(2e6), 256)[None, :] * np.ones((32, 1))
    res = merge_exposures(capture(ramp), EXPOSURES, saturation_level=FULL - BLACK, noise=NOISE)
    assert res.exposure_ratio == pytest.approx(16.0)
    # The merge measures about 16x (the bracket) more range at SNR >= 10 than one exposure.
    assert 6.0 < res.dynamic_range_gain < 20.0
    assert res.dynamic_range > 500
    narrow = merge_exposures(capture(np.full((32, 32), 1e5)), EXPOSURES, saturation_level=FULL - BLACK, noise=NOISE)
    assert narrow.dynamic_range_gain == pytest.approx(1.0, abs=0.05)


def test_noise_is_measured_from_the_brackets():
    rng = np.random.default_rng(8)
    radiance = np.kron(rng.uniform(1e3, 2e5, (12, 12)), np.ones((12, 12)))  # flat patches
    model = estimate_noise(capture(radiance, seed=9), EXPOSURES, saturation_level=FULL - BLACK)
    assert model.read_noise == pytest.approx(READ_NOISE, rel=0.15)
    assert model.electrons_per_count == pytest.approx(GAIN, rel=0.2)


def test_brackets_without_shot_noise_give_the_default_gain_not_an_absurd_one():
    rng = np.random.default_rng(8)
    radiance = np.kron(rng.uniform(1e3, 2e5, (12, 12)), np.ones((12, 12)))
    # the same scaled frame in every bracket, plus read noise only: nothing grows with the light
    frames = np.stack([radiance * t + rng.normal(0, READ_NOISE, radiance.shape) for t in EXPOSURES])
    model = estimate_noise(frames.astype(np.float32), EXPOSURES, saturation_level=FULL - BLACK)
    assert "barely visible" in model.source and 1.0 < model.electrons_per_count < 4763   # a bound, not 1/noise
    assert model.read_noise == pytest.approx(READ_NOISE, rel=0.3)


def test_batch_axis_matches_individual_merges():
    rng = np.random.default_rng(1)
    scenes = rng.uniform(1e3, 1e6, (2, 24, 24))
    exposures = np.array([[0.001, 0.004, 0.016], [0.016, 0.002, 0.008]])  # any order
    stack = np.stack([capture(s, e, seed=k) for k, (s, e) in enumerate(zip(scenes, exposures))])
    res = merge_exposures(stack, exposures, saturation_level=FULL - BLACK, noise=NOISE)
    assert isinstance(res, HdrResult) and res.radiance.shape == (2, 24, 24)
    for k in range(2):
        single = merge_exposures(stack[k], exposures[k], saturation_level=FULL - BLACK, noise=NOISE)
        np.testing.assert_allclose(res.radiance[k], single.radiance, rtol=1e-6)
        np.testing.assert_array_equal(res.valid[k], single.valid)
        np.testing.assert_allclose(res.flux_ratio[k], single.flux_ratio, rtol=1e-9)


def test_per_pixel_saturation_levels():
    radiance = np.full((4, 4), 2e5)  # 3200 codes at 16 ms
    stack = capture(radiance, noise=False)
    levels = np.full((3, 4, 4), FULL - BLACK, np.float32)
    levels[:, 0, 0] = 3000.0  # a pixel with a high black level clips earlier
    res = merge_exposures(stack, EXPOSURES, saturation_level=levels, noise=NOISE)
    assert res.valid.all()
    assert res.radiance[0, 0] == pytest.approx(2e5, rel=0.01)


def test_duplicate_exposure_time_rejected():
    stack = np.ones((3, 4, 4), np.float32) * 100
    with pytest.raises(ValueError, match=r"exposure 0\.004 s listed twice"):
        merge_exposures(stack, [0.001, 0.004, 0.004], saturation_level=FULL, noise=NOISE)


def test_nan_rejected():
    stack = np.ones((3, 4, 4), np.float32) * 100
    stack[1, 2, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        merge_exposures(stack, EXPOSURES, saturation_level=FULL, noise=NOISE)


@pytest.mark.parametrize(
    "exposures, message",
    [([0.001, 0.004], "shape"), ([0.001, -0.004, 0.016], "not positive"), ([0.001, np.nan, 0.016], "NaN")],
)
def test_bad_exposures_rejected(exposures, message):
    stack = np.ones((3, 4, 4), np.float32) * 100
    with pytest.raises(ValueError, match=message):
        merge_exposures(stack, exposures, saturation_level=FULL, noise=NOISE)


def test_empty_bracket_rejected():
    with pytest.raises(ValueError):
        merge_exposures(np.ones((0, 4, 4), np.float32), np.zeros(0), saturation_level=FULL, noise=NOISE)
