import json

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from cca_cli.metrics import (
    ContrastTable,
    bar_contrast,
    contrast_table,
    mtf_limit,
    resolution_gain,
)
from cca_cli.targets import chart_groups_for_grid, resolution_chart


@pytest.fixture(scope="module")
def chart():
    return resolution_chart()


def _coherent_lowpass_intensity(amplitude, radius):
    n = amplitude.shape[0]
    f = np.fft.fftfreq(n) * n
    pupil = (f[:, None] ** 2 + f[None, :] ** 2) <= radius**2
    field = np.fft.ifft2(np.fft.fft2(amplitude) * pupil)
    return (np.abs(field) ** 2).astype(np.float32)


def test_perfect_chart(chart):
    intensity = chart.image**2
    table = contrast_table(intensity, chart)
    assert table.widths_px.tolist() == list(chart.widths)
    assert np.all(table.horizontal == 1.0) and np.all(table.vertical == 1.0)
    assert mtf_limit(table) == 1
    assert bar_contrast(intensity, chart.groups[0]) == 1.0


def test_gaussian_blur(chart):
    blurred = gaussian_filter(chart.image, sigma=2.0)
    table = contrast_table(blurred, chart)
    limit = mtf_limit(table)
    assert limit is not None and limit > 1
    # contrast decreases with decreasing width while the bars are still resolved
    resolved = table.widths_px >= limit
    for arr in (table.horizontal, table.vertical):
        assert np.all(np.diff(arr[resolved]) < 0)
        assert arr[0] < 1.0
    assert table.minimum()[~resolved][0] < 0.2
    # a stronger blur gives a coarser limit
    assert mtf_limit(contrast_table(gaussian_filter(chart.image, 4.0), chart)) > limit


def test_all_wider_rule():
    table = ContrastTable(
        widths_px=np.array([8, 6, 4, 2, 1]),
        horizontal=np.array([0.9, 0.8, 0.1, 0.7, 0.6]),
        vertical=np.array([0.9, 0.8, 0.9, 0.7, 0.6]),
    )
    assert mtf_limit(table) == 6  # width 4 fails, so 2 and 1 do not count
    assert mtf_limit(table, threshold=0.05) == 1
    assert np.allclose(table.minimum(), [0.9, 0.8, 0.1, 0.7, 0.6])
    d = table.to_dict()
    assert json.loads(json.dumps(d)) == d
    assert d["widths_px"] == [8, 6, 4, 2, 1] and isinstance(d["horizontal"][0], float)
    fail_first = ContrastTable(
        widths_px=np.array([8, 6]), horizontal=np.array([0.9, 0.9]), vertical=np.array([0.1, 0.9])
    )
    assert mtf_limit(fail_first) is None


def test_uniform_and_zero_images(chart):
    uniform = np.full(chart.image.shape, 0.37, dtype=np.float32)
    table = contrast_table(uniform, chart)
    assert np.allclose(table.horizontal, 0.0) and np.allclose(table.vertical, 0.0)
    assert mtf_limit(table) is None
    assert bar_contrast(np.zeros(chart.image.shape), chart.groups[0]) == 0.0


def test_contrast_reversal(chart):
    inverted = 1.0 - chart.image
    assert bar_contrast(inverted, chart.groups[0]) == -1.0


def test_coherent_lowpass_limits(chart):
    # coherent cutoff period 512/21 = 24.4 px -> only bars >= ~12 px survive
    observed = mtf_limit(contrast_table(_coherent_lowpass_intensity(chart.image, 21), chart))
    assert observed is not None and observed >= 12, observed
    # synthetic aperture radius 184 -> 2 px bars (period 4 px) resolved
    recovered = mtf_limit(contrast_table(_coherent_lowpass_intensity(chart.image, 184), chart))
    assert recovered is not None and recovered <= 2, recovered


def test_coherent_gain(chart):
    obs = mtf_limit(contrast_table(_coherent_lowpass_intensity(chart.image, 21), chart))
    rec = mtf_limit(contrast_table(_coherent_lowpass_intensity(chart.image, 184), chart))
    assert resolution_gain(obs, rec) >= 6.0
    assert resolution_gain(None, rec) is None and resolution_gain(obs, None) is None
    assert resolution_gain(12, 2) == 6.0
    with pytest.raises(ValueError, match="recovered_limit"):
        resolution_gain(12, 0)


def test_other_grid(chart):
    up = np.kron(gaussian_filter(chart.image, 2.0), np.ones((2, 2), np.float32))
    t1 = contrast_table(gaussian_filter(chart.image, 2.0), chart)
    t2 = contrast_table(up, chart_groups_for_grid(chart, 1024))
    assert np.allclose(t1.horizontal, t2.horizontal, atol=1e-6)
    assert np.array_equal(t1.widths_px, t2.widths_px)


def test_shape_errors(chart):
    with pytest.raises(ValueError, match=r"\(512, 512\).*\(256, 256\)"):
        contrast_table(np.zeros((256, 256)), chart)
    with pytest.raises(ValueError, match=r"\(100, 100\)"):
        contrast_table(np.zeros((100, 100)), chart.groups)
    with pytest.raises(ValueError, match=r"\(100, 100\)"):
        bar_contrast(np.zeros((100, 100)), chart.groups[0])
    with pytest.raises(ValueError, match="2-D"):
        bar_contrast(np.zeros(10), chart.groups[0])
    with pytest.raises(ValueError, match="real"):
        bar_contrast(np.zeros((512, 512), complex), chart.groups[0])
    with pytest.raises(ValueError, match="vertical group"):
        contrast_table(chart.image, [g for g in chart.groups if g.orientation == "horizontal"])
    with pytest.raises(ValueError, match="threshold"):
        mtf_limit(contrast_table(chart.image, chart), threshold=float("nan"))
