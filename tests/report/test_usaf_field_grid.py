import numpy as np
import pytest

from cca_cli.optics.fft import fft2c, ifft2c
from cca_cli.report.comparison import field_intensity_on_grid
from cca_cli.report.summary import on_grid


def _bandlimited_field(n, radius, seed=0):
    rng = np.random.default_rng(seed)
    spec = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))).astype(np.complex64)
    yy, xx = np.mgrid[:n, :n] - n // 2
    spec[np.hypot(yy, xx) > radius] = 0
    return ifft2c(spec)


def test_field_intensity_on_grid_matches_finer_truth():
    # a field band-limited to 0.45 of the n-grid's Nyquist: |field|² needs 0.9 of it, fine on n
    n, big = 64, 160
    field = _bandlimited_field(n, 0.45 * n / 2)
    direct = field_intensity_on_grid(field, big)
    via_intensity = on_grid(np.abs(field) ** 2, big)
    assert np.allclose(direct, via_intensity, atol=1e-4 * direct.max())
    assert np.allclose(field_intensity_on_grid(field, n), np.abs(field) ** 2)
    assert field_intensity_on_grid(np.full((n, n), 2 + 0j, np.complex64), big) == pytest.approx(4.0, rel=1e-5)


def test_field_intensity_on_grid_avoids_aliasing():
    # band-limited to 0.9 of Nyquist: |field|² on its own grid aliases, the resampled one does not
    n, big = 64, 256
    field = _bandlimited_field(n, 0.9 * n / 2, seed=1)
    fine = field_intensity_on_grid(field, big)
    aliased = on_grid(np.abs(field) ** 2, big)
    spec = np.abs(fft2c(fine.astype(np.complex64)))
    yy, xx = np.mgrid[:big, :big] - big // 2
    assert spec[np.hypot(yy, xx) > n / 2].max() > 1e-2 * spec.max()  # energy beyond the n-grid
    assert np.abs(fine - aliased).max() > 0.1 * fine.max()
    # the n-grid samples of the fine intensity are the field's own |·|²
    step = big // n
    assert np.allclose(fine[::step, ::step], np.abs(field) ** 2, atol=1e-4 * fine.max())
