"""Report figures: the recovery drawn pixel for pixel, phase masked by amplitude, zooms on the finest features."""

from __future__ import annotations

import numpy as np
import pytest

from cca_cli.report import figures
from cca_cli.report.regions import Region, bar_region, detail_region, usaf_region
from cca_cli.targets import resolution_chart, usaf1951_chart


def _png(path) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(path)[..., :3]


def _panel(image: np.ndarray, size: int, title_lines: int = 1) -> np.ndarray:
    """The image axes of a one-panel figure (the layout of figures._draw)."""
    top = 14 + 18 * title_lines + figures._TITLE
    return image[top:top + size, figures._LEFT:figures._LEFT + size]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    rng = np.random.default_rng(0)
    m = 96
    amplitude = np.zeros((m, m), np.float32)
    amplitude[20:70, 10:60] = rng.uniform(0.5, 1.0, (50, 50))      # an object on a dark background
    obj = (amplitude * np.exp(1j * rng.uniform(-3, 3, (m, m)))).astype(np.complex64)
    centres = np.array([[y, x] for y in (-6.0, 0.0, 6.0) for x in (-6.0, 0.0, 6.0)])
    region = Region((0.25, 0.5, 0.25, 0.5), "test region")
    out = tmp_path_factory.mktemp("figures")
    paths = figures.write_figures(
        out, observed=np.abs(obj[::2, ::2]) ** 2, recovered_object=obj, spectrum=np.fft.fftshift(np.fft.fft2(obj)),
        pupil_centres_px=centres, pupil_radius_px=5.0, field_width_m=12e-3, residual=np.array([0.5, 0.1]),
        change=np.array([1.0, 0.1]), summary={"sar": 2.0, "tol": 0.2, "stopped_by": "tol"}, units="counts/s",
        region=region, grid_indices=np.indices((3, 3)).reshape(2, -1).T)
    return out, paths, obj


def test_report_writes_the_figures(written):
    out, paths, _ = written
    assert {p.name for p in paths} == {"observed_centre.png", "recovered_magnitude.png", "recovered_phase.png",
                                       "observed_vs_recovered.png", "spectrum.png", "convergence.png"}


def test_the_recovery_is_drawn_pixel_for_pixel(written):
    out, _, obj = written
    k = figures.magnification(obj.shape[-1])
    assert k == 5
    panel = _panel(_png(out / "recovered_magnitude.png"), obj.shape[-1] * k)[..., 0]
    amplitude = np.abs(obj)
    expected = np.clip(amplitude / np.percentile(amplitude, 99.9), 0, 1)
    # every recovery pixel is a k x k block of one grey level equal to its value (8-bit PNG),
    # except where the zoom region's outline (rows and columns 24 and 48) is drawn on top
    blocks = panel.reshape(96, k, 96, k).transpose(0, 2, 1, 3).reshape(96, 96, k * k)
    outline = np.zeros((96, 96), bool)
    outline[[23, 24, 47, 48], 23:49] = outline[23:49, [23, 24, 47, 48]] = True
    assert np.all(np.abs(blocks[~outline] - expected[~outline][:, None]) <= 1.5 / 255)


def test_phase_is_black_where_there_is_no_amplitude(written):
    out, _, obj = written
    k = figures.magnification(obj.shape[-1])
    panel = _panel(_png(out / "recovered_phase.png"), obj.shape[-1] * k, title_lines=2)[::k, ::k]
    dark = np.abs(obj) == 0
    assert np.all(panel[dark] == 0)                       # masked background
    assert np.all(panel[~dark].max(axis=-1) > 0.5)        # the hsv colours of the object are bright


def test_bar_region_holds_the_finest_resolved_groups():
    chart = resolution_chart(256, widths=(12, 8, 6, 4, 3, 2))
    region = bar_region(chart.groups, 3, 256)
    y0, y1, x0, x1 = region.pixels(256)
    for group in chart.groups:
        gy0, gy1, gx0, gx1 = group.box
        inside = y0 <= gy0 and gy1 <= y1 and x0 <= gx0 and gx1 <= x1
        if group.width_px == 3:
            assert inside
        if group.width_px >= 8:
            assert not inside
    assert region.label.startswith("3 px bars (finest resolved)")
    assert y1 - y0 == x1 - x0 and (y1 - y0) <= 0.4 * 256


def test_usaf_region_holds_the_finest_resolved_element():
    chart = usaf1951_chart(512, pixel_pitch_m=25e-6, groups=(0, 1))
    region = usaf_region(chart, {"group": 1, "element": 3})
    y0, y1, x0, x1 = region.pixels(chart.size)
    element = next(e for e in chart.elements if (e.group, e.element) == (1, 3))
    for box in (element.horizontal.box, element.vertical.box):
        assert y0 <= box[0] and box[1] <= y1 and x0 <= box[2] and box[3] <= x1
    assert "group 1 element 3 (finest resolved)" in region.label


def test_detail_region_finds_the_fine_structure():
    rng = np.random.default_rng(1)
    image = np.ones((128, 128), np.float32)
    image[70:100, 30:60] += rng.normal(0, 0.5, (30, 30)).astype(np.float32)   # fine detail, lower left
    y0, y1, x0, x1 = detail_region(image, cutoff_px=8).pixels(128)
    assert y0 <= 85 <= y1 and x0 <= 45 <= x1
    assert y1 - y0 == x1 - x0 == 32


def test_the_sweep_montage_shows_every_panel_on_the_truth_s_grey_scale(tmp_path, monkeypatch):
    """A recovery that lost brightness must look dimmer than the truth, not be stretched to the same white."""
    import numpy as np

    from cca_cli.report import sweep_figures

    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 1, (64, 64))
    crops = [({"x": 0.6, "group": None, "rmse_recovered": 0.1},
              {"truth": truth, "observed": 0.8 * truth, "recovered": 0.5 * truth})]
    data = sweep_figures.SweepPlotData(study="overlap", x="array.overlap", group=None,
                                       series=[{"x": 0.6, "group": None}], crops=crops)
    limits = {}

    def keep(plt, fig, path, **kw):
        limits[path.name] = [ax.images[0].get_clim() for ax in fig.axes if ax.images]
        plt.close(fig)
        return path

    monkeypatch.setattr(sweep_figures, "_save", keep)
    sweep_figures.plot_sweep(data, tmp_path)
    top = np.percentile(truth[16:48, 16:48], 99.5)
    assert limits["montage.png"] == [(0.0, top)] * 3    # truth, observed and recovered alike
