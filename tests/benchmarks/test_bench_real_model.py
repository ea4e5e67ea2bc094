"""The real-data benchmark's common representation reproduces cca's forward model (small, no data files)."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import real_model  # noqa: E402  (a broken import must fail these tests, not skip them)

from cca_cli.optics.forward import ForwardModel  # noqa: E402
from cca_cli.optics.pupil import circular_pupils  # noqa: E402
from cca_cli.sampling.grid import band_layout  # noqa: E402


def _cca_intensity(centres, radius, n, m, spectrum):
    layout = band_layout(centres, radius, sensor_size=n, hires_size=m)
    model = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, radius))
    return model.sensor_intensity(spectrum), layout


def test_common_model_matches_cca_with_fractional_centres():
    rng = np.random.default_rng(3)
    n, m, radius = 16, 48, 3.7  # cca picks a 16² capture grid for this radius
    centres = np.array([[0.0, 0.0], [4.4, -2.6], [-7.5, 6.2], [9.9, 10.1]])
    spectrum = (rng.standard_normal((m, m)) + 1j * rng.standard_normal((m, m))).astype(np.complex64)
    reference, layout = _cca_intensity(centres, radius, n, m, spectrum)
    windows = np.rint(centres).astype(int)
    rec = real_model.Recovery(spectrum, real_model.circle_pupils(n, layout.centres_px - windows, radius, edge_px=1.0),
                              np.arange(len(centres)), windows)
    mine = np.abs(real_model.predicted_fields(rec)) ** 2
    scale = (m / n) ** 2  # cca returns sensor irradiance: |ψ|² / (M/m)²
    np.testing.assert_allclose(mine / scale, reference, rtol=0, atol=1e-5 * reference.max())


def test_shared_box_pupil_is_embedded_at_the_window_centre():
    box = np.zeros((1, 6, 6), np.complex64)
    box[0, 3, 3] = 1.0
    embedded = real_model.embed_centred(box, 10)
    assert embedded.shape == (1, 10, 10) and embedded[0, 5, 5] == 1.0 and np.count_nonzero(embedded) == 1
