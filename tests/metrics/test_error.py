import numpy as np
import pytest

from cca_cli.metrics import amplitude_rmse, relative_error, rmse
from cca_cli.targets import resolution_chart


@pytest.fixture(scope="module")
def truth():
    return resolution_chart(128, widths=(8, 6, 4, 3, 2, 1)).image


def test_identical_is_zero(truth):
    assert rmse(truth, truth) == 0.0
    assert rmse(truth, truth, fit_scale=False) == 0.0
    assert amplitude_rmse(truth.astype(np.complex64), truth) == 0.0
    assert relative_error(truth, truth) == 0.0


def test_scale_invariance(truth):
    rng = np.random.default_rng(0)
    noisy = truth + 0.05 * rng.standard_normal(truth.shape).astype(np.float32)
    base = rmse(noisy, truth)
    assert base > 0.01
    assert rmse(7.5 * noisy, truth) == pytest.approx(base, rel=1e-9)
    assert rmse(3.0 * truth, truth) == pytest.approx(0.0, abs=1e-12)
    # without the fit: residual 2*truth, so RMSE = 2 * sqrt(fill fraction) / 1
    assert rmse(3.0 * truth, truth, fit_scale=False) == pytest.approx(2 * np.sqrt(truth.mean()))
    # amplitude metric ignores phase and a global amplitude scale
    phase = np.exp(1j * rng.uniform(0, 2 * np.pi, truth.shape))
    assert amplitude_rmse(2.0 * truth * phase, truth) == pytest.approx(0.0, abs=1e-12)


def test_known_values():
    truth = np.array([[0.0, 2.0], [2.0, 0.0]])
    rec = np.array([[1.0, 2.0], [2.0, 1.0]])
    # no fit: sqrt((1 + 0 + 0 + 1) / 4) / max(truth) = sqrt(0.5) / 2
    assert rmse(rec, truth, fit_scale=False) == pytest.approx(np.sqrt(0.5) / 2)
    # fit: a = <rec,truth>/<rec,rec> = 8/10; residual = [0.8, -0.4, -0.4, 0.8]
    expected = np.sqrt((0.64 + 0.16 + 0.16 + 0.64) / 4) / 2
    assert rmse(rec, truth) == pytest.approx(expected)
    assert relative_error([3.0, 4.0], [0.0, 5.0]) == pytest.approx(np.sqrt(9 + 1) / 5)
    assert amplitude_rmse(-rec, truth, fit_scale=False) == pytest.approx(np.sqrt(0.5) / 2)


def test_float32_precision():
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.0, 1.0, (1024, 1024))
    rec = truth + 1e-3 * rng.standard_normal(truth.shape)
    r64 = rmse(rec, truth)
    r32 = rmse(rec.astype(np.float32), truth.astype(np.float32))
    assert r32 == pytest.approx(r64, rel=1e-3)
    assert isinstance(r32, float)
    # large offsets: float32 accumulation would lose the small difference
    big = 1000.0 + truth.astype(np.float32)
    expected = 0.01 / np.sqrt(np.mean((1000.0 + truth) ** 2))
    assert relative_error(big + np.float32(0.01), big) == pytest.approx(expected, rel=1e-2)


def test_errors(truth):
    with pytest.raises(ValueError, match=r"\(128, 128\).*\(64, 64\)|\(64, 64\).*\(128, 128\)"):
        rmse(np.zeros((64, 64)), truth)
    with pytest.raises(ValueError, match=r"\(3,\)"):
        relative_error(np.zeros(3), np.ones(4))
    bad = truth.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        rmse(bad, truth)
    with pytest.raises(ValueError, match="truth"):
        rmse(truth, np.zeros_like(truth))
    with pytest.raises(ValueError, match="real"):
        rmse(truth.astype(complex), truth)
    with pytest.raises(ValueError, match="b"):
        relative_error(truth, np.zeros_like(truth))
