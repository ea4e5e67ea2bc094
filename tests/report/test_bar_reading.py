"""Three-bar readings of a recorded target at boxes given in frame pixels."""

import numpy as np
import pytest
from pydantic import ValidationError

from cca_cli.config.model import ReportSection
from cca_cli.metrics.bars import usaf_period_m
from cca_cli.report.bar_reading import FrameToRecovery, finest_resolved, read_elements


def _three_bars(size: int, period_px: float, centre_x: float, depth: float) -> np.ndarray:
    """Amplitude 1 with three dark vertical bars (half a period wide) of relative depth ``depth``."""
    x = np.arange(size)[None, :] - centre_x
    bars = (np.abs(x) < 1.5 * period_px) & (np.mod(x + 0.25 * period_px, period_px) < 0.5 * period_px)
    image = np.ones((size, size))
    image[:, :] -= depth * np.broadcast_to(bars, (size, size))
    return image


def test_frame_pixels_map_onto_a_padded_recovery_region():
    # frames of 32 px placed at (8, 8) on a 48 px sensor grid, recovered on 144 px, region cut at (24, 24)
    to_recovery = FrameToRecovery(48, 144, offset_yx=(8, 8), origin_yx=(24, 24))
    assert to_recovery.scale == 3
    assert to_recovery(16, 0) == pytest.approx(72 + (8 + 16 - 24) * 3 - 24)
    assert to_recovery.box((0, 32, 0, 32)) == pytest.approx((0, 96, 0, 96))


def test_sharp_bars_read_high_contrast_and_blurred_bars_do_not():
    pixel_m = 0.5e-6
    period = usaf_period_m(9, 1) / pixel_m  # 3.9 px per period on the recovered grid
    amplitude = _three_bars(96, period, 48.0, 0.8)
    spectrum = np.fft.fftshift(np.fft.fft2(amplitude))
    k = np.hypot(*np.meshgrid(np.arange(96) - 48, np.arange(96) - 48, indexing="ij"))
    blurred = np.fft.ifft2(np.fft.ifftshift(spectrum * (k < 96 / period * 0.8))).real  # below the bar frequency
    elements = [{"element": "G9E1", "profile": "col", "box_px": [30.0, 66.0, 40.0, 56.0]}]
    identity = FrameToRecovery(96, 96)
    sharp = read_elements(amplitude.astype(np.complex64), np.clip(blurred, 0, None) ** 2, elements, pixel_m, identity)
    reading = sharp["G9E1 col"]
    assert reading["lp_per_mm"] == pytest.approx(512.0)
    assert reading["period_px"] == pytest.approx(period, rel=1e-3)
    assert reading["recovered"] > 0.5
    assert reading["observed"] is None or reading["observed"] < 0.1
    assert finest_resolved(sharp, "recovered") == "G9E1" and finest_resolved(sharp, "observed") is None


def test_bar_elements_are_checked_when_the_config_is_read():
    good = ReportSection(bar_elements=[{"element": "G8E2", "profile": "row", "box_px": [1, 5, 2, 6]}])
    assert good.bar_elements[0].box_px == [1, 5, 2, 6]
    for bad, says in (({"element": "G8E7", "profile": "row", "box_px": [1, 5, 2, 6]}, "element"),
                      ({"element": "G8E2", "profile": "diagonal", "box_px": [1, 5, 2, 6]}, "profile"),
                      ({"element": "G8E2", "profile": "row", "box_px": [5, 1, 2, 6]}, "y0 < y1")):
        with pytest.raises(ValidationError, match=says):
            ReportSection(bar_elements=[bad])


def test_offset_to_observed_finds_a_sub_pixel_shift_of_the_recovery():
    from cca_cli.report.bar_reading import offset_to_observed

    rng = np.random.default_rng(2)
    n = 64
    ky, kx = np.meshgrid(np.fft.fftfreq(n) * n, np.fft.fftfreq(n) * n, indexing="ij")
    spectrum = np.fft.fft2(rng.standard_normal((n, n))) * (np.hypot(ky, kx) < 12)
    observed = np.fft.ifft2(spectrum).real
    shifted = np.fft.ifft2(spectrum * np.exp(-2j * np.pi * (1.3 * ky - 2.6 * kx) / n)).real  # moved by (1.3, -2.6)
    dy, dx = offset_to_observed(shifted, observed, 10.0)
    assert dy == pytest.approx(1.3, abs=0.15) and dx == pytest.approx(-2.6, abs=0.15)
