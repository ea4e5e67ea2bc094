"""Multiplexed forward model and recovery: equivalence, adjoint, improvement."""

import numpy as np
import pytest

from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions
from cca_cli.engines.base import run_engine
from cca_cli.engines.multiplex import MultiplexedAlternatingMinimization, MultiplexedProblem
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.projections import project_grouped_magnitudes, project_magnitudes
from cca_cli.metrics import rmse
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.multiplex import (MultiplexGeometry, MultiplexedForwardModel, coverage_map, design_band,
                                      group_chunk_slices, random_patterns, rect_lattice)
from cca_cli.optics.pupil import circular_pupils
from cca_cli.report.summary import on_grid
from cca_cli.targets import resolution_chart

R = 5.0


def _object(size):
    chart = resolution_chart(64, widths=(3, 2, 1))
    amplitude = on_grid(np.asarray(chart.image, np.float32), size)
    return np.clip(amplitude, 0, None).astype(np.complex64)


def _geometry(patterns, *, cameras=3, sources=3, camera_pitch=2 * R, source_overlap=0.6):
    return MultiplexGeometry(camera_centres_px=rect_lattice(cameras, cameras, camera_pitch),
                             source_shifts_px=rect_lattice(sources, sources, (1 - source_overlap) * 2 * R),
                             patterns=tuple(tuple(p) for p in patterns), pupil_radius_px=R,
                             camera_shape=(cameras, cameras), source_shape=(sources, sources))


def test_virtual_captures_are_ordered_pattern_camera_source():
    geo = _geometry([(0, 4), (8,)], cameras=2)
    assert geo.n_measurements == 8 and geo.n_virtual == 4 * 2 + 4 * 1
    assert geo.group_offsets.tolist() == [0, 2, 4, 6, 8, 9, 10, 11, 12]
    np.testing.assert_allclose(geo.virtual_centres_px[1], geo.camera_centres_px[0] + geo.source_shifts_px[4])
    np.testing.assert_allclose(geo.virtual_centres_px[-1], geo.camera_centres_px[3] + geo.source_shifts_px[8])
    assert group_chunk_slices(geo.group_offsets, 3) == [slice(0, 2), slice(2, 4), slice(4, 6), slice(6, 9),
                                                       slice(9, 12)]


def test_grouped_projection_with_one_field_per_group_is_the_plain_projection():
    rng = np.random.default_rng(1)
    fields = (rng.standard_normal((4, 8, 8)) + 1j * rng.standard_normal((4, 8, 8))).astype(np.complex64)
    amps = rng.random((4, 8, 8)).astype(np.float32)
    weights = rng.random((4, 8, 8)).astype(np.float32)
    a, b = fields.copy(), fields.copy()
    ma = project_magnitudes(a, amps, np.empty((2, 4, 8, 8), np.float32), weights=weights, eps=1e-6)
    mb = project_grouped_magnitudes(b, amps, np.empty((4, 8, 8), np.float32), np.arange(5), weights=weights, eps=1e-6)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert mb == pytest.approx(ma, rel=1e-5)


def test_grouped_projection_matches_the_summed_intensity():
    rng = np.random.default_rng(2)
    fields = (rng.standard_normal((5, 8, 8)) + 1j * rng.standard_normal((5, 8, 8))).astype(np.complex64)
    amps = rng.random((2, 8, 8)).astype(np.float32) + 0.1
    before = fields.copy()
    project_grouped_magnitudes(fields, amps, np.empty((5, 8, 8), np.float32), np.array([0, 3, 5]))
    np.testing.assert_allclose(np.sqrt((np.abs(fields[:3]) ** 2).sum(0)), amps[0], rtol=1e-4)
    np.testing.assert_allclose(np.sqrt((np.abs(fields[3:]) ** 2).sum(0)), amps[1], rtol=1e-4)
    # the phases and the intensity ratios inside a group are kept
    ratio = fields / before
    np.testing.assert_allclose(ratio[:3] / ratio[0], 1.0, rtol=1e-4)


def _altmin(problem, iterations):
    options = AltMinOptions(max_iterations=iterations, tol=0.0, chunk=4, threads=1)
    engine = (MultiplexedAlternatingMinimization if isinstance(problem, MultiplexedProblem)
              else AlternatingMinimization)(problem, options)
    return run_engine(engine)


def test_nmux_one_equals_the_single_source_path():
    geo = _geometry([(3,), (5,)])
    mux = MultiplexedForwardModel(geo, sensor_size=64)
    obj = _object(mux.layout.hires_size)
    images = mux.sensor_intensity(fft.fft2c(obj).astype(np.complex64))
    assert images.shape == (18,) + mux.model.field_shape

    single = ForwardModel(mux.layout, circular_pupils(mux.layout.box_size, mux.layout.box_centres, R))
    reference = single.sensor_intensity(fft.fft2c(obj).astype(np.complex64))
    np.testing.assert_allclose(images, reference, rtol=1e-5, atol=1e-6)

    # Both paths recover the same data. They batch their FFTs differently, so they agree to float32
    # rounding, which the iterations amplify. How much is measured, not assumed: the single path run on
    # the two forward models' images (which differ by that rounding alone) gives the spread.
    mux_problem = MultiplexedProblem.from_sensor_images(mux, images)
    one_problem = PhaseRetrievalProblem.from_sensor_images(single, images)
    s_mux, _ = _altmin(mux_problem, 1)
    s_one, _ = _altmin(one_problem, 1)
    scale = np.abs(s_one).max()
    eps = np.finfo(np.float32).eps
    assert np.abs(s_mux - s_one).max() / scale < 64 * eps  # one iteration: a few roundings of each FFT

    s_mux, h_mux = _altmin(mux_problem, 15)
    s_one, h_one = _altmin(one_problem, 15)
    s_ref, _ = _altmin(PhaseRetrievalProblem.from_sensor_images(single, reference), 15)
    np.testing.assert_allclose(h_mux.array("residual"), h_one.array("residual"), rtol=1e-3)
    spread = np.abs(s_ref - s_one).max() / scale
    assert np.abs(s_mux - s_one).max() / scale <= max(4 * spread, 64 * eps)


def test_adjoint_dot_product_of_the_linear_part():
    geo = _geometry(random_patterns(9, 3, 2, seed=4))
    mux = MultiplexedForwardModel(geo, sensor_size=64)
    rng = np.random.default_rng(0)
    m_big = mux.layout.hires_size
    spectrum = (rng.standard_normal((m_big, m_big)) + 1j * rng.standard_normal((m_big, m_big))).astype(np.complex64)
    shape = (geo.n_virtual,) + mux.model.field_shape
    fields = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    lhs = np.vdot(mux.fields(spectrum).astype(np.complex128), fields.astype(np.complex128))
    rhs = np.vdot(spectrum.astype(np.complex128), mux.adjoint(fields).astype(np.complex128))
    assert abs(lhs - rhs) <= 1e-4 * abs(lhs)
    # the summation over a measurement's sources and its adjoint
    per_virtual = rng.standard_normal((geo.n_virtual, 3))
    per_measurement = rng.standard_normal((geo.n_measurements, 3))
    assert np.vdot(mux.group_sum(per_virtual), per_measurement) == pytest.approx(
        np.vdot(per_virtual, mux.group_spread(per_measurement)))


def test_coverage_counts_measurements_not_sources():
    geo = _geometry([(4, 5)], cameras=1)
    coverage = coverage_map(geo, 64)
    # both regions belong to one image: their overlap is constrained once
    assert coverage.max() == 1
    assert coverage[32, 32] == 1 and coverage[32, 32 + 2] == 1
    assert design_band(geo, 64).sum() > coverage.sum()
    two = coverage_map(_geometry([(4,), (5,)], cameras=1), 64)
    assert two.max() == 2


def test_small_mux_case_beats_its_centre_image():
    geo = _geometry(random_patterns(9, 4, 2, seed=0), camera_pitch=2 * R, source_overlap=0.6)
    mux = MultiplexedForwardModel(geo, sensor_size=64)
    obj = _object(mux.layout.hires_size)
    spectrum = fft.fft2c(obj).astype(np.complex64)
    images = mux.sensor_intensity(spectrum)
    on_axis = MultiplexedForwardModel(_geometry([(4,)], cameras=1), sensor_size=64,
                                      hires_size=mux.layout.hires_size).sensor_intensity(spectrum)[0]
    truth = np.abs(obj) ** 2
    engine = MultiplexedAlternatingMinimization(MultiplexedProblem.from_sensor_images(mux, images),
                                                AltMinOptions(max_iterations=100, tol=0.0, threads=1))
    recovered, history = run_engine(engine)
    recovered_intensity = np.abs(fft.ifft2c(recovered)) ** 2
    e_obs = rmse(on_grid(on_axis, truth.shape[-1]), truth)
    e_rec = rmse(recovered_intensity, truth)
    assert history.array("residual")[-1] < history.array("residual")[0]
    assert e_rec < 0.75 * e_obs
