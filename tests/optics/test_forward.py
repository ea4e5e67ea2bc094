"""The camera-array forward operator: adjoint, normal diagonal, units, backends, pupils."""

import math

import numpy as np
import pytest

from cca_cli.optics import fft
from cca_cli.optics import pupil as pupil_module
from cca_cli.optics.forward import ForwardModel, chunk_slices, to_model_layout, to_sensor_layout
from cca_cli.optics.pupil import circular_pupils
from cca_cli.optics.zernike import zernike_phase
from cca_cli.sampling.grid import band_layout, square_scan

RNG = np.random.default_rng(11)
needs_pyfftw = pytest.mark.skipif(not fft.HAVE_PYFFTW, reason="pyfftw not installed or CCA_FFT_BACKEND=scipy")


def _model(radius=5.3, grid=3, overlap=0.61, *, sensor_size=None, phase=False):
    centres = square_scan(grid, 2 * radius * (1 - overlap)).centres_yx_m + RNG.uniform(-0.4, 0.4, (grid * grid, 2))
    layout = band_layout(centres, radius, sensor_size=sensor_size)
    pupils = circular_pupils(layout.box_size, layout.box_centres, radius).astype(np.complex64)
    if phase:
        pupils = pupils * np.exp(1j * zernike_phase(layout.box_size, layout.box_centres, radius, [0.3]))
    return ForwardModel(layout, pupils.astype(np.complex64))


def _random_complex(shape):
    return (RNG.standard_normal(shape) + 1j * RNG.standard_normal(shape)).astype(np.complex64)


def _dot(a, b):
    return np.vdot(a.astype(np.complex128).ravel(), b.astype(np.complex128).ravel())


@pytest.mark.parametrize("backend", ["scipy", pytest.param("pyfftw", marks=needs_pyfftw)])
@pytest.mark.parametrize(("radius", "grid", "phase"), [(5.3, 3, False), (3.7, 5, True)])
def test_adjoint_dot_product(backend, radius, grid, phase):
    with fft.use_backend(backend):
        model = _model(radius, grid, phase=phase)
        x = _random_complex(model.spectrum_shape)
        y = _random_complex((model.n_images,) + model.field_shape)
        y_before = y.copy()
        lhs = _dot(model.forward(x, chunk=4), y)
        rhs = _dot(x, model.adjoint(y, chunk=4))
    assert abs(lhs - rhs) <= 1e-4 * abs(lhs)
    np.testing.assert_array_equal(y, y_before)  # adjoint() leaves its input alone


def test_normal_diagonal_is_the_normal_operator():
    model = _model(4.6, 3, phase=True)
    x = _random_complex(model.spectrum_shape)
    normal = model.adjoint(model.forward(x))
    diagonal = model.normal_diagonal()
    assert diagonal.dtype == np.float32 and diagonal.shape == model.spectrum_shape
    np.testing.assert_allclose(normal, diagonal * x, atol=2e-5 * np.max(np.abs(normal)))
    inside = diagonal > 0
    np.testing.assert_allclose(normal[inside] / x[inside], diagonal[inside], rtol=1e-3, atol=1e-4)
    # Every capture contributes its pupil power once: Σ diagonal = K · pupil area.
    assert diagonal.sum() == pytest.approx(float(np.sum(np.abs(model.pupils) ** 2)), rel=1e-5)


def test_unit_plane_wave_gives_unit_irradiance_in_the_centre_capture():
    model = _model(5.3, 3, sensor_size=64)
    size = model.layout.hires_size
    spectrum = fft.fft2c(np.ones((size, size), np.complex64)).astype(np.complex64)
    images = model.sensor_intensity(spectrum)
    assert images.shape == (model.n_images,) + model.field_shape and images.dtype == np.float32
    np.testing.assert_allclose(images[4], 1.0, atol=1e-5)
    assert model.intensity_scale == pytest.approx((size / model.layout.lowres_size) ** 2)


@pytest.mark.parametrize("chunk", [1, 4, 64])
def test_forward_is_independent_of_the_chunk_size(chunk):
    model = _model(4.0, 3)
    x = _random_complex(model.spectrum_shape)
    np.testing.assert_allclose(model.forward(x, chunk=chunk), model.forward(x, chunk=9), atol=1e-5)


@needs_pyfftw
def test_pyfftw_and_scipy_give_the_same_forward_result():
    model = _model(5.3, 3)
    x = _random_complex(model.spectrum_shape)
    with fft.use_backend("scipy"):
        a = model.forward(x)
        ia = model.sensor_intensity(x)
    with fft.use_backend("pyfftw"):
        b = model.forward(x)
        ib = model.sensor_intensity(x)
    scale = np.max(np.abs(a))
    np.testing.assert_allclose(a, b, atol=1e-5 * scale)
    np.testing.assert_allclose(ia, ib, atol=1e-5 * np.max(ia))


def test_sensor_intensity_of_a_real_object_matches_an_explicit_computation():
    """Low-pass of a real object through the centre pupil, computed directly on the M grid."""
    model = _model(5.3, 3, sensor_size=64)
    size = model.layout.hires_size
    obj = RNG.uniform(0, 1, (size, size)).astype(np.complex64)
    spectrum = fft.fft2c(obj).astype(np.complex64)
    layout = model.layout
    b, (y0, x0) = layout.box_size, layout.box_origins[4]
    mask = np.zeros((size, size), np.complex64)
    mask[y0:y0 + b, x0:x0 + b] = model.pupils[4]
    expected_hires = np.abs(fft.ifft2c(spectrum * mask)) ** 2
    expected = fft.fourier_resample(expected_hires[None], layout.lowres_size)[0]
    got = model.sensor_intensity(spectrum)[4]
    np.testing.assert_allclose(got, expected, atol=1e-4 * expected.max())


def test_forward_model_rejects_badly_shaped_pupils():
    layout = band_layout(square_scan(3, 4.0).centres_yx_m, 5.0)
    with pytest.raises(ValueError, match="pupils must have shape"):
        ForwardModel(layout, np.ones((2, layout.box_size, layout.box_size), np.float32))
    with pytest.raises(ValueError):
        ForwardModel(layout, np.ones((9, layout.box_size + 1, layout.box_size + 1), np.float32))
    # A single pupil is broadcast to all captures.
    model = ForwardModel(layout, circular_pupils(layout.box_size, [[layout.box_size / 2] * 2], 5.0))
    assert model.pupils.shape == (9, layout.box_size, layout.box_size)


def test_forward_model_given_its_pupil_boxes_keeps_them_and_computes_the_same_fields():
    model = _model(phase=True)
    layout = model.layout
    pupils = model.pupils.copy()
    boxes = pupils * np.float32(1.0 / layout.lowres_size)
    given = ForwardModel(layout, pupils, pupil_boxes=boxes)
    assert given.pupils is pupils and given.pupil_boxes is boxes
    spectrum = _random_complex(model.spectrum_shape)
    np.testing.assert_array_equal(given.forward(spectrum), model.forward(spectrum))
    with pytest.raises(ValueError, match="pupil_boxes must be a C-contiguous complex64"):
        ForwardModel(layout, pupils, pupil_boxes=boxes.astype(np.complex128))
    with pytest.raises(ValueError, match="pupils must be a C-contiguous complex64"):
        ForwardModel(layout, pupils[:1], pupil_boxes=boxes)


@pytest.mark.parametrize("radius", [6.0, 10.0, 20.945])
def test_circular_pupil_area_is_pi_r_squared(radius):
    box = 2 * math.ceil(radius) + 4
    centres = [[box / 2, box / 2], [box / 2 - 0.3, box / 2 + 0.25]]
    binary = circular_pupils(box, centres, radius, edge_px=0)
    assert binary.dtype == np.float32 and set(np.unique(binary)) <= {0.0, 1.0}
    soft = circular_pupils(box, centres, radius)
    assert soft.min() >= 0 and soft.max() <= 1
    for pupil in (*binary, *soft):
        assert pupil.sum() == pytest.approx(math.pi * radius ** 2, rel=0.03)
    # The anti-aliased disc's area is exact to a fraction of its edge and changes smoothly with its centre.
    assert soft[0].sum() == pytest.approx(math.pi * radius ** 2, rel=0.005)
    nudged = circular_pupils(box, [[box / 2 + 0.01, box / 2]], radius)[0]
    assert 0 < np.abs(nudged - soft[0]).max() < 0.02


def test_circular_pupils_of_many_captures_are_each_captures_own_disc():
    """A box set is made a few captures at a time (its work array stays in cache): every disc, binary or
    anti-aliased, is exactly the one made for its capture alone, across the chunks' edges."""
    rng = np.random.default_rng(3)
    box = 40
    centres = rng.uniform(15, 25, (3 * pupil_module._WORK_BYTES // (8 * box * box) + 5, 2))
    for edge in (0.0, 1.0):
        together = circular_pupils(box, centres, 12.3, edge_px=edge)
        alone = np.stack([circular_pupils(box, [centre], 12.3, edge_px=edge)[0] for centre in centres])
        assert together.dtype == np.float32 and np.array_equal(together, alone)


def test_zernike_defocus_phase_is_radially_symmetric():
    phase = zernike_phase(24, [[12.0, 12.0]], 8.0, [0.5])[0]
    np.testing.assert_allclose(phase, phase.T, atol=1e-6)
    assert phase[12, 12] == pytest.approx(2 * np.pi * 0.5 * np.sqrt(3) * -1.0, rel=1e-6)
    assert np.all(zernike_phase(24, [[12.0, 12.0]], 8.0, [0.0, 0.0, 0.0]) == 0)


def test_zernike_modes_match_their_closed_forms():
    """The RMS-normalised modes written out (Noll): defocus, both astigmatisms, coma x, spherical."""
    from cca_cli.optics.zernike import zernike_basis

    grid = np.arange(20.0)
    y, x = ((grid[:, None] - 9.3) / 7.0) * np.ones((1, 20)), ((grid[None, :] - 10.1) / 7.0) * np.ones((20, 1))
    r2 = x * x + y * y
    expected = {(2, 0): np.sqrt(3) * (2 * r2 - 1), (2, 2): np.sqrt(6) * (x * x - y * y), (2, -2): np.sqrt(6) * 2 * x * y,
                (3, 1): np.sqrt(8) * (3 * r2 - 2) * x, (4, 0): np.sqrt(5) * (6 * r2 * r2 - 6 * r2 + 1)}
    basis = zernike_basis(20, [[9.3, 10.1]], 7.0, modes=list(expected))
    for j, values in enumerate(expected.values()):
        np.testing.assert_allclose(basis[j, 0], 2 * np.pi * values, atol=2e-4)


def test_layout_conversions_are_inverse_and_chunks_cover_everything():
    images = RNG.standard_normal((2, 6, 6))
    np.testing.assert_array_equal(to_sensor_layout(to_model_layout(images)), images)
    assert to_model_layout(images)[0, 0, 0] == images[0, 3, 3]
    for n, chunk in [(25, 16), (9, 4), (1, 8), (64, 64)]:
        slices = chunk_slices(n, chunk)
        covered = np.concatenate([np.arange(n)[s] for s in slices])
        np.testing.assert_array_equal(covered, np.arange(n))
        assert max(s.stop - s.start for s in slices) <= chunk
