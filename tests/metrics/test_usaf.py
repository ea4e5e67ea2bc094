import json

import pytest
from scipy.ndimage import gaussian_filter

from cca_cli.metrics import UsafReading, usaf_gain, usaf_resolution
from cca_cli.targets import usaf1951_chart


@pytest.fixture(scope="module")
def chart():
    return usaf1951_chart(512, pixel_pitch_m=10e-6)


def test_sharp_chart_resolves_finest(chart):
    reading = usaf_resolution(chart.image**2, chart)
    finest = chart.elements[-1]
    assert (reading.group, reading.element) == (finest.group, finest.element)
    assert reading.lp_per_mm == finest.lp_per_mm and reading.width_px == finest.width_px
    assert len(reading.contrasts) == len(chart.elements)
    assert all(c.horizontal == 1.0 and c.vertical == 1.0 for c in reading.contrasts)
    d = reading.to_dict()
    assert json.loads(json.dumps(d)) == d


def test_blurred_chart_resolves_coarser(chart):
    sharp = usaf_resolution(chart.image, chart)
    blurred = usaf_resolution(gaussian_filter(chart.image, 3.0), chart)
    assert blurred.resolved
    assert blurred.lp_per_mm < sharp.lp_per_mm
    assert blurred.width_px > sharp.width_px
    # MTF20 rule: every coarser element resolved, the next finer one not
    idx = [(c.group, c.element) for c in blurred.contrasts].index((blurred.group, blurred.element))
    assert all(min(c.horizontal, c.vertical) >= 0.2 for c in blurred.contrasts[: idx + 1])
    nxt = blurred.contrasts[idx + 1]
    assert min(nxt.horizontal, nxt.vertical) < 0.2
    gain = usaf_gain(blurred, sharp)
    assert gain == pytest.approx(sharp.lp_per_mm / blurred.lp_per_mm)
    assert gain > 1.0


def test_unresolved_and_gain_none(chart):
    flat = usaf_resolution(chart.image * 0 + 1.0, chart)
    assert not flat.resolved and flat.group is None and flat.lp_per_mm is None
    assert flat.to_dict()["lp_per_mm"] is None
    sharp = usaf_resolution(chart.image, chart)
    assert usaf_gain(flat, sharp) is None and usaf_gain(sharp, flat) is None
    assert usaf_gain(sharp, sharp) == 1.0
    assert isinstance(sharp, UsafReading)


def test_shape_mismatch(chart):
    with pytest.raises(ValueError, match=r"\(512, 512\).*\(256, 256\)"):
        usaf_resolution(chart.image[:256, :256], chart)
