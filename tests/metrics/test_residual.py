"""Split residual: one global scale, bright-field / dark-field subsets."""

import numpy as np
import pytest

from cca_cli.metrics.residual import split_amplitude_residual


def test_a_scaled_exact_model_has_zero_residual():
    rng = np.random.default_rng(0)
    data = rng.random((6, 4, 4))
    r = split_amplitude_residual(3.0 * data, data, [True, True, False, False, False, False])
    assert r.scale == pytest.approx(1 / 3)
    assert r.all == pytest.approx(0, abs=1e-12) and r.dark_field == pytest.approx(0, abs=1e-12)


def test_the_scale_is_global_not_per_subset():
    data = np.ones((2, 3, 3))
    data[1] *= 0.1                              # a dim dark-field frame
    model = np.stack([np.ones((3, 3)), np.full((3, 3), 0.2)])  # twice too bright in the dark frame
    r = split_amplitude_residual(model, data, [True, False])
    s = (9 * 1 + 9 * 0.02) / (9 + 9 * 0.04)
    assert r.scale == pytest.approx(s)
    assert r.bright_field == pytest.approx(abs(s - 1))
    assert r.dark_field == pytest.approx(abs(0.2 * s - 0.1) / 0.1)
    total = np.sqrt((9 * (s - 1) ** 2 + 9 * (0.2 * s - 0.1) ** 2) / (9 + 9 * 0.01))
    assert r.all == pytest.approx(total)
    assert r.per_capture == pytest.approx([abs(s - 1), abs(0.2 * s - 0.1) / 0.1])


def test_empty_subset_and_bad_input():
    data = np.ones((2, 2, 2))
    assert np.isnan(split_amplitude_residual(data, data, [True, True]).dark_field)
    with pytest.raises(ValueError, match="one entry per capture"):
        split_amplitude_residual(data, data, [True])
    with pytest.raises(ValueError, match="shape"):
        split_amplitude_residual(data[:, :1], data, [True, False])
    with pytest.raises(ValueError, match="zero"):
        split_amplitude_residual(0 * data, data, [True, False])
