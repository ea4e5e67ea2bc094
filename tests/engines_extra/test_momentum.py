"""Sequential momentum engine and position refinement on a small resolution-chart case."""

import numpy as np
import pytest

from cca_cli.engines import calibration as cal
from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions
from cca_cli.engines.base import run_engine
from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.engines.registry import get_engine
from cca_cli.engines.stopping import StoppingPolicy
from cca_cli.metrics import rmse
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.noise import add_gaussian_noise
from cca_cli.optics.pupil import circular_pupils
from cca_cli.optics.zernike import zernike_phase
from cca_cli.sampling.grid import band_layout, square_scan
from cca_cli.sampling.overlap import step_m
from cca_cli.targets import resolution_chart

RADIUS = 6.0


def make_case(*, position_error=0.0, snr_db=30.0, seed=0, size=96, grid=7):
    chart = resolution_chart(size, widths=(6, 4, 3, 2)).image
    centres = square_scan(grid, step_m(2 * RADIUS, 0.61)).centres_yx_m
    layout = band_layout(centres, RADIUS, hires_size=size)
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-position_error, position_error, centres.shape)
    truth_model = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres + offsets, RADIUS))
    images = truth_model.sensor_intensity(fft.fft2c(chart.astype(np.complex64)).astype(np.complex64))
    images = add_gaussian_noise(images, snr_db, rng)
    ideal = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, RADIUS))
    problem = PhaseRetrievalProblem.from_sensor_images(ideal, images)
    support = ideal.normal_diagonal() > 0
    band_truth = np.abs(fft.ifft2c(fft.fft2c(chart.astype(np.complex64)) * support)) ** 2
    return problem, chart ** 2, band_truth, offsets


def intensity(spectrum):
    return np.abs(fft.ifft2c(spectrum)) ** 2


def rmse_curve(engine, truth):
    curve = []
    while not engine.done():
        engine.update()
        curve.append(rmse(intensity(engine.spectrum()), truth))
    engine.close()
    return np.array(curve)


#: Engine options of the position-refinement tests.
REFINEMENT_RUN = dict(max_iterations=25, tol=0, batch=8)


@pytest.fixture(scope="module")
def clean_case():
    return make_case()


@pytest.fixture(scope="module")
def clean_recovery(clean_case):
    """The clean case recovered without refinement (:data:`REFINEMENT_RUN`)."""
    spectrum, _ = run_engine(SequentialMomentum(clean_case[0], MomentumOptions(**REFINEMENT_RUN)))
    return spectrum


def test_momentum_recovers_small_case(clean_case):
    problem, truth, band_truth, _ = clean_case
    spectrum, history = run_engine(SequentialMomentum(problem, MomentumOptions(max_iterations=30, tol=0)))
    assert spectrum.dtype == np.complex64
    assert history.iterations == 30
    assert history.records[-1].residual < 0.5 * history.records[0].residual
    # Near the noise floor relative to what the synthetic aperture can pass.
    assert rmse(intensity(spectrum), band_truth) < 0.02


def test_momentum_needs_fewer_iterations_than_altmin(clean_case):
    problem, _, band_truth, _ = clean_case
    am = rmse_curve(AlternatingMinimization(problem, AltMinOptions(max_iterations=60, tol=0)), band_truth)
    mo = rmse_curve(SequentialMomentum(problem, MomentumOptions(max_iterations=60, tol=0)), band_truth)
    target = 1.5 * min(am.min(), mo.min()) + 0.01
    first_am = int(np.argmax(am <= target)) + 1 if np.any(am <= target) else 10**6
    first_mo = int(np.argmax(mo <= target)) + 1
    assert np.any(mo <= target)
    assert first_mo < first_am / 2


def test_poisson_cost_and_weights_recover(clean_case):
    problem, _, band_truth, _ = clean_case
    weights = np.ones_like(problem.amplitudes)
    weights[:, :2, :] = 0.0  # a band of invalid pixels (field layout) must not break the fit
    weighted = PhaseRetrievalProblem(model=problem.model, amplitudes=problem.amplitudes, weights=weights)
    spectrum, history = run_engine(SequentialMomentum(
        weighted, MomentumOptions(max_iterations=30, tol=0, cost="poisson")))
    assert rmse(intensity(spectrum), band_truth) < 0.03
    assert history.records[-1].residual < history.records[0].residual


def test_registry_and_reconstruct_stage_keywords():
    entry = get_engine("momentum")
    options = entry.options(tau=1e-3, max_iterations=5, tol=1e-5)
    assert entry.engine_class() is SequentialMomentum and options.max_iterations == 5
    for bad in (dict(alpha=1.5), dict(beta=0), dict(eta=1.0), dict(cost="l1"), dict(batch=0)):
        with pytest.raises(ValueError):
            MomentumOptions(**bad)


def test_position_refinement_does_not_hurt_error_free_data(clean_case, clean_recovery):
    problem, _, band_truth, _ = clean_case
    plain = clean_recovery
    refined_engine = SequentialMomentum(problem, MomentumOptions(position_refinement="both", **REFINEMENT_RUN))
    refined, _ = run_engine(refined_engine)
    assert rmse(intensity(refined), band_truth) <= 1.05 * rmse(intensity(plain), band_truth)
    offsets = refined_engine.calibration().offsets
    assert np.abs(offsets).mean() < 0.05 and np.abs(offsets).max() < 0.3


@pytest.mark.parametrize("mode", ["per_image", "both"])
def test_position_refinement_recovers_random_offsets(clean_case, clean_recovery, mode):
    _, _, band_truth, _ = clean_case
    problem, _, _, true_offsets = make_case(position_error=1.0, seed=1)
    reference = rmse(intensity(clean_recovery), band_truth)
    plain, _ = run_engine(SequentialMomentum(problem, MomentumOptions(**REFINEMENT_RUN)))
    engine = SequentialMomentum(problem, MomentumOptions(position_refinement=mode, **REFINEMENT_RUN))
    refined, _ = run_engine(engine)
    assert rmse(intensity(plain), band_truth) > 3.0 * reference  # the errors matter ...
    assert rmse(intensity(refined), band_truth) <= 1.6 * reference  # ... and refinement removes most of it
    found = engine.calibration().offsets
    assert np.mean(np.abs(found - true_offsets)) < 0.2  # of 0.5 px on average


def test_pupil_functions_match_simulation_helpers():
    layout = band_layout(square_scan(3, 5.0).centres_yx_m, RADIUS, hires_size=48)
    offsets = np.full((layout.n_images, 2), 0.3)
    disc = cal.pupil_functions(layout, offsets=offsets)
    np.testing.assert_array_equal(disc.real, circular_pupils(layout.box_size, layout.box_centres + offsets, RADIUS))
    aberrated = cal.pupil_functions(layout, coefficients=[0.2, -0.1, 0.05], order=2)
    phase = zernike_phase(layout.box_size, layout.box_centres, RADIUS, [0.2, -0.1, 0.05])
    expected = circular_pupils(layout.box_size, layout.box_centres, RADIUS) * np.exp(1j * phase)
    np.testing.assert_allclose(aberrated, expected, atol=2e-5)
    assert 0 < cal.max_position_offset(layout) <= 2.0


def test_batch_growth_takes_inconsistent_data_past_the_small_batch_plateau():
    # Pupils displaced by up to a pixel that the model does not know: no spectrum fits every capture.
    problem = make_case(position_error=1.0, seed=3)[0]
    run = dict(max_iterations=300, tol=0, batch=4, plateau=0.01, plateau_window=5)
    fixed = SequentialMomentum(problem, MomentumOptions(**run))
    _, fixed_history = run_engine(fixed)
    growing = SequentialMomentum(problem, MomentumOptions(**run, batch_growth=2))
    batches, misfit = [], None
    while not growing.done():
        misfit = growing.update()[0]
        batches.append(growing.batch)
    growing.close()
    assert batches[0] == 4 and batches[-1] == problem.model.n_images   # 4, 8, 16, 32, then all 49
    assert len(set(batches)) == 5
    assert fixed.stopping.on_plateau() and growing.stopping.on_plateau()
    assert misfit < 0.97 * fixed_history.records[-1].residual


def test_a_shorter_growth_window_grows_sooner_and_still_stops_on_the_plateau_window():
    problem = make_case(position_error=1.0, seed=3)[0]
    run = dict(max_iterations=300, tol=0, batch=4, plateau=0.01, plateau_window=8, batch_growth=2)

    def stages(options):
        engine, batches = SequentialMomentum(problem, options), []
        while not engine.done():
            batches.append(engine.batch)   # the batch size this pass runs
            engine.update()
        engine.close()
        return engine, [batches.count(size) for size in sorted(set(batches))]

    slow, slow_stages = stages(MomentumOptions(**run))
    quick, quick_stages = stages(MomentumOptions(**run, growth_window=2))
    assert len(quick_stages) == len(slow_stages) == 5
    # Each batch size lasts more than its look-back: 9 passes at least with 8, 3 with 2 ...
    assert min(slow_stages[:-1]) >= 9 and min(quick_stages[:-1]) >= 3
    assert sum(quick_stages[:-1]) < sum(slow_stages[:-1])
    # ... but the last (every capture) ends only on a plateau over plateau_window passes.
    assert quick_stages[-1] >= 9 and quick.stopping.on_plateau() and slow.stopping.on_plateau()


def test_the_stopping_policy_grows_on_the_growth_window_and_ends_on_the_plateau_window():
    grown = []
    policy = StoppingPolicy(max_iterations=100, tol=0, plateau=0.01, plateau_window=6, growth_window=2,
                            can_grow=lambda: len(grown) < 1)
    flat = [policy.record(1.0, 1.0) for _ in range(3)]
    assert flat == [False, False, True]   # the third flat pass looks back two
    policy.grew()
    grown.append(True)
    ends = []
    while not policy.done():
        policy.record(1.0, 1.0)
        ends.append(policy.iteration)
    assert len(ends) == 7 and policy.reason() == "plateau"   # then seven passes: more than six to look back


@pytest.mark.parametrize("value", [0, -1])
def test_growth_window_is_checked(value):
    with pytest.raises(ValueError, match="growth_window must be ≥ 1"):
        MomentumOptions(growth_window=value)


def test_batch_growth_survives_a_checkpoint_restore():
    problem = make_case(position_error=1.0, seed=3)[0]
    options = MomentumOptions(max_iterations=60, tol=0, batch=4, plateau=0.01, plateau_window=5, batch_growth=2)
    engine = SequentialMomentum(problem, options)
    while engine.batch < 16:
        engine.update()
    state = engine.state()
    engine.close()
    resumed = SequentialMomentum(problem, options)
    resumed.restore(state)
    assert resumed.batch == engine.batch
    assert not resumed.stopping.on_plateau()
    resumed.close()


def test_batch_growth_is_checked():
    with pytest.raises(ValueError, match="batch_growth must be ≥ 1"):
        MomentumOptions(batch_growth=0)


def test_the_captures_held_back_spread_from_the_bright_field_outwards_and_spare_the_axis():
    from cca_cli.engines.momentum import held_back_captures

    centres = square_scan(9, 5.0).centres_yx_m
    radius = 8.0
    held = held_back_captures(centres, radius, 0.1)
    distance = np.hypot(*centres.T)
    assert held.size == 8 and int(np.argmin(distance)) not in held
    assert np.any(distance[held] < radius) and np.any(distance[held] >= radius)
    assert distance[held].max() == distance.max()                      # the outermost dark field too
    assert held_back_captures(centres, radius, 0.0).size == 0


def test_captures_held_back_end_the_run_and_it_returns_to_their_best_fit():
    problem = make_case(position_error=1.0, seed=3)[0]   # positions off: the model cannot fit every capture
    options = MomentumOptions(max_iterations=300, tol=0, batch=4, eta=0.7, hold_back=0.1, hold_back_patience=4)
    engine = SequentialMomentum(problem, options)
    spectra, held = [], []
    while not engine.done():
        engine.update()
        spectra.append(engine.spectrum().copy())
        held.append(engine.held_back_residual)
    engine.close()
    best = int(np.argmin(held))
    assert engine.stop_reason() == "held_back" and held[-1] > 1.01 * held[best]
    np.testing.assert_array_equal(engine.spectrum(), spectra[best])   # the run returned to its best state
    assert 0 < held[best] < held[0]
