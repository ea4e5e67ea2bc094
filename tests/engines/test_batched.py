"""The batched engines (numpy here, CuPy on a GPU) against the CPU engines on a small simulated problem."""

import numpy as np
import pytest

from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions
from cca_cli.engines.base import run_engine
from cca_cli.engines import batched
from cca_cli.engines.batched import (BatchedAlternatingMinimization, BatchedMomentum, BoxOperator, RpieFactors,
                                     merged_steps, unsupported_options)
from cca_cli.engines.calibrator import subset_layout
from cca_cli.engines.momentum import MAX_LANES, MAX_THREADS, MomentumOptions, SequentialMomentum, lanes_for
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.schedule import build_schedule
from cca_cli.metrics import rmse
from cca_cli.optics import backend, fft, kernels
from cca_cli.optics.backend import DeviceUnavailable
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import band_layout, square_scan
from cca_cli.targets import resolution_chart

SIZE = 64
RADIUS = 6.0


@pytest.fixture(scope="module")
def simulated():
    """A 5 x 5 scan of a resolution chart: model, band-grid captures, truth and the centre capture's index."""
    scan = square_scan(5, 2 * RADIUS * (1 - 0.61))
    layout = band_layout(scan.centres_yx_m, RADIUS, sensor_size=SIZE)
    model = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, RADIUS))
    truth = np.asarray(resolution_chart(SIZE, widths=(4, 3, 2, 1)).image, np.complex64)
    images = model.sensor_intensity(fft.fft2c(truth).astype(np.complex64))
    weights = np.random.default_rng(0).uniform(0.5, 1.0, images.shape).astype(np.float32)
    return model, images, weights, truth, scan.centre_index


def _relative(a, b) -> float:
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(a)).max())


@pytest.mark.parametrize("weighted", [False, True])
def test_batched_altmin_is_the_cpu_engine_to_float32_rounding(simulated, weighted):
    model, images, weights, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images, weights if weighted else None)
    options = AltMinOptions(max_iterations=10, tol=0.0, threads=1)
    cpu, cpu_history = run_engine(AlternatingMinimization(problem, options))
    batched, history = run_engine(BatchedAlternatingMinimization(problem, options, xp=np))
    assert batched.dtype == np.complex64 and batched.shape == model.spectrum_shape
    assert _relative(cpu, batched) < 1e-5
    np.testing.assert_allclose(history["residual"], cpu_history["residual"], rtol=1e-4)
    np.testing.assert_allclose(history["change"], cpu_history["change"], rtol=1e-3)


@pytest.mark.parametrize("options", [{}, {"cost": "poisson"}, {"pupil_recovery": "shared", "pupil_model": "full"},
                                     {"pupil_recovery": "shared", "pupil_model": "smooth", "eta": 0.3},
                                     {"pupil_recovery": "shared", "pupil_model": "zernike"},
                                     {"pupil_recovery": "shared", "pupil_model": "smooth", "pupil_tilt": "pinned",
                                      "alpha": 0.3, "hold_back": 0.1, "hold_back_patience": 2}])
def test_batched_momentum_in_the_cpu_order_is_the_cpu_engine(simulated, options):
    """Two lanes visit the captures as the CPU engine with one thread does: the same passes, to rounding."""
    model, images, _, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    opts = MomentumOptions(max_iterations=6, tol=0.0, threads=1, **options)
    cpu_engine = SequentialMomentum(problem, opts)
    cpu, cpu_history = run_engine(cpu_engine)
    engine = BatchedMomentum(problem, opts, xp=np, lanes=2)
    batched, history = run_engine(engine)
    assert _relative(cpu, batched) < 1e-5
    np.testing.assert_allclose(history["residual"], cpu_history["residual"], rtol=1e-4)
    if opts.hold_back:
        np.testing.assert_array_equal(engine.held_back, cpu_engine.held_back)
        np.testing.assert_allclose(history["held_back"], cpu_history["held_back"], rtol=1e-4)
    if opts.pupil_recovery != "none":
        np.testing.assert_allclose(engine.calibration().pupils, cpu_engine.calibration().pupils, atol=1e-5)


@pytest.mark.parametrize("threads", [1, 4, 16])
def test_batched_momentum_given_threads_visits_as_the_cpu_engine_with_them(simulated, threads):
    """``threads`` set: the batched engine takes the CPU engine's lanes for that count, so the two agree."""
    model, images, _, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    opts = MomentumOptions(max_iterations=6, tol=0.0, threads=threads, pupil_recovery="shared", pupil_model="smooth")
    cpu, _ = run_engine(SequentialMomentum(problem, opts))
    engine = BatchedMomentum(problem, opts, xp=np)
    assert engine._lanes == lanes_for(min(threads, MAX_THREADS))
    batched, _ = run_engine(engine)
    assert _relative(cpu, batched) < 1e-5
    unset = BatchedMomentum(problem, MomentumOptions(max_iterations=1, tol=0.0), xp=np)
    assert unset._lanes == MAX_LANES


@pytest.mark.parametrize("threads", [1, 4, 16])
def test_batched_momentum_takes_the_cpu_engine_s_lanes_for_few_captures_too(simulated, threads):
    """The CPU engine uses no more threads than captures; the batched engine's lanes follow the same rule."""
    model, images, _, _, _ = simulated
    few = [0, 1, 2]
    small = ForwardModel(subset_layout(model.layout, np.array(few)), model.pupil_boxes[few])
    problem = PhaseRetrievalProblem.from_sensor_images(small, images[few])
    opts = MomentumOptions(max_iterations=1, tol=0.0, threads=threads)
    cpu = SequentialMomentum(problem, opts)
    assert BatchedMomentum(problem, opts, xp=np)._lanes == cpu._lanes
    cpu.close()


@pytest.mark.parametrize("pupil_model", ["full", "zernike"])
def test_batched_momentum_recovers_one_pupil_per_camera(simulated, pupil_model):
    model, images, _, _, _ = simulated
    cameras = np.arange(model.n_images) % 3     # three cameras: the pupil sums are scattered per camera
    problem = PhaseRetrievalProblem.from_sensor_images(model, images, pupil_index=cameras)
    opts = MomentumOptions(max_iterations=4, tol=0.0, threads=1, pupil_recovery="per_camera",
                           pupil_model=pupil_model)
    cpu_engine = SequentialMomentum(problem, opts)
    cpu, _ = run_engine(cpu_engine)
    engine = BatchedMomentum(problem, opts, xp=np, lanes=2)
    batched, _ = run_engine(engine)
    assert _relative(cpu, batched) < 1e-5
    found, expected = engine.calibration().pupil, cpu_engine.calibration().pupil
    assert found.maps.shape[0] == 3
    np.testing.assert_allclose(found.maps, expected.maps, atol=1e-5)
    np.testing.assert_allclose(found.coefficients, expected.coefficients, atol=1e-6)


def test_batched_momentum_with_every_lane_in_one_call_recovers_as_well(simulated):
    """Eight lanes (a GPU's calls) change the visiting order, not what the recovery reaches."""
    model, images, _, truth, centre = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    opts = MomentumOptions(max_iterations=25, tol=0.0, threads=1)
    cpu, cpu_history = run_engine(SequentialMomentum(problem, opts))
    batched, history = run_engine(BatchedMomentum(problem, opts, xp=np, lanes=8))
    truth_intensity = np.abs(truth) ** 2
    errors = [rmse((np.abs(fft.ifft2c(s)) ** 2).astype(np.float32), truth_intensity) for s in (cpu, batched)]
    observed = rmse(fft.fourier_resample(images[centre:centre + 1], SIZE)[0], truth_intensity)
    assert errors[1] < 0.7 * observed
    assert errors[1] < 1.05 * errors[0]
    assert history["residual"][-1] < 1.5 * cpu_history["residual"][-1]
    assert history["residual"][-1] < 1e-2 * history["residual"][0]


def test_merged_steps_visit_every_capture_once_with_disjoint_boxes(simulated):
    model, _, _, _, _ = simulated
    layout = model.layout
    distances = np.hypot(*layout.centres_px.T)
    schedule = build_schedule(layout.box_origins, layout.box_size, distances, 2, lanes=8)
    steps = merged_steps(schedule)
    assert np.array_equal(np.sort(np.concatenate(steps)), np.arange(model.n_images))
    b = layout.box_size
    origins = layout.box_origins[schedule.order]
    for phase in schedule.phases:   # boxes of different lanes never overlap: one call equals running them in turn
        cover = [np.zeros(model.spectrum_shape, bool) for _ in phase.lanes]
        for lane, seen in zip(phase.lanes, cover):
            for batch in lane:
                for y0, x0 in origins[batch]:
                    seen[y0:y0 + b, x0:x0 + b] = True
        assert np.sum(cover, axis=0).max() <= 1


def test_the_box_operator_is_the_forward_model(simulated):
    model, _, _, truth, _ = simulated
    spectrum = fft.fft2c(truth).astype(np.complex64)
    operator = BoxOperator(np, model.layout)
    everything = slice(0, model.n_images)
    fields = operator.fields(spectrum, everything, model.pupil_boxes)
    np.testing.assert_allclose(fields, model.forward(spectrum), atol=1e-5 * np.abs(fields).max())
    adjoint = np.zeros(model.spectrum_shape, np.complex64)
    operator.scatter(operator.spectra(fields.copy()), everything, adjoint, np.conj(model.pupil_boxes))
    expected = model.adjoint(model.forward(spectrum))
    np.testing.assert_allclose(adjoint, expected, atol=1e-5 * np.abs(expected).max())


@pytest.mark.parametrize("group_bytes", [batched.FIELD_BYTES, 3 * SIZE * SIZE * 4])
def test_rpie_factors_on_the_device_are_the_compiled_kernels(simulated, monkeypatch, group_bytes):
    """Batches of uneven sizes, out of order, formed together or a few batches at a time."""
    model, _, _, _, _ = simulated
    layout = model.layout
    monkeypatch.setattr(batched, "FIELD_BYTES", group_bytes)
    rng = np.random.default_rng(3)
    shape = (model.n_images, layout.box_size, layout.box_size)
    pupils = (model.pupils * np.exp(1j * rng.uniform(0, 1, shape)) * rng.uniform(0.5, 1.5, shape)).astype(np.complex64)
    batches = [slice(8, 20), slice(0, 8), slice(20, 23), slice(23, model.n_images)]
    options = dict(alpha=0.3, tau=1e-3, scale=0.7)
    expected = np.zeros_like(pupils)
    kernels.rpie_factors(pupils, np.ascontiguousarray(layout.box_origins, np.int64),
                         np.array([[b.start, b.stop] for b in batches], np.int64),
                         coverage=np.zeros(model.spectrum_shape, np.float32), out=expected, **options)
    found = RpieFactors(np, BoxOperator(np, layout), batches, **options)(pupils)
    np.testing.assert_allclose(found, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())
    assert len(RpieFactors(np, BoxOperator(np, layout), batches, **options)._groups) == (1 if group_bytes > 1e6 else 2)


def test_checkpoints_move_between_the_cpu_and_the_batched_engine(simulated):
    model, images, _, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    opts = MomentumOptions(max_iterations=6, tol=0.0, threads=1, pupil_recovery="shared", pupil_model="full")
    straight, _ = run_engine(BatchedMomentum(problem, opts, xp=np, lanes=2))
    first = SequentialMomentum(problem, opts)
    for _ in range(3):
        first.update()
    state = first.state()
    resumed = BatchedMomentum(problem, opts, xp=np, lanes=2)
    assert set(resumed.state()) == set(state)
    resumed.restore(state)
    spectrum, _ = run_engine(resumed)
    assert resumed.stopping.iteration == 6
    # The restored pupil step cannot be undone (as on the CPU), so the runs may part slightly.
    assert _relative(straight, spectrum) < 1e-2


@pytest.mark.parametrize("option, value", [("position_refinement", "per_image"), ("brightness", True)])
def test_options_the_gpu_engine_lacks_are_named(simulated, option, value):
    model, images, _, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    opts = MomentumOptions(**{option: value})
    assert unsupported_options(opts)
    with pytest.raises(DeviceUnavailable, match=f"{option}: .*device cpu"):
        BatchedMomentum(problem, opts, xp=np)
    assert unsupported_options(AltMinOptions()) == []
    for pupil_model in ("full", "smooth", "zernike"):
        assert unsupported_options(MomentumOptions(pupil_recovery="per_camera", pupil_model=pupil_model,
                                                   batch_growth=2)) == []


# ----------------------------------------------------------------------------- on a GPU (skipped without one)
def _cupy():
    if not backend.device_status().cuda:
        pytest.skip(f"needs CuPy and a CUDA GPU ({backend.device_status().summary})")
    return backend.cupy_module()


@pytest.mark.gpu
def test_gpu_altmin_agrees_with_the_cpu_engine(simulated):
    cupy = _cupy()
    model, images, weights, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images, weights)
    options = AltMinOptions(max_iterations=10, tol=0.0, threads=1)
    cpu, _ = run_engine(AlternatingMinimization(problem, options))
    gpu, _ = run_engine(BatchedAlternatingMinimization(problem, options, xp=cupy))
    assert isinstance(gpu, np.ndarray)
    assert _relative(cpu, gpu) <= 1e-4


@pytest.mark.gpu
@pytest.mark.parametrize("options", [{}, {"pupil_recovery": "shared", "pupil_model": "full"},
                                     {"pupil_recovery": "shared", "pupil_model": "zernike"}])
def test_gpu_momentum_agrees_with_the_cpu_engine(simulated, options):
    cupy = _cupy()
    model, images, _, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    opts = MomentumOptions(max_iterations=6, tol=0.0, threads=1, **options)
    cpu, _ = run_engine(SequentialMomentum(problem, opts))
    gpu, _ = run_engine(BatchedMomentum(problem, opts, xp=cupy, lanes=2))
    assert _relative(cpu, gpu) <= 1e-4


GROWING = {"pupil_recovery": "shared", "pupil_model": "smooth", "pupil_tilt": "pinned", "alpha": 0.3,
           "hold_back": 0.1, "batch": 3, "batch_growth": 2, "plateau": 0.5, "plateau_window": 1}


def test_the_growing_options_grow_batches_and_step_the_pupil(simulated):
    """The options the recorded-pass test below uses lay the captures out again mid-run (numpy, no graph)."""
    model, images, _, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    engine = BatchedMomentum(problem, MomentumOptions(max_iterations=12, tol=0.0, threads=1, **GROWING), xp=np)
    run_engine(engine)
    assert engine.batch >= 4 * GROWING["batch"]
    assert not engine._graphed.recorded


@pytest.mark.gpu
@pytest.mark.parametrize("engine_class", ["altmin", "momentum"])
def test_gpu_recorded_passes_are_the_launched_ones(simulated, engine_class, monkeypatch):
    """Replayed CUDA graphs give the passes launched step by step, through pupil steps and growing batches."""
    cupy = _cupy()
    recordings = []
    record = backend.GraphedWork._record
    monkeypatch.setattr(backend.GraphedWork, "_record", lambda self: (recordings.append(1), record(self))[1])
    model, images, weights, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images, weights)
    if engine_class == "altmin":
        options = AltMinOptions(max_iterations=10, tol=0.0, threads=1)
        make = lambda graphs: BatchedAlternatingMinimization(problem, options, xp=cupy, graphs=graphs)  # noqa: E731
    else:
        options = MomentumOptions(max_iterations=12, tol=0.0, threads=1, **GROWING)
        make = lambda graphs: BatchedMomentum(problem, options, xp=cupy, graphs=graphs)  # noqa: E731
    recorded_engine, launched_engine = make(True), make(False)
    recorded, recorded_history = run_engine(recorded_engine)
    launched, launched_history = run_engine(launched_engine)
    # altmin records once; momentum once per arrangement that lasts two passes (growing batches lay out again)
    assert (len(recordings) == 1 if engine_class == "altmin" else len(recordings) >= 2)
    assert not launched_engine._graphed.recorded
    assert _relative(launched, recorded) <= 1e-5
    np.testing.assert_allclose(recorded_history["residual"], launched_history["residual"], rtol=1e-4)
    if engine_class == "momentum":
        assert recorded_engine.batch == launched_engine.batch > GROWING["batch"]
        np.testing.assert_allclose(recorded_engine.calibration().pupils, launched_engine.calibration().pupils,
                                   atol=1e-5)


@pytest.mark.gpu
@pytest.mark.parametrize("options", [None, {}, {"pupil_recovery": "shared", "pupil_model": "smooth"},
                                     {"pupil_recovery": "shared", "pupil_model": "zernike"}])
def test_gpu_runs_repeat_bit_for_bit(simulated, options):
    """The same captures and options give the same bits on the GPU (sums in capture order, no atomics)."""
    cupy = _cupy()
    model, images, weights, _, _ = simulated
    problem = PhaseRetrievalProblem.from_sensor_images(model, images, weights)
    runs = []
    for _ in range(2):
        if options is None:
            engine = BatchedAlternatingMinimization(problem, AltMinOptions(max_iterations=8, tol=0.0), xp=cupy)
        else:
            engine = BatchedMomentum(problem, MomentumOptions(max_iterations=8, tol=0.0, **options), xp=cupy)
        runs.append(run_engine(engine)[0])
    np.testing.assert_array_equal(runs[0], runs[1])
