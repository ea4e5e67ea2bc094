"""The compiled kernels and their numpy fallbacks compute the same thing."""

import numpy as np
import pytest

from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.optics import kernels
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import band_layout, square_scan

if not kernels.HAVE_NUMBA:
    pytest.skip("numba not installed or CCA_KERNELS=numpy", allow_module_level=True)


def _model():
    layout = band_layout(square_scan(5, 8.0).centres_yx_m, 6.3, sensor_size=64)
    return ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, 6.3))


def _both(function):
    results = {}
    for name in ("numba", "numpy"):
        with kernels.use_kernels(name):
            results[name] = function()
    return results["numba"], results["numpy"]


def test_forward_and_adjoint_agree():
    model = _model()
    rng = np.random.default_rng(1)
    spectrum = (rng.standard_normal(model.spectrum_shape) + 1j * rng.standard_normal(model.spectrum_shape))
    spectrum = spectrum.astype(np.complex64)
    fast, slow = _both(lambda: model.forward(spectrum))
    np.testing.assert_allclose(fast, slow, atol=1e-5 * np.abs(slow).max())
    fields = fast.copy()
    fast, slow = _both(lambda: model.adjoint(fields))
    np.testing.assert_allclose(fast, slow, atol=1e-5 * np.abs(slow).max())


@pytest.mark.parametrize("weighted", [False, True])
def test_projection_agrees(weighted):
    rng = np.random.default_rng(2)
    shape = (5, 24, 24)
    fields = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    amplitudes = np.abs(rng.standard_normal(shape)).astype(np.float32)
    weights = rng.random(shape).astype(np.float32) if weighted else None

    def run():
        out = fields.copy()
        misfit = kernels.project_magnitudes(out, amplitudes, np.empty((2,) + shape, np.float32), weights=weights,
                                            eps=1e-6)
        return out, misfit

    (fast, fast_misfit), (slow, slow_misfit) = _both(run)
    np.testing.assert_allclose(fast, slow, atol=1e-5)
    assert fast_misfit == pytest.approx(slow_misfit, rel=1e-5)
    if not weighted:
        np.testing.assert_allclose(np.abs(fast), amplitudes, atol=1e-4)


def test_tikhonov_update_agrees():
    rng = np.random.default_rng(3)
    numerator = (rng.standard_normal((16, 16)) + 1j * rng.standard_normal((16, 16))).astype(np.complex64)
    previous = (rng.standard_normal((16, 16)) + 1j * rng.standard_normal((16, 16))).astype(np.complex64)
    inverse = rng.random((16, 16)).astype(np.float32)

    def run():
        out = numerator.copy()
        return out, kernels.tikhonov_update(out, inverse, previous)

    (fast, (dc_fast, n_fast)), (slow, (dc_slow, n_slow)) = _both(run)
    np.testing.assert_allclose(fast, numerator * inverse, rtol=1e-6)
    np.testing.assert_allclose(slow, numerator * inverse, rtol=1e-6)
    assert dc_fast == pytest.approx(dc_slow, rel=1e-5) and n_fast == pytest.approx(n_slow, rel=1e-5)


def test_altmin_iterations_agree_between_kernels():
    model = _model()
    rng = np.random.default_rng(4)
    amplitudes = np.abs(rng.standard_normal((model.n_images,) + model.field_shape)).astype(np.float32)
    problem = PhaseRetrievalProblem(model, amplitudes)

    def run():
        engine = AlternatingMinimization(problem, AltMinOptions(max_iterations=5, tol=0, chunk=7))
        for _ in range(5):
            engine.update()
        engine.close()
        return engine.spectrum().copy()

    fast, slow = _both(run)
    np.testing.assert_allclose(fast, slow, atol=1e-4 * np.abs(slow).max())


@pytest.mark.parametrize("weighted", [False, True])
def test_momentum_lanes_fused_in_one_call_agree_with_the_numpy_kernels(weighted):
    """With numba and FFTW the momentum engine runs each lane in one compiled call; numpy runs it step by step."""
    from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum

    model = _model()
    rng = np.random.default_rng(5)
    amplitudes = np.abs(rng.standard_normal((model.n_images,) + model.field_shape)).astype(np.float32)
    weights = rng.random(amplitudes.shape).astype(np.float32) if weighted else None
    problem = PhaseRetrievalProblem(model, amplitudes, weights=weights)
    fused = []

    def run():
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=4, tol=0, batch=3))
        two_lanes = any(len(phase.lanes) == 2 for phase in engine._schedule.phases)
        fused.append(engine.passes.fused and two_lanes)
        misfits = [engine.update()[0] for _ in range(4)]
        engine.close()
        return engine.spectrum().copy(), np.array(misfits)

    (fast, fast_misfits), (slow, slow_misfits) = _both(run)
    from cca_cli.optics import fft

    if fft.backend_name() == "pyfftw" and fft.raw_fftw_available():
        assert fused == [True, False]
    np.testing.assert_allclose(fast, slow, atol=1e-4 * np.abs(slow).max())
    np.testing.assert_allclose(fast_misfits, slow_misfits, rtol=1e-4)


@pytest.mark.parametrize("model", ["full", "smooth"])
def test_momentum_lanes_with_pupil_sums_fused_in_one_call_agree_with_the_step_by_step_pass(model):
    """Map pupil models sum their fit inside the fused lane; numpy kernels run the same pass step by step."""
    from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum

    forward = _model()
    rng = np.random.default_rng(6)
    amplitudes = np.abs(rng.standard_normal((forward.n_images,) + forward.field_shape)).astype(np.float32) + 0.5
    problem = PhaseRetrievalProblem(forward, amplitudes)
    fused = []

    def run():
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=4, tol=0, batch=3, pupil_recovery="shared",
                                                             pupil_model=model, pupil_estimate=False))
        fused.append(engine.passes.fused)
        for _ in range(4):
            engine.update()
        engine.close()
        return engine.spectrum().copy(), engine.calibration().pupil.maps

    (fast, fast_maps), (slow, slow_maps) = _both(run)
    from cca_cli.optics import fft

    if fft.backend_name() == "pyfftw" and fft.raw_fftw_available():
        assert fused == [True, False]
    np.testing.assert_allclose(fast, slow, atol=1e-4 * np.abs(slow).max())
    np.testing.assert_allclose(fast_maps, slow_maps, atol=1e-4)


@pytest.mark.parametrize("chunk", [1, 2])
@pytest.mark.parametrize("threads", [1, 2])
def test_fused_lanes_in_cache_sized_chunks_agree_with_the_step_by_step_pass(chunk, threads, monkeypatch):
    """A fused lane transforms a batch a few captures at a time; threads sharing a batch scatter after both read."""
    from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum

    forward = _model()
    m = forward.field_shape[0]
    assert kernels.lane_chunk(m) > 3          # small fields: one chunk per batch unless told otherwise
    monkeypatch.setattr(kernels, "_LANE_CHUNK_BYTES", chunk * 8 * m * m)
    assert kernels.lane_chunk(m) == chunk
    rng = np.random.default_rng(7)
    amplitudes = np.abs(rng.standard_normal((forward.n_images,) + forward.field_shape)).astype(np.float32) + 0.5
    problem = PhaseRetrievalProblem(forward, amplitudes)

    def run():
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=4, tol=0, batch=3, threads=threads,
                                                             pupil_recovery="shared", pupil_model="full",
                                                             pupil_estimate=False))
        fused.append(engine.passes.fused)
        misfits = [engine.update()[0] for _ in range(4)]
        engine.close()
        return engine.spectrum().copy(), engine.calibration().pupil.maps, np.array(misfits)

    fused = []
    (fast, fast_maps, fast_misfits), (slow, slow_maps, slow_misfits) = _both(run)
    from cca_cli.optics import fft

    if fft.backend_name() == "pyfftw" and fft.raw_fftw_available():
        assert fused == [True, False]
    np.testing.assert_allclose(fast, slow, atol=1e-4 * np.abs(slow).max())
    np.testing.assert_allclose(fast_maps, slow_maps, atol=1e-4)
    np.testing.assert_allclose(fast_misfits, slow_misfits, rtol=1e-4)


def test_fused_lanes_give_the_same_spectrum_whatever_their_chunk(monkeypatch):
    """Chunks change only how many captures one FFT call transforms, not what is computed."""
    from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum
    from cca_cli.optics import fft

    if not (fft.backend_name() == "pyfftw" and fft.raw_fftw_available()):
        pytest.skip("fused lanes need pyfftw and raw FFTW plans")
    forward = _model()
    m = forward.field_shape[0]
    rng = np.random.default_rng(9)
    amplitudes = np.abs(rng.standard_normal((forward.n_images,) + forward.field_shape)).astype(np.float32) + 0.5
    problem = PhaseRetrievalProblem(forward, amplitudes)
    spectra = []
    for chunk in (1, 64):
        monkeypatch.setattr(kernels, "_LANE_CHUNK_BYTES", chunk * 8 * m * m)
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=4, tol=0, batch=5, threads=2,
                                                             pupil_recovery="shared", pupil_model="full",
                                                             pupil_estimate=False))
        assert engine.passes.fused
        for _ in range(4):
            engine.update()
        engine.close()
        spectra.append(engine.spectrum().copy())
    # FFTW's plans for one transform and for a batch of many may round differently (pyFFTW 0.15.0's FFTW does),
    # and four passes of pupil steps carry that to 1.6e-6 of the peak; a capture placed or scattered wrongly
    # would differ by its whole share of the spectrum.
    np.testing.assert_allclose(spectra[0], spectra[1], rtol=0, atol=1e-5 * np.abs(spectra[1]).max())


def test_pupils_from_maps_and_rpie_factors_agree_and_match_the_formulas():
    rng = np.random.default_rng(8)
    K, b, M = 7, 6, 20
    discs = rng.random((K, b, b)).astype(np.float32)
    maps = (rng.standard_normal((2, b, b)) + 1j * rng.standard_normal((2, b, b))).astype(np.complex64)
    index = rng.integers(0, 2, K).astype(np.int64)
    origins = rng.integers(0, M - b, (K, 2)).astype(np.int64)   # overlapping boxes
    batches = np.array([[0, 3], [3, 7]], np.int64)

    def run():
        pupils, boxes, factors, separate = (np.zeros((K, b, b), np.complex64) for _ in range(4))
        coverage = np.zeros((M, M), np.float32)
        kernels.map_pupil_factors(discs, maps, index, origins, batches, alpha=0.2, tau=1e-3, scale=0.5,
                                  forward_scale=0.25, coverage=coverage, pupils=pupils, boxes=boxes, factors=factors)
        assert not coverage.any()
        kernels.rpie_factors(pupils, origins, batches, alpha=0.2, tau=1e-3, scale=0.5, coverage=coverage,
                             out=separate)
        np.testing.assert_array_equal(separate, factors)   # the same factors as from the pupils
        return pupils, boxes, factors

    (pupils, boxes, factors), (slow_pupils, slow_boxes, slow_factors) = _both(run)
    np.testing.assert_array_equal(pupils, discs * maps[index])
    np.testing.assert_array_equal(boxes, pupils * np.float32(0.25))
    np.testing.assert_array_equal(slow_pupils, pupils)
    np.testing.assert_array_equal(slow_boxes, boxes)
    for start, stop in batches:   # scale · P* / ((1 − α) D_B + α max D_B + τ), D_B the batch's pupil power
        power = np.zeros((M, M))
        for i in range(start, stop):
            power[origins[i, 0]:origins[i, 0] + b, origins[i, 1]:origins[i, 1] + b] += np.abs(pupils[i]) ** 2
        for i in range(start, stop):
            y, x = origins[i]
            expected = 0.5 * np.conj(pupils[i]) / (0.8 * power[y:y + b, x:x + b] + 0.2 * power.max() + 1e-3)
            np.testing.assert_allclose(factors[i], expected, rtol=1e-5)
    np.testing.assert_allclose(slow_factors, factors, rtol=1e-6)


def test_lanes_forming_map_pupils_on_the_fly_give_bit_identical_spectra():
    """A map model's pupils and rPIE factors formed inside the lane, or stored by map_pupil_factors: the
    same bits, whether the lane scatters each batch itself or leaves it to scatter_map_boxes in parts."""
    from cca_cli.optics.forward import Workspace

    rng = np.random.default_rng(12)
    K, b, m, M = 9, 8, 16, 40
    discs = rng.random((K, b, b)).astype(np.float32)
    maps = (rng.standard_normal((2, b, b)) + 1j * rng.standard_normal((2, b, b))).astype(np.complex64)
    index = rng.integers(0, 2, K).astype(np.int64)
    origins = rng.integers(0, M - b, (K, 2)).astype(np.int64)   # overlapping boxes
    batches = np.array([[0, 4], [4, 9]], np.int64)
    start = (rng.standard_normal((M, M)) + 1j * rng.standard_normal((M, M))).astype(np.complex64)
    amplitudes = rng.random((K, m, m)).astype(np.float32)
    options = dict(alpha=0.2, tau=1e-3, scale=0.5 / m)
    workspace = Workspace(5, m, threads=1, band=(m // 2 - b // 2, m // 2 + b // 2), effort="estimate")
    raw = workspace.box_fft.raw_plans()
    if not kernels.can_fuse_lanes(raw):
        pytest.skip("fused lanes need pyfftw and raw FFTW plans")
    pupils, boxes, factors = (np.zeros((K, b, b), np.complex64) for _ in range(3))
    coverage = np.zeros((M, M), np.float32)
    kernels.map_pupil_factors(discs, maps, index, origins, batches, forward_scale=1.0 / m, coverage=coverage,
                              pupils=pupils, boxes=boxes, factors=factors, **options)
    parts = kernels.MapPupils(discs, maps, index, forward_scale=1.0 / m, **options)
    np.testing.assert_array_equal(parts.pupils(), pupils)
    work = np.empty((5, b, b), np.complex64)

    stored, formed = start.copy(), start.copy()
    misfit = kernels.sequential_lane(raw, batches, stored, origins, boxes, factors, workspace.fields, amplitudes,
                                     None, 1e-6, boxes=work)
    same = kernels.sequential_lane(raw, batches, formed, origins, None, None, workspace.fields, amplitudes, None,
                                   1e-6, boxes=work, map_pupils=parts, coverage=coverage)
    assert not coverage.any()
    assert misfit == same
    np.testing.assert_array_equal(formed, stored)
    assert not np.array_equal(formed, start)

    # one batch run in two parts, each left unscattered, then scattered in order
    stored, formed = start.copy(), start.copy()
    for spectrum, mapped in ((stored, False), (formed, True)):
        held = []
        for first, last in ((4, 7), (7, 9)):
            part = np.empty((last - first, b, b), np.complex64)
            kernels.sequential_lane(raw, np.array([[first, last]], np.int64), spectrum, origins,
                                    None if mapped else boxes, None if mapped else factors, workspace.fields,
                                    amplitudes, None, 1e-6, boxes=part, scatter=False,
                                    map_pupils=parts if mapped else None, coverage=coverage if mapped else None)
            held.append((first, part))
        for first, part in held:
            if mapped:
                kernels.scatter_map_boxes(part, origins, parts, coverage, spectrum, (4, 9), first)
            else:
                kernels.scatter_boxes(part, origins, factors, spectrum, first)
    assert not coverage.any()
    np.testing.assert_array_equal(formed, stored)


@pytest.mark.parametrize("threads, batch", [(1, 3), (2, 3), (2, 25)])
def test_momentum_engine_forming_map_pupils_in_its_lanes_matches_stored_pupils_bit_for_bit(threads, batch):
    """The engine's map-pupil lanes against the same engine made to store pupils, boxes and factors:
    lanes side by side, one batch shared by two threads (batch 25: every capture), batches that grow."""
    from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum
    from cca_cli.optics import fft

    if not (fft.backend_name() == "pyfftw" and fft.raw_fftw_available()):
        pytest.skip("fused lanes need pyfftw and raw FFTW plans")

    class StoredPupils(SequentialMomentum):
        def _set_recovered_model(self):
            self._map_pupils = None
            self._set_model(None, self.calibrator.recovery.map_parts())

    forward = _model()
    rng = np.random.default_rng(11)
    amplitudes = np.abs(rng.standard_normal((forward.n_images,) + forward.field_shape)).astype(np.float32) + 0.5
    problem = PhaseRetrievalProblem(forward, amplitudes)
    results = []
    for engine_class in (SequentialMomentum, StoredPupils):
        engine = engine_class(problem, MomentumOptions(max_iterations=6, tol=0, batch=batch, batch_growth=2,
                                                       threads=threads, pupil_recovery="shared", pupil_model="full",
                                                       pupil_estimate=False))
        assert engine.passes.fused and ((engine._map_pupils is not None) == (engine_class is SequentialMomentum))
        misfits = [engine.update()[0] for _ in range(6)]
        engine.close()
        results.append((engine.spectrum().copy(), engine.calibration().pupil.maps, misfits))
    (formed, formed_maps, formed_misfits), (stored, stored_maps, stored_misfits) = results
    np.testing.assert_array_equal(formed, stored)
    np.testing.assert_array_equal(formed_maps, stored_maps)
    assert formed_misfits == stored_misfits


def test_momentum_step_agrees():
    rng = np.random.default_rng(6)
    arrays = [(rng.standard_normal((16, 16)) + 1j * rng.standard_normal((16, 16))).astype(np.complex64)
              for _ in range(3)]

    def run():
        spectrum, anchor, velocity = (a.copy() for a in arrays)
        change, norm = kernels.momentum_step(spectrum, anchor, velocity, 0.7)
        return spectrum, anchor, velocity, np.array([change, norm])

    fast, slow = _both(run)
    expected_velocity = 0.7 * arrays[2] + (arrays[0] - arrays[1])
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_allclose(fast[2], expected_velocity, atol=1e-5)
    np.testing.assert_allclose(fast[0], arrays[0] + 0.7 * expected_velocity, atol=1e-5)
    np.testing.assert_array_equal(fast[1], fast[0])
    change, norm = fast[3]
    assert change == pytest.approx(np.sum(np.abs(fast[0] - arrays[1]) ** 2), rel=1e-4)
    assert norm == pytest.approx(np.sum(np.abs(arrays[1]) ** 2), rel=1e-4)
