"""Sensor noise: the paper's SNR definition, reproducibility, shot noise statistics."""

import numpy as np
import pytest

from cca_cli.optics.noise import add_gaussian_noise, add_shot_and_read_noise, gaussian_noise_sigma


def _scene(rng, n=512):
    return rng.uniform(0.2, 1.0, (2, n, n)).astype(np.float32) * np.array([1.0, 4.0], np.float32)[:, None, None]


@pytest.mark.parametrize("snr_db", [10.0, 30.0])
def test_gaussian_noise_follows_the_snr_definition(snr_db):
    images = _scene(np.random.default_rng(0))
    noisy = add_gaussian_noise(images, snr_db, np.random.default_rng(1))
    assert noisy.dtype == np.float32 and noisy.shape == images.shape
    noise = (noisy - images).astype(np.float64)
    for i in range(images.shape[0]):
        expected = images[i].var(dtype=np.float64) / 10 ** (snr_db / 10)
        assert noise[i].var() == pytest.approx(expected, rel=0.03)
        assert abs(noise[i].mean()) < 5 * np.sqrt(expected / noise[i].size)
        measured_snr = 10 * np.log10(images[i].var(dtype=np.float64) / noise[i].var())
        assert measured_snr == pytest.approx(snr_db, abs=0.15)
    np.testing.assert_allclose(gaussian_noise_sigma(images, snr_db) ** 2,
                               images.reshape(2, -1).var(axis=1, dtype=np.float64) / 10 ** (snr_db / 10),
                               rtol=1e-12)


def test_noise_is_reproducible_from_the_seed():
    images = _scene(np.random.default_rng(0), 64)
    a = add_gaussian_noise(images, 20, np.random.default_rng(5))
    b = add_gaussian_noise(images, 20, np.random.default_rng(5))
    c = add_gaussian_noise(images, 20, np.random.default_rng(6))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    p = add_shot_and_read_noise(images, photons_per_unit=100, read_noise_e=1, rng=np.random.default_rng(5))
    q = add_shot_and_read_noise(images, photons_per_unit=100, read_noise_e=1, rng=np.random.default_rng(5))
    np.testing.assert_array_equal(p, q)


def test_shot_and_read_noise_preserve_the_mean_with_poisson_variance():
    level, photons, read = 0.5, 1000.0, 2.0
    images = np.full((1, 512, 512), level, np.float32)
    noisy = add_shot_and_read_noise(images, photons_per_unit=photons, read_noise_e=read,
                                    rng=np.random.default_rng(2)).astype(np.float64)
    assert noisy.mean() == pytest.approx(level, rel=2e-3)
    expected_var = (level * photons + read ** 2) / photons ** 2
    assert noisy.var() == pytest.approx(expected_var, rel=0.03)
    with pytest.raises(ValueError, match="photons_per_unit"):
        add_shot_and_read_noise(images, photons_per_unit=0, read_noise_e=0, rng=np.random.default_rng(0))
