import itertools

import numpy as np
import pytest

from cca_cli.targets import (
    BarChart,
    BarGroup,
    chart_groups_for_grid,
    resolution_chart,
    usaf1951_chart,
    usaf_lp_per_mm,
)

DEFAULT = (20, 18, 16, 14, 12, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1)


@pytest.fixture(scope="module")
def chart():
    return resolution_chart()


def _gap(a, b):
    """Chebyshev-style separation of two half-open boxes (negative if overlapping)."""
    gy = max(b[0] - a[1], a[0] - b[1])
    gx = max(b[2] - a[3], a[2] - b[3])
    return max(gy, gx)


def _check_layout(ch: BarChart, widths):
    size = ch.image.shape[0]
    assert ch.image.shape == (size, size)
    assert ch.image.dtype == np.float32
    assert set(np.unique(ch.image).tolist()) == {0.0, 1.0}
    assert ch.widths == tuple(sorted(widths, reverse=True))
    assert len(ch.groups) == 2 * len(widths)
    keys = {(g.width_px, g.orientation) for g in ch.groups}
    assert keys == {(w, o) for w in widths for o in ("horizontal", "vertical")}
    for g in ch.groups:
        y0, y1, x0, x1 = g.box
        assert min(y0, x0) >= 4 and y1 <= size - 4 and x1 <= size - 4
        assert len(g.bar_boxes) == 3 and len(g.gap_boxes) == 2
        axis = g.axis
        for b in g.bar_boxes + g.gap_boxes:
            # inside the group box, requested width across the bars, common length
            assert y0 <= b[0] < b[1] <= y1 and x0 <= b[2] < b[3] <= x1
            across = b[1] - b[0] if axis == 0 else b[3] - b[2]
            along = b[3] - b[2] if axis == 0 else b[1] - b[0]
            assert across == g.width_px
            assert along == max(5 * g.width_px, 7)
        for b in g.bar_boxes:
            assert np.all(ch.image[b[0]:b[1], b[2]:b[3]] == 1.0)
        for b in g.gap_boxes:
            assert np.all(ch.image[b[0]:b[1], b[2]:b[3]] == 0.0)
    # groups do not overlap and keep the quiet margin
    for a, b in itertools.combinations(ch.groups, 2):
        assert _gap(a.box, b.box) >= max(a.width_px, b.width_px, 4), (a, b)
    # nothing is drawn outside the bar boxes
    mask = np.zeros(ch.image.shape, bool)
    for g in ch.groups:
        for b in g.bar_boxes:
            mask[b[0]:b[1], b[2]:b[3]] = True
    assert np.array_equal(mask, ch.image == 1.0)


def test_default_chart_layout(chart):
    assert chart.image.shape == (512, 512)
    _check_layout(chart, DEFAULT)
    assert chart.widths == DEFAULT


def test_orientation_semantics(chart):
    h = chart.group(20, "horizontal")
    v = chart.group(20, "vertical")
    # horizontal bars are stacked along y: bar boxes differ in y, share x range
    assert len({b[0] for b in h.bar_boxes}) == 3 and len({b[2] for b in h.bar_boxes}) == 1
    assert len({b[2] for b in v.bar_boxes}) == 3 and len({b[0] for b in v.bar_boxes}) == 1
    with pytest.raises(ValueError, match="orientation"):
        chart.group(13, "horizontal")


@pytest.mark.parametrize(
    "size, widths", [(128, (8, 6, 4, 3, 2, 1)), (64, (4, 3, 2, 1))]
)
def test_small_charts_fit(size, widths):
    _check_layout(resolution_chart(size, widths=widths), widths)


def test_too_many_widths_raises():
    with pytest.raises(ValueError, match="larger size"):
        resolution_chart(64, widths=(8, 6, 4, 3, 2, 1))
    with pytest.raises(ValueError, match="larger size"):
        resolution_chart(128, widths=DEFAULT)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"widths": ()}, "widths"),
        ({"widths": (3, 3)}, "unique"),
        ({"widths": (0,)}, "widths"),
        ({"widths": (2.5,)}, "widths"),
        ({"bars": 1}, "bars"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        resolution_chart(128, **kwargs)
    with pytest.raises(ValueError, match="size"):
        resolution_chart(0)


def test_deterministic_and_read_only(chart):
    again = resolution_chart()
    assert np.array_equal(again.image, chart.image) and again.groups == chart.groups
    with pytest.raises(ValueError):
        chart.image[0, 0] = 1.0


def test_bars_parameter():
    ch = resolution_chart(128, widths=(4, 2), bars=4)
    g = ch.group(4, "vertical")
    assert len(g.bar_boxes) == 4 and len(g.gap_boxes) == 3
    assert g.box[3] - g.box[2] == 7 * 4


def test_groups_for_grid(chart):
    doubled = chart_groups_for_grid(chart, 1024)
    for g, d in zip(chart.groups, doubled):
        assert isinstance(d, BarGroup)
        assert d.width_px == g.width_px and d.orientation == g.orientation
        assert d.box == tuple(2 * c for c in g.box)
        assert d.bar_boxes == tuple(tuple(2 * c for c in b) for b in g.bar_boxes)
    # non-integer factor: group boxes round outward and still cover the scaled box
    odd = chart_groups_for_grid(chart, 700)
    s = 700 / 512
    for g, d in zip(chart.groups, odd):
        assert d.box[0] <= g.box[0] * s and d.box[1] >= g.box[1] * s
        assert d.box[2] <= g.box[2] * s and d.box[3] >= g.box[3] * s
        for b in d.bar_boxes + d.gap_boxes:
            assert d.box[0] <= b[0] < b[1] <= d.box[1] and d.box[2] <= b[2] < b[3] <= d.box[3]
    with pytest.raises(ValueError, match="grid_size"):
        chart_groups_for_grid(chart, 0)


def test_usaf_lp_per_mm():
    assert usaf_lp_per_mm(0, 1) == 1.0
    assert usaf_lp_per_mm(1, 1) == 2.0
    assert usaf_lp_per_mm(2, 3) == pytest.approx(2 ** (2 + 2 / 6))
    assert usaf_lp_per_mm(-2, 1) == 0.25
    with pytest.raises(ValueError, match="element"):
        usaf_lp_per_mm(0, 7)


def test_usaf_chart_widths():
    pitch = 10e-6
    ch = usaf1951_chart(512, pixel_pitch_m=pitch)
    assert ch.image.shape == (512, 512) and ch.image.dtype == np.float32
    assert set(np.unique(ch.image).tolist()) == {0.0, 1.0}
    assert ch.pixel_pitch_m == pitch
    assert len(ch.elements) >= 6
    lps = [e.lp_per_mm for e in ch.elements]
    assert lps == sorted(lps)
    # the finest element that is >= 1 px wide at 10 um is group 3 element 6 (3.5 px)
    assert (ch.elements[-1].group, ch.elements[-1].element) == (3, 6)
    for e in ch.elements:
        exact = 1e-3 / (2 * usaf_lp_per_mm(e.group, e.element)) / pitch
        assert e.width_px == pytest.approx(exact)
        assert e.lp_per_mm == pytest.approx(usaf_lp_per_mm(e.group, e.element))
        for g, axis in ((e.horizontal, 0), (e.vertical, 1)):
            assert abs(g.width_px - exact) <= 0.5 + 1e-9
            for b in g.bar_boxes:
                assert (b[1] - b[0] if axis == 0 else b[3] - b[2]) == g.width_px
                assert np.all(ch.image[b[0]:b[1], b[2]:b[3]] == 1.0)
            for b in g.gap_boxes:
                assert np.all(ch.image[b[0]:b[1], b[2]:b[3]] == 0.0)
    boxes = [(g.box, g.width_px) for e in ch.elements for g in (e.horizontal, e.vertical)]
    for (a, wa), (b, wb) in itertools.combinations(boxes, 2):
        assert _gap(a, b) >= max(wa, wb, 4)


def test_usaf_chart_errors():
    with pytest.raises(ValueError, match="pixel_pitch_m"):
        usaf1951_chart(256, pixel_pitch_m=-1.0)
    with pytest.raises(ValueError, match="pixel_pitch_m"):
        usaf1951_chart(256, pixel_pitch_m=1e-2)  # every bar < 1 px (widest 0.2 px)
    with pytest.raises(ValueError, match="size"):
        usaf1951_chart(16, pixel_pitch_m=10e-6, groups=(0,))  # 50 px bars in 16 px


def test_a_chart_that_does_not_fit_names_the_config_keys():
    """The config's words, not the chart maker's: ``scene.size_px`` and ``scene.widths_px``."""
    from cca_cli.config.model import SceneSection
    from cca_cli.errors import ConfigError
    from cca_cli.workflows.scenes import build_scene

    with pytest.raises(ConfigError) as caught:
        build_scene(SceneSection(size_px=64, widths_px=[12, 10, 8]), 64)
    message = str(caught.value)
    assert message.startswith("scene.size_px: a chart with scene.widths_px [12, 10, 8]")
    assert message.endswith("use a larger scene.size_px or fewer/smaller scene.widths_px")
