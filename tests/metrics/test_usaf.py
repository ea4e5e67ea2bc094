"""USAF 1951 reading: MTF20 rule, gains, and the three-bar criterion against the area mean."""

import json

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from cca_cli.metrics import UsafReading, bar_contrast, three_bar_contrast, usaf_gain, usaf_resolution
from cca_cli.metrics.usaf import CRITERIA
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


# --- three-bar criterion (default) -------------------------------------------------


def _paint(chart, bar_levels, gap_levels):
    """Every element's bars/gaps painted with the given per-bar / per-gap intensities."""
    image = np.zeros(chart.image.shape, np.float32)
    for el in chart.elements:
        for group in (el.horizontal, el.vertical):
            for (y0, y1, x0, x1), v in zip(group.bar_boxes, bar_levels):
                image[y0:y1, x0:x1] = v
            for (y0, y1, x0, x1), v in zip(group.gap_boxes, gap_levels):
                image[y0:y1, x0:x1] = v
    return image


def test_three_bar_is_default(chart):
    image = gaussian_filter(chart.image, 2.0)
    default = usaf_resolution(image, chart)
    explicit = usaf_resolution(image, chart, criterion="three_bar")
    assert default.criterion == "three_bar" and default.to_dict()["criterion"] == "three_bar"
    assert [c.to_dict() for c in default.contrasts] == [c.to_dict() for c in explicit.contrasts]
    el = chart.elements[3]
    assert default.contrasts[3].vertical == pytest.approx(three_bar_contrast(image, el.vertical))
    area = usaf_resolution(image, chart, criterion="area_mean")
    assert area.criterion == "area_mean"
    assert area.contrasts[3].vertical == pytest.approx(bar_contrast(image, el.vertical))
    assert CRITERIA == ("three_bar", "area_mean")


def test_three_bar_blurred_vs_sharp(chart):
    sharp = usaf_resolution(chart.image, chart, criterion="three_bar")
    assert (sharp.group, sharp.element) == (chart.elements[-1].group, chart.elements[-1].element)
    assert all(c.horizontal == 1.0 and c.vertical == 1.0 for c in sharp.contrasts)
    readings = [usaf_resolution(gaussian_filter(chart.image, s), chart) for s in (3.0, 5.0, 8.0)]
    lps = [r.lp_per_mm for r in readings]
    assert all(lp is not None for lp in lps)
    assert sharp.lp_per_mm > lps[0] > lps[1] > lps[2]
    for r in readings:  # every coarser element resolved, the next finer one not
        idx = [(c.group, c.element) for c in r.contrasts].index((r.group, r.element))
        assert all(min(c.horizontal, c.vertical) >= 0.2 for c in r.contrasts[: idx + 1])
        assert min(r.contrasts[idx + 1].horizontal, r.contrasts[idx + 1].vertical) < 0.2
    assert usaf_gain(readings[2], sharp) > usaf_gain(readings[0], sharp) > 1.0


def test_fused_bars_unresolved_by_three_bar_only(chart):
    # bars 2 and 3 fused (second gap as bright as the bars): bright on average, not three bars
    fused = _paint(chart, (1.0, 1.0, 1.0), (0.0, 1.0))
    area = usaf_resolution(fused, chart, criterion="area_mean")
    three = usaf_resolution(fused, chart)
    assert area.lp_per_mm == chart.elements[-1].lp_per_mm
    assert all(c.horizontal == pytest.approx(1 / 3) for c in area.contrasts)
    assert not three.resolved
    assert all(c.horizontal == 0.0 and c.vertical == 0.0 for c in three.contrasts)


def test_blob_unresolved_by_three_bar_only(chart):
    # one bright blob on the centre bar with faint outer bars barely above the gaps
    blob = _paint(chart, (0.3, 1.0, 0.3), (0.25, 0.25))
    area = usaf_resolution(blob, chart, criterion="area_mean")
    three = usaf_resolution(blob, chart)
    assert area.resolved and min(area.contrasts[0].horizontal, area.contrasts[0].vertical) > 0.3
    assert not three.resolved
    assert three.contrasts[0].horizontal == pytest.approx(0.05 / 0.55, rel=1e-5)
    # a gap brighter than a neighbour reads negative
    assert three_bar_contrast(_paint(chart, (1.0, 0.2, 1.0), (0.3, 0.0)), chart.elements[0].vertical) < 0


def test_three_bar_reads_central_part_of_bars(chart):
    el = chart.elements[0]
    image = np.array(chart.image)
    for y0, y1, x0, x1 in el.vertical.gap_boxes:  # light leaking into the gap ends (10 % of the length)
        n = max(1, (y1 - y0) // 10)
        image[y0:y0 + n, x0:x1] = 1.0
        image[y1 - n:y1, x0:x1] = 1.0
    assert three_bar_contrast(image, el.vertical) == 1.0
    assert bar_contrast(image, el.vertical) < 1.0


def test_three_bar_rejects_bad_input(chart):
    with pytest.raises(ValueError, match="criterion"):
        usaf_resolution(chart.image, chart, criterion="rayleigh")
    with pytest.raises(ValueError, match="BarGroup"):
        three_bar_contrast(chart.image, chart.elements[0])
    with pytest.raises(ValueError, match="complex|real"):
        three_bar_contrast(chart.image.astype(np.complex64), chart.elements[0].vertical)
