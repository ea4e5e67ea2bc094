"""Centred FFTs, Fourier resampling and the in-place FFT backends."""

import numpy as np
import pytest

from cca_cli.errors import ConfigError
from cca_cli.optics import fft

RNG = np.random.default_rng(3)
BACKENDS = ["scipy", pytest.param("pyfftw", marks=pytest.mark.skipif(not fft.HAVE_PYFFTW, reason="pyfftw disabled"))]


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
        plan = fft.InPlaceFFT2(buffer, threads=1)
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


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("count", [0, 1, 3, 5, 6])
def test_banded_fft_of_the_first_count_fields_matches_numpy(backend, count):
    with fft.use_backend(backend):
        buffer = fft.zeros((6, 16, 16))
        plan = fft.BandedFFT2(buffer, 4, 12, threads=1)
        data = np.zeros((6, 16, 16), np.complex64)
        data[:, 4:12, 3:13] = _random_complex((6, 8, 10))
        buffer[...] = data
        plan.inverse(count)
        np.testing.assert_allclose(buffer[:count], np.fft.ifft2(data[:count]) * 256, atol=1e-3)
        if count == 0:
            np.testing.assert_array_equal(buffer, data)
        plan.forward(count)
        np.testing.assert_allclose(buffer[:count, 4:12], data[:count, 4:12] * 256, atol=1e-2)


def test_banded_fft_rejects_a_count_beyond_the_buffer():
    plan = fft.BandedFFT2(fft.zeros((2, 8, 8)), 2, 6, threads=1)
    with pytest.raises(ValueError, match="count must be in"):
        plan.inverse(3)


def test_planning_effort_comes_from_the_environment(monkeypatch):
    monkeypatch.setenv("CCA_FFTW_PLANNING", "Estimate")
    assert fft.planning_effort() == "estimate"
    monkeypatch.delenv("CCA_FFTW_PLANNING")
    assert fft.planning_effort() == "exact"
    monkeypatch.setenv("CCA_FFTW_PLANNING", "hard")
    with pytest.raises(ConfigError, match="CCA_FFTW_PLANNING='hard' is not one of exact, estimate, auto, measure, patient"):
        fft.planning_effort()
    with pytest.raises(ConfigError, match="CCA_FFTW_PLANNING"):
        fft.BandedFFT2(fft.zeros((2, 8, 8)), 2, 6, threads=1)


def _raw_or_skip(plan):
    raw = plan.raw_plans()
    if raw is None:
        pytest.skip("raw FFTW plans need pyfftw's FFTW library on Linux")
    return raw


def test_raw_plans_compute_the_same_transforms_as_the_buffer_methods():
    plan = fft.BandedFFT2(fft.zeros((3, 16, 16)), 4, 12, threads=1)
    raw = _raw_or_skip(plan)
    assert raw.counts.tolist() == [1, 2, 3] and raw.buffer is plan.buffer
    data = np.zeros((3, 16, 16), np.complex64)
    data[:, 4:12, 3:13] = _random_complex((3, 8, 10))
    plan.buffer[...] = data
    raw.execute(2, 0)
    raw.execute(2, 1)
    np.testing.assert_allclose(plan.buffer[:2], np.fft.ifft2(data[:2]) * 256, atol=1e-3)
    np.testing.assert_array_equal(plan.buffer[2], data[2])
    raw.execute(2, 2)
    raw.execute(2, 3)
    np.testing.assert_allclose(plan.buffer[:2, 4:12], data[:2, 4:12] * 256, atol=1e-2)
    with pytest.raises(ValueError, match="no plan for count 5"):
        raw.execute(5, 0)


def test_raw_plans_refuse_another_buffer():
    plan = fft.BandedFFT2(fft.zeros((4, 8, 8)), 2, 6, threads=1)
    raw = _raw_or_skip(plan)
    with pytest.raises(ValueError, match="buffer these FFTW plans were made for"):
        with raw.executing(fft.zeros((4, 8, 8))):
            pass
    with raw.executing(plan.buffer) as held:
        assert held.plans.shape == (3, 4) and held.counts.tolist() == [1, 2, 4]


def test_closed_transforms_raise_instead_of_running():
    for backend in ("scipy", "pyfftw") if fft.HAVE_PYFFTW else ("scipy",):
        with fft.use_backend(backend):
            banded = fft.BandedFFT2(fft.zeros((2, 8, 8)), 2, 6, threads=1)
            full = fft.InPlaceFFT2(fft.zeros((2, 8, 8)), threads=1)
        banded.close()
        full.close()
        if backend == "pyfftw":
            with pytest.raises(RuntimeError, match="released"):
                banded.inverse(1)
            with pytest.raises(RuntimeError, match="released"):
                full.forward()


def test_transforms_refuse_buffers_they_cannot_plan():
    with pytest.raises(ValueError, match="C-contiguous"):
        fft.InPlaceFFT2(fft.zeros((4, 8, 8))[:, :, ::2])
    with pytest.raises(ValueError, match="band rows"):
        fft.BandedFFT2(fft.zeros((2, 8, 8)), 6, 2)
    with pytest.raises(ValueError, match="unknown FFTW planning effort"):
        fft.BandedFFT2(fft.zeros((2, 8, 8)), 2, 6, effort="exhaustive")


@pytest.mark.skipif(not fft.HAVE_PYFFTW, reason="the alignment serves FFTW")
def test_buffers_are_aligned_to_64_bytes_so_a_shape_has_one_fftw_plan():
    # FFTW picks (and rounds with) other codelets for other alignments; every SIMD width fits in 64 bytes.
    for shape in [(1,), (3, 5, 7), (2, 90, 90), (17, 31)]:
        assert fft.empty(shape).ctypes.data % 64 == 0
        assert fft.zeros(shape, np.float32).ctypes.data % 64 == 0
