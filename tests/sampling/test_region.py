"""Recovering a rectangle of a larger scene on the square periodic grid: embedding, and what the edge leaks."""

from pathlib import Path

import numpy as np
import pytest

from cca_cli.config.load import parse_config
from cca_cli.config.model import PaddingSection, ReconstructSection
from cca_cli.metrics import rmse
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.report.summary import band_limited_truth, on_grid
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.region import plan_embedding, resolution_cell_px
from cca_cli.library.data import CaptureSet
from cca_cli.workflows.recovery import embed_region, reconstruct_captures
from cca_cli.stages.simulate import simulate


def test_plan_and_embed():
    assert plan_embedding((30, 50), pupil_radius_px=5.0).apodize_px == 0  # no taper by default
    region = plan_embedding((30, 50), pupil_radius_px=5.0, apodize_px=5)  # cell 5 px: guard 20
    assert region.guard_px == 20 and region.apodize_px == 5
    assert region.size >= 50 + 40 and region.size % 2 == 0
    images = np.random.default_rng(0).uniform(1, 2, (2, 30, 50)).astype(np.float32)
    padded, weights = region.embed(images, np.full((2, 30, 50), 0.5, np.float32))
    assert padded.shape == weights.shape == (2, region.size, region.size)
    np.testing.assert_array_equal(region.crop(padded), images)
    oy, ox = region.offset_yx
    inner = region.crop(weights)
    assert weights.sum() == pytest.approx(inner.sum()) and (inner > 0).all()
    assert inner[0, 15, 25] == 0.5 and inner[0, 0, 25] < 0.1 * 0.5  # apodized at the edge
    # The guard band starts as the region mirrored, fading to the mean at the grid's edge.
    assert padded[0, oy - 1, ox + 10] == pytest.approx(images[0, 0, 10], rel=0.05)
    assert padded[0, 0, 0] == pytest.approx(images[0].mean(), rel=1e-5)
    y0, x0, h, w = region.hires_box(2 * region.size)
    assert (h, w) == (60, 100) and (y0, x0) == (2 * oy, 2 * ox)


def test_square_periodic_images_are_left_alone():
    geometry = simulate(parse_config({"scene": {"kind": "natural", "size_px": 64, "field_width_m": 8e-3}, "array": {"grid": 3},
                                      "optics": {"aperture_diameter_m": 45e-3}, "noise": {"model": "none"}})).geometry
    captures = CaptureSet(intensity=np.ones((9, 64, 64), np.float32), geometry=geometry)
    same, region = embed_region(captures, ReconstructSection(), source=Path("x"))
    assert region is None and same is captures
    with pytest.raises(Exception, match="must be square"):
        embed_region(CaptureSet(intensity=np.ones((9, 64, 48), np.float32), geometry=geometry),
                     ReconstructSection(padding=PaddingSection(mode="off")), source=Path("x"))


@pytest.fixture(scope="module")
def two_scenes():
    """A portrait, and the same portrait with a fingerprint outside a 48 x 72 window; 5 x 5 scan, no noise."""
    base = {"optics": {"wavelength_m": 550e-9, "focal_length_m": 0.8, "aperture_diameter_m": 45e-3,
                       "pixel_pitch_m": 2e-6, "distance_m": 50.0},
            "scene": {"kind": "natural", "size_px": 96, "field_width_m": 12e-3},
            "array": {"grid": 5, "overlap": 0.61}, "noise": {"model": "none"}}
    sim = simulate(parse_config(base))
    other = simulate(parse_config({**base, "scene": {**base["scene"], "kind": "fingerprint"}}))
    return sim, other


def _window_recovery(sim, field, window, mode):
    y0, x0, h, w = window
    layout = sim.layout
    model = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px))
    images = fft.fourier_resample(model.sensor_intensity(fft.fft2c(field)), 96)
    geometry = with_field_width(sim.geometry, sim.geometry.field_width_m * w / 96)
    captures = CaptureSet(intensity=images[:, y0:y0 + h, x0:x0 + w], geometry=geometry, boundary="open")
    section = ReconstructSection(iterations=60, tol=0.0, padding=PaddingSection(mode=mode))
    obj = reconstruct_captures(captures, section, source=Path("window")).intensity
    truth = band_limited_truth(field, sim.geometry)[y0:y0 + h, x0:x0 + w]
    return on_grid(obj.astype(np.float32), (h, w)), truth, resolution_cell_px(w, geometry.pupil_radius_px)


def _mixed(sim, other, window):
    y0, x0, h, w = window
    inside = np.zeros(sim.scene.field.shape, bool)
    inside[y0:y0 + h, x0:x0 + w] = True
    return np.where(inside, sim.scene.field, other.scene.field).astype(np.complex64)


def test_guard_band_beats_the_periodic_crop(two_scenes):
    sim, other = two_scenes
    window = (24, 24, 48, 48)
    mixed = _mixed(sim, other, window)
    padded, truth, _ = _window_recovery(sim, mixed, window, "auto")
    periodic, _, _ = _window_recovery(sim, mixed, window, "off")
    assert rmse(padded, truth) < 0.6 * rmse(periodic, truth), (rmse(padded, truth), rmse(periodic, truth))


def test_what_the_edge_leaks_into_a_rectangle_is_bounded(two_scenes):
    # Same scene inside a 48 x 72 window, different outside: the two recoveries differ mostly at the edge.
    sim, other = two_scenes
    window = (24, 12, 48, 72)
    first, truth, cell = _window_recovery(sim, sim.scene.field, window, "auto")
    second, _, _ = _window_recovery(sim, _mixed(sim, other, window), window, "auto")
    assert rmse(first, truth) < 0.03
    leak = (first - second) / first.max()
    h, w = leak.shape
    depth = np.minimum(np.minimum(np.arange(h), np.arange(h)[::-1])[:, None],
                       np.minimum(np.arange(w), np.arange(w)[::-1])[None, :]) / cell
    edge = np.sqrt(np.mean(leak[depth < 1] ** 2))
    inner = np.sqrt(np.mean(leak[depth >= 2] ** 2))
    assert inner < 0.06 and inner < 0.7 * edge, (edge, inner)
