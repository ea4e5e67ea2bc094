"""Three-bar profile reading: synthetic bars of known contrast, the ±25 % period rule, the table reader."""

import math

import numpy as np
import pytest

from cca_cli.metrics.bars import (
    BarElement,
    parse_element_table,
    read_bar_elements,
    three_bar_profile_contrast,
    usaf_period_m,
)


def bars_image(period, dark=0.2, bright=1.0, n=64, axis=1, start=10):
    """Three dark bars (half a period wide) across ``axis`` on a bright field."""
    coord = np.arange(n)
    profile = np.full(n, bright)
    for k in range(3):
        lo = start + k * period
        profile[(coord >= lo) & (coord < lo + period / 2)] = dark
    return np.tile(profile, (n, 1)) if axis == 1 else np.tile(profile[:, None], (1, n))


@pytest.mark.parametrize("axis", [0, 1])
def test_square_bars_give_the_michelson_contrast(axis):
    image = bars_image(8, dark=0.2, bright=1.0, axis=axis)
    box = (5, 45, 5, 45)
    c = three_bar_profile_contrast(image, box, 8.0, axis)
    assert c == pytest.approx((1.0 - 0.2) / (1.0 + 0.2), abs=1e-12)


def test_reading_along_the_wrong_axis_finds_nothing():
    image = bars_image(8, axis=1)
    assert math.isnan(three_bar_profile_contrast(image, (5, 45, 5, 45), 8.0, 0))


def test_minima_spaced_off_the_nominal_period_do_not_count():
    image = bars_image(8, axis=1)
    assert math.isnan(three_bar_profile_contrast(image, (5, 45, 5, 45), 12.0, 1))   # 8 is 33 % off 12
    assert not math.isnan(three_bar_profile_contrast(image, (5, 45, 5, 45), 9.5, 1))  # 16 % off


def test_smooth_bars_and_a_flat_image():
    x = np.arange(80)
    profile = 1.0 + 0.5 * np.cos(2 * np.pi * (x - 20) / 10.0 + np.pi)  # minima at 20, 30, 40, ...
    image = np.tile(profile, (30, 1))
    assert three_bar_profile_contrast(image, (0, 29, 15, 45), 10.0, 1) == pytest.approx(0.5, abs=1e-9)
    assert math.isnan(three_bar_profile_contrast(np.ones((30, 30)), (0, 29, 0, 29), 8.0, 1))


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="box"):
        three_bar_profile_contrast(np.ones((10, 10)), (0, 20, 0, 5), 3.0, 1)
    with pytest.raises(ValueError, match="axis"):
        three_bar_profile_contrast(np.ones((10, 10)), (0, 9, 0, 9), 3.0, 2)
    with pytest.raises(ValueError, match="real 2-D"):
        three_bar_profile_contrast(np.ones((10, 10), complex), (0, 9, 0, 9), 3.0, 1)


TABLE = """
| element | lp/mm | profile | box rows, cols (low-res px) | centre C |
|---|---|---|---|---|
| G8E2 | 287 | col / row | 6.9–10.6, 17.9–23.1 / 11.6–16.4, 18.8–22.5 | – / – |
| G9E4 | 724 | col / row | 26.0–29.5, 12.4–14.9 / 23.5–25.9, 12.5–14.6 | – / – |
"""


def test_table_reader_and_period():
    elements = parse_element_table(TABLE)
    assert [(e.name, e.orientation) for e in elements] == [("G8E2", "col"), ("G8E2", "row"),
                                                          ("G9E4", "col"), ("G9E4", "row")]
    assert elements[1].box == (11.6, 16.4, 18.8, 22.5) and elements[1].axis == 0
    assert 1e-3 / usaf_period_m(9, 1) == pytest.approx(512.0)
    with pytest.raises(ValueError, match="G8E1"):
        parse_element_table("| G8E1 | 256 | row | 1–2 / 3–4 |")


def test_read_bar_elements_scales_boxes_and_periods():
    pixel = 1e-6
    period_px = usaf_period_m(8, 1) / pixel  # 3.9 table px
    image = bars_image(period_px * 4, axis=1, n=128, start=20)  # 4x finer image
    element = BarElement(8, 1, 1, (2.0, 28.0, 3.0, 28.0))
    out = read_bar_elements(image, [element], pixel, upsampling=4)
    assert out["G8E1 col"] == pytest.approx(0.8 / 1.2, abs=0.05)
