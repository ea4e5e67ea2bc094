"""Centred FFTs, Fourier resampling and the in-place FFT backends."""

import numpy as np
import pytest

from cca_cli.optics import fft

RNG = np.random.default_rng(3)
BACKENDS = ["scipy", "pyfftw"]


def _random_complex(shape):
    return (RNG.standard_normal(shape) + 1j * RNG.standard_normal(shape)).astype(np.complex64)


def _energy(a):
    return float(np.vdot(a.astype(np.complex128).ravel(), a.astype(np.complex128).ravel()).real)


@pytest.mark.parametrize("n", [32, 33, 64])
def test_fft2c_and_ifft2c_are_unitary(n):
    x = _random_complex((3, n, n))
    spectrum = fft.fft2c(x)
    assert abs(_energy(spectrum) / _energy(x) - 1.0) < 1e-5
    assert abs(_energy(fft.ifft2c(x)) / _energy(x) - 1.0) < 1e-5
    np.testing.assert_allclose(fft.ifft2c(spectrum), x, atol=1e-5)


def test_fft2c_puts_dc_at_the_centre():
    for n in (16, 17):
        spectrum = fft.fft2c(np.ones((n, n), np.complex64))
        assert abs(spectrum[n // 2, n // 2] - n) < 1e-4
        spectrum[n // 2, n // 2] = 0
        assert np.max(np.abs(spectrum)) < 1e-4


def _band_limited(n, cutoff):
    image = RNG.standard_normal((2, n, n))
    spectrum = np.fft.fftshift(np.fft.fft2(image), axes=(-2, -1))
    k = np.arange(n) - n // 2
    mask = (np.abs(k)[:, None] <= cutoff) & (np.abs(k)[None, :] <= cutoff)
    return np.fft.ifft2(np.fft.ifftshift(spectrum * mask, axes=(-2, -1))).real.astype(np.float32)


def test_fourier_resample_round_trip_is_exact_for_band_limited_images():
    small = _band_limited(32, 12)
    big = fft.fourier_resample(small, 64)
    assert big.shape == (2, 64, 64) and big.dtype == np.float32
    # Sample values are preserved: every other sample of the finer grid is the coarse sample.
    np.testing.assert_allclose(big[:, ::2, ::2], small, atol=1e-4)
    np.testing.assert_allclose(fft.fourier_resample(big, 32), small, atol=1e-4)
    # A non-multiple size also round-trips.
    np.testing.assert_allclose(fft.fourier_resample(fft.fourier_resample(small, 50), 32), small, atol=1e-4)


def test_fourier_resample_preserves_constants():
    constant = np.full((1, 24, 24), 3.5, np.float32)
    for size in (24, 36, 64, 16):
        np.testing.assert_allclose(fft.fourier_resample(constant, size), 3.5, rtol=1e-5)


def test_fourier_resample_rejects_non_square_images():
    with pytest.raises(ValueError, match="square"):
        fft.fourier_resample(np.zeros((4, 6)), 8)


@pytest.mark.parametrize("backend", BACKENDS)
def test_in_place_fft_is_unnormalised_and_matches_numpy(backend):
    with fft.use_backend(backend):
        buffer = fft.zeros((2, 16, 16))
        data = _random_complex((2, 16, 16))
        plan = fft.InPlaceFFT2(buffer, threads=1)  # FFTW_MEASURE planning may scribble on the buffer
        buffer[...] = data
        assert plan.backend == backend
        out = plan.forward()
        assert out is buffer
        np.testing.assert_allclose(buffer, np.fft.fft2(data), atol=1e-3)
        plan.inverse()
        np.testing.assert_allclose(buffer, data * 256, atol=1e-2)


def test_in_place_fft_needs_complex64():
    with pytest.raises(ValueError, match="complex64"):
        fft.InPlaceFFT2(np.zeros((4, 4), np.complex128))


def test_use_backend_restores_and_rejects_unknown_names():
    before = fft.backend_name()
    with fft.use_backend("scipy"):
        assert fft.backend_name() == "scipy"
    assert fft.backend_name() == before
    with pytest.raises(ValueError, match="unknown FFT backend"):
        with fft.use_backend("cufft"):
            pass
