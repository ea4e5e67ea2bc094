"""Non-square recoveries (a rectangle or a whole frame): zoom regions, figures, report numbers, API round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

import cca_cli as cca
from cca_cli.report import figures
from cca_cli.report.regions import Region, detail_region


def _png(path) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(path)[..., :3]


def test_a_region_is_cut_per_axis_from_an_h_by_w_image():
    image = np.arange(60 * 100, dtype=np.float32).reshape(60, 100)
    region = Region((0.5, 1.0, 0.2, 0.5), "lower band")
    assert region.pixels(image.shape) == (30, 60, 20, 50)
    assert region.crop(image).shape == (30, 30)            # half the height, 30 % of the width: square here
    assert region.crop(image)[0, 0] == image[30, 20]
    assert region.pixels(100) == (50, 100, 20, 50)         # a bare side still means a square grid


def test_detail_region_on_a_wide_image_is_square_in_pixels_and_finds_the_detail():
    rng = np.random.default_rng(3)
    rows, cols = 64, 160
    image = np.ones((rows, cols), np.float32)
    image[24:44, 112:132] += rng.normal(0, 0.5, (20, 20)).astype(np.float32)   # fine detail, right of centre
    region = detail_region(image, cutoff_px=10)
    y0, y1, x0, x1 = region.pixels(image.shape)
    assert y1 - y0 == x1 - x0 == 40                        # a quarter of the longer side, square in pixels
    assert y0 <= 34 <= y1 and x0 <= 122 <= x1
    fy0, fy1, fx0, fx1 = region.fractions
    assert (fy1 - fy0) * rows == pytest.approx((fx1 - fx0) * cols)


def test_sharpness_figures_of_a_rectangle_do_not_depend_on_its_orientation():
    from cca_cli.metrics.sharpness import rms_frequency, spectral_energy_beyond

    rows, cols = 48, 96
    y, x = np.indices((rows, cols))
    # 10 cycles across the width, 3 across the height (6 per width-length): a radius of 8 separates them
    wide = 1 + 0.5 * np.cos(2 * np.pi * 10 * x / cols) + 0.5 * np.cos(2 * np.pi * 3 * y / rows)
    tall = wide.T                                           # the same scene turned: its width is 48 px
    assert spectral_energy_beyond(wide, 8.0) == pytest.approx(0.5, abs=1e-6)
    assert spectral_energy_beyond(tall, 8.0 * rows / cols) == pytest.approx(0.5, abs=1e-6)
    assert spectral_energy_beyond(wide, 5.0) == pytest.approx(1.0) and spectral_energy_beyond(wide, 11.0) < 1e-9
    assert rms_frequency(wide, 1e-4) == pytest.approx(rms_frequency(tall, 1e-4))


@pytest.fixture(scope="module")
def wide_figures(tmp_path_factory):
    """The report figures of a 48 x 80 recovery cut from a 128-px grid, with every figure's axes limits recorded."""
    rng = np.random.default_rng(0)
    rows, cols = 48, 80
    amplitude = np.full((rows, cols), 0.2, np.float32)
    amplitude[10:30, 20:60] = rng.uniform(0.5, 1.0, (20, 40))
    obj = (amplitude * np.exp(1j * rng.uniform(-1, 1, (rows, cols)))).astype(np.complex64)
    spectrum = np.fft.fftshift(np.fft.fft2(rng.normal(size=(128, 128)))).astype(np.complex64)
    centres = np.array([[y, x] for y in (-8.0, 0.0, 8.0) for x in (-8.0, 0.0, 8.0)])
    limits = {}
    save = figures._save

    def recording_save(plt, fig, path, *, tight=True):
        limits[path.name] = [(ax.get_xlim(), ax.get_ylim()) for ax in fig.axes]
        limits[path.name + " titles"] = " ".join(ax.get_title() for ax in fig.axes)
        return save(plt, fig, path, tight=tight)

    out = tmp_path_factory.mktemp("wide")
    patch = pytest.MonkeyPatch()
    patch.setattr(figures, "_save", recording_save)
    try:
        figures.write_figures(
            out, observed=np.abs(obj) ** 2, recovered_object=obj, spectrum=spectrum, pupil_centres_px=centres,
            pupil_radius_px=6.0, field_width_m=8e-3, spectrum_field_width_m=8e-3 * 128 / cols,
            residual=np.array([0.5, 0.1]), change=np.array([1.0, 0.1]), summary={"sar": 2.0}, units="counts/s",
            region=Region((0.25, 0.75, 0.3, 0.6), "test"), grid_indices=np.indices((3, 3)).reshape(2, -1).T)
    finally:
        patch.undo()
    return out, obj, limits


def test_a_wide_recovery_is_drawn_pixel_for_pixel_at_its_aspect(wide_figures):
    out, obj, _ = wide_figures
    rows, cols = obj.shape
    k = figures.magnification(max(rows, cols))
    top = 14 + 18 + figures._TITLE
    png = _png(out / "recovered_magnitude.png")[..., 0]
    panel = png[top:top + rows * k, figures._LEFT:figures._LEFT + cols * k]
    amplitude = np.abs(obj)
    expected = np.clip(amplitude / np.percentile(amplitude, 99.9), 0, 1)
    blocks = panel.reshape(rows, k, cols, k).transpose(0, 2, 1, 3).reshape(rows, cols, k * k)
    y0, y1, x0, x1 = Region((0.25, 0.75, 0.3, 0.6), "").pixels((rows, cols))
    covered = np.zeros((rows, cols), bool)     # by the zoom region's outline and the axes frame
    covered[[y0 - 1, y0, y1 - 1, y1], x0 - 1:x1 + 1] = covered[y0 - 1:y1 + 1, [x0 - 1, x0, x1 - 1, x1]] = True
    covered[[0, -1], :] = covered[:, [0, -1]] = True
    assert np.all(np.abs(blocks[~covered] - expected[~covered][:, None]) <= 1.5 / 255)
    right, bottom = figures._LEFT + cols * k, top + rows * k          # the frame closes the panel just there
    middle_row, middle_col = top + rows * k // 2, figures._LEFT + cols * k // 2
    assert png[middle_row, right] < 0.05 and png[middle_row, right + 2] > 0.9
    assert png[bottom, middle_col] < 0.05 and png[bottom - 1, middle_col] > 0.05


def test_axes_cover_the_field_in_both_directions(wide_figures):
    _, obj, limits = wide_figures
    rows, cols = obj.shape
    width_mm = 8.0
    height_mm = width_mm * rows / cols                      # 4.8 mm: square pixels
    (x, y), _bar = limits["recovered_magnitude.png"]
    assert x == pytest.approx((-width_mm / 2, width_mm / 2))
    assert y == pytest.approx((height_mm / 2, -height_mm / 2))
    full = limits["observed_vs_recovered.png"]
    assert full[0] == (pytest.approx((-4.0, 4.0)), pytest.approx((2.4, -2.4)))
    zoom_x, zoom_y = full[3]                                # first zoom panel: square at the object
    assert zoom_x[1] - zoom_x[0] == pytest.approx(zoom_y[0] - zoom_y[1], rel=0.05)


def test_the_spectrum_of_the_larger_grid_is_scaled_by_that_grid_and_says_so(wide_figures):
    _, _, limits = wide_figures
    (x, y), _bar = limits["spectrum.png"]
    grid_mm = 8.0 * 128 / 80                                # the engine's grid, 12.8 mm wide
    reach = (8.0 + 6.0) * 1.08 / grid_mm                    # outermost footprint, cycles/mm of that grid
    assert x == pytest.approx((-reach, reach)) and y == pytest.approx((reach, -reach))
    title = " ".join(limits["spectrum.png titles"].split())
    assert "of the whole 128 x 128 px grid the engine ran on (12.8 mm wide)" in title
    assert "the recovered 8 mm x 4.8 mm field and its guard band" in title


def test_api_reconstructs_saves_loads_reports_and_exports_a_rectangle(tmp_path):
    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=12e-3, grid=3, overlap=0.61)
    chart = cca.resolution_chart(96, widths=(6, 4))
    images = cca.simulate(chart.image, g, snr_db=None)[:, 24:72, :]         # 48 x 96 sensor px, 6 x 12 mm
    result = cca.reconstruct(images, g, iterations=2, tol=0)
    rows, cols = result.object.shape
    assert result.region is not None and cols / rows == pytest.approx(2.0, abs=0.05)
    height_m, width_m = result.field_m
    assert width_m == pytest.approx(12e-3, abs=result.pixel_size_m)
    assert height_m == pytest.approx(6e-3, abs=result.pixel_size_m)

    path = cca.save(result, tmp_path / "recon.h5")
    back = cca.load(path)
    assert back.object.shape == (rows, cols) and back.region == result.region
    assert back.pixel_size_m == pytest.approx(result.pixel_size_m)
    from cca_cli.io.export import read_exported

    for source in (back, path):
        exported = read_exported(cca.export(source, tmp_path / f"{type(source).__name__}.tif"))
        assert exported.values.shape == (rows, cols)
        assert exported.pixel_size_m == pytest.approx(result.pixel_size_m)

    from cca_cli.config.model import ReportSection
    from cca_cli.io.h5 import Provenance
    from cca_cli.stages import report

    summary = report.run(path, ReportSection(figures=False), tmp_path / "report",
                         provenance=Provenance.make("report", "", ""))
    assert summary["recovered_shape_px"] == [rows, cols]
    assert summary["recovered_field_m"] == pytest.approx([height_m, width_m])
    y0, y1, x0, x1 = json.loads((tmp_path / "report" / "report.json").read_text())["zoom_region"]["fractions"]
    assert (y1 - y0) * rows == pytest.approx((x1 - x0) * cols, abs=1e-3)   # the zoom is square in pixels
