"""Spectral reach: how far out an image's detail reaches."""

import numpy as np
import pytest

from cca_cli.metrics.sharpness import spectral_reach


def test_reach_of_band_limited_noise_is_its_band_and_blurring_shortens_it():
    rng = np.random.default_rng(1)
    n = 128
    ky, kx = np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n), indexing="ij")
    radius = np.hypot(ky, kx)
    spectrum = np.fft.fft2(rng.standard_normal((n, n)))
    wide = np.fft.ifft2(spectrum * (radius <= 0.3)).real
    narrow = np.fft.ifft2(spectrum * (radius <= 0.1)).real
    # a flat (white) spectrum inside a disc encloses 99% of its power at 0.995 of the radius
    assert spectral_reach(wide, share=0.99) == pytest.approx(0.3 * np.sqrt(0.99), rel=0.03)
    assert spectral_reach(narrow, pixel_m=2e-6) == pytest.approx(0.1 * np.sqrt(0.99) / 2e-6, rel=0.05)
    assert spectral_reach(np.ones((8, 8))) == 0.0
    with pytest.raises(ValueError, match="share"):
        spectral_reach(wide, share=1.0)
