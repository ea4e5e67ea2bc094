"""FFTW planning: bounded, chosen by how long the transforms run, reused from the cache, interruptible."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from typer.testing import CliRunner

from cca_cli.commands.app import app
from cca_cli.optics import fft, fftw_plans

pytestmark = pytest.mark.skipif(not fft.HAVE_PYFFTW, reason="FFTW planning needs pyfftw")
RNG = np.random.default_rng(5)


@pytest.fixture
def cold_cache(tmp_path, monkeypatch):
    """FFTW as on a fresh machine: no wisdom in memory, an empty cache directory."""
    import pyfftw

    monkeypatch.setenv("CCA_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CCA_FFTW_PLANNING", "auto")
    monkeypatch.setattr(fftw_plans, "_wisdom_loaded", False)
    monkeypatch.setattr(fftw_plans, "_step_cost", dict(fftw_plans._step_cost))
    monkeypatch.setattr(fftw_plans, "_budgets", {})
    with fft.PLANNER_LOCK:
        pyfftw.forget_wisdom()
    return tmp_path


def _band_data(shape, rows):
    data = np.zeros(shape, np.complex64)
    data[:, rows[0]:rows[1]] = RNG.standard_normal((shape[0], rows[1] - rows[0], shape[2]))
    return data


def test_auto_planning_times_nothing_up_front_then_improves_the_plans_in_use(cold_cache, monkeypatch):
    monkeypatch.setattr(fftw_plans, "UPGRADE_SHARE", 50.0)  # improve eagerly: the mechanism is tested here, not the budget
    before = fft.planning_seconds()
    transform = fft.BandedFFT2(fft.zeros((2, 16, 16)), 4, 12, threads=1)
    plans = transform._plans
    assert fft.planning_seconds() == before and set(plans.level) == {"estimate"}
    data = _band_data((2, 16, 16), (4, 12))
    deadline = time.perf_counter() + 60  # planning steps are paced by the transform time: a loaded machine needs longer
    while time.perf_counter() < deadline:  # the data survive every planning step taken between the calls
        transform.buffer[...] = data
        transform.inverse(2)
        np.testing.assert_allclose(transform.buffer, np.fft.ifft2(data) * 256, atol=1e-3)
        transform.forward(2)
        np.testing.assert_allclose(transform.buffer[:, 4:12], data[:, 4:12] * 256, atol=1e-2)
        if set(plans.level[4:]) == {"patient"}:
            break
    assert plans.level[4:] == ["patient"] * 4  # the count-2 transforms that ran
    assert plans.level[:4] == ["estimate"] * 4  # the count-1 transforms never ran
    assert fft.planning_seconds() > before
    assert (cold_cache / fftw_plans._wisdom_path().name).is_file()
    # Another transform of the same shape starts from what was found, without timing anything.
    spent = fft.planning_seconds()
    again = fft.BandedFFT2(fft.zeros((2, 16, 16)), 4, 12, threads=1)
    assert again._plans.level[4:] == ["patient"] * 4 and fft.planning_seconds() == spent


def test_auto_planning_spends_at_most_its_share_of_the_run(cold_cache, monkeypatch):
    monkeypatch.setattr(fftw_plans, "SHAPE_SECONDS", 0.2)  # reach the long-run share within the test
    transform = fft.BandedFFT2(fft.zeros((16, 48, 48)), 12, 36, threads=1)
    transform.buffer[...] = _band_data((16, 48, 48), (12, 36))
    start = time.perf_counter()
    while time.perf_counter() - start < 1.0:
        transform.inverse(16)
        transform.forward(16)
    budget = transform._plans.budget
    assert budget.busy > 0.2
    # A step is cut off at what the budget allows, or at twice its expected cost.
    assert budget.allowance() >= -2 * max(fftw_plans._step_cost.values()) - 0.05


def test_the_budget_lets_a_step_through_only_when_it_fits(monkeypatch):
    budget = fftw_plans._Budget()
    budget.busy, budget.spent = 4.0, 0.5
    assert budget.allows(0.5)  # 1.0 s in all is a quarter of 4 s
    assert not budget.allows(0.6) and budget.next_check == pytest.approx(1.1 / fftw_plans.UPGRADE_SHARE)
    budget.busy, budget.spent = 100.0, 2.9  # past SHAPE_SECONDS the long-run share applies
    assert not budget.allows(7.2) and budget.next_check == pytest.approx(10.1 / fftw_plans.LONG_RUN_SHARE)
    assert budget.allows(7.0)


def test_short_runs_plan_next_to_nothing(cold_cache):
    transform = fft.InPlaceFFT2(fft.zeros((4, 40, 40)), threads=1)
    for _ in range(5):
        transform.forward()
        transform.inverse()
    assert transform._plans.budget.spent == 0.0 and set(transform._plans.level) == {"estimate"}


@pytest.fixture
def cold_exact(cold_cache, monkeypatch):
    """``exact`` planning on a fresh machine: no checked plans in memory or in the cache."""
    monkeypatch.setenv("CCA_FFTW_PLANNING", "exact")
    monkeypatch.setattr(fftw_plans, "_exact_plans", {})
    monkeypatch.setattr(fftw_plans, "_exact_checked", set())
    monkeypatch.setattr(fftw_plans, "_exact_loaded", False)
    monkeypatch.setattr(fftw_plans, "UPGRADE_SHARE", 50.0)  # improve eagerly: the mechanism is tested, not the budget
    return cold_cache


def _transformed(transform, data, rounds):
    """The inverse then forward transform of ``data`` (count 2), ``rounds`` times: each round's result."""
    results = []
    for _ in range(rounds):
        transform.buffer[...] = data
        transform.inverse(2)
        inverse = transform.buffer.copy()
        transform.forward(2)
        results.append((inverse, transform.buffer.copy()))
    return results


@pytest.mark.parametrize("size", [48, 54])
def test_exact_planning_keeps_only_timed_plans_that_round_as_the_estimated_ones(cold_exact, size):
    import pyfftw

    band = (size // 4, size - size // 4)
    data = _band_data((2, size, size), band)
    reference = fft.BandedFFT2(fft.zeros((2, size, size)), *band, threads=1, effort="estimate")
    expected = _transformed(reference, data, 1)[0]
    transform = fft.BandedFFT2(fft.zeros((2, size, size)), *band, threads=1)
    plans = transform._plans
    assert plans.exact and set(plans.level) == {"estimate"}
    deadline = time.perf_counter() + 60
    while time.perf_counter() < deadline:
        for inverse, forward in _transformed(transform, data, 5):  # bit for bit, before and after each step
            np.testing.assert_array_equal(inverse, expected[0])
            np.testing.assert_array_equal(forward, expected[1])
        if all(plans.level[i] == "measure" or i in plans.budget.stuck for i in range(4, 8)):
            break
    verdicts = [fftw_plans._exact_plans[plans._key(i)][0] for i in range(4, 8)]
    assert set(verdicts) <= {"measure", "rejected"}
    assert [plans.level[i] for i in range(4, 8)] == ["measure" if v == "measure" else "estimate" for v in verdicts]
    assert plans.level[:4] == ["estimate"] * 4  # the count-1 transforms never ran
    with fft.PLANNER_LOCK:  # nothing timed is left in FFTW's wisdom for a later estimated plan to pick up
        assert pyfftw.export_wisdom() == _empty_wisdom()
    machine, saved = fftw_plans._read_exact_file()
    assert machine == fftw_plans._machine()
    assert {key: entry[0] for key, entry in saved.items()} == {plans._key(i): v for i, v in zip(range(4, 8), verdicts)}


def _empty_wisdom():
    import pyfftw

    pyfftw.forget_wisdom()
    return pyfftw.export_wisdom()


def test_a_timed_plan_that_rounds_otherwise_is_never_used(cold_exact, monkeypatch):
    data = _band_data((2, 32, 32), (8, 24))
    expected = _transformed(fft.BandedFFT2(fft.zeros((2, 32, 32)), 8, 24, threads=1, effort="estimate"), data, 1)[0]
    real_plan = fftw_plans._pyfftw_plan

    def other_algorithm(view, spec, threads, level, **options):  # a timed "plan" that transforms otherwise
        if level == "measure" and not options.get("wisdom_only"):
            return real_plan(view, spec._replace(sign=-spec.sign), threads, "estimate")
        return real_plan(view, spec, threads, level, **options)

    monkeypatch.setattr(fftw_plans, "_pyfftw_plan", other_algorithm)
    transform = fft.BandedFFT2(fft.zeros((2, 32, 32)), 8, 24, threads=1)
    plans = transform._plans
    deadline = time.perf_counter() + 60
    while time.perf_counter() < deadline and not set(range(4, 8)) <= plans.budget.stuck:
        for inverse, forward in _transformed(transform, data, 5):
            np.testing.assert_array_equal(inverse, expected[0])
            np.testing.assert_array_equal(forward, expected[1])
    assert set(range(4, 8)) <= plans.budget.stuck and set(plans.level) == {"estimate"}
    assert {fftw_plans._exact_plans[plans._key(i)] for i in range(4, 8)} == {("rejected", "measure")}


def test_a_cached_plan_is_checked_again_before_use(cold_exact):
    buffer = fft.zeros((2, 24, 24))  # both transforms share one buffer, and so their keys
    transform = fft.BandedFFT2(buffer, 6, 18, threads=1)
    key = transform._plans._key(4)
    wrong = transform._plans._key(7)  # another transform's wisdom cannot make this one's plan
    fftw_plans._exact_plans.clear()
    with fft.PLANNER_LOCK:
        import pyfftw

        pyfftw.forget_wisdom()
        scratch = fftw_plans._scratch_like(transform.buffer)
        spec = transform._plans.specs[7]
        fftw_plans._pyfftw_plan(spec.view(scratch), spec, 1, "measure")
        foreign = pyfftw.export_wisdom()
        pyfftw.forget_wisdom()
    fftw_plans._exact_plans[key] = ("measure", foreign)
    fftw_plans._exact_plans[wrong] = ("measure", foreign)
    own_verdict = transform._plans._rounds_exactly(7, "measure", foreign)[0]
    again = fft.BandedFFT2(buffer, 6, 18, threads=1)
    assert again._plans.level[4] == "estimate" and 4 in again._plans.budget.stuck
    assert fftw_plans._exact_plans[key] == ("rejected", "measure")
    # Its own wisdom: checked, then used if it rounds as the estimated plan (FFTW's choice on this machine).
    assert again._plans.level[7] == ("measure" if own_verdict else "estimate")


def _saved_plans_of(transform, i):
    """Take one ``exact`` planning step for transform ``i`` (saved to the cache), then forget it as a new process would."""
    plans = transform._plans
    with fft.PLANNER_LOCK:
        plans._improve_exact(i)
    assert fftw_plans._read_exact_file()[1], "no verdict was saved, so this test checks nothing"
    fftw_plans._exact_plans.clear()
    fftw_plans._exact_checked.clear()
    fftw_plans._exact_loaded = False


def test_plans_saved_on_this_machine_are_trusted_and_another_machines_are_checked(cold_exact, monkeypatch):
    import pickle

    buffer = fft.zeros((2, 20, 20))
    transform = fft.BandedFFT2(buffer, 5, 15, threads=1)
    transform._plans.budget.busy = 100.0  # the step fits the budget
    _saved_plans_of(transform, 4)
    checks = []
    real_check = fftw_plans.PlanSet._rounds_exactly
    monkeypatch.setattr(fftw_plans.PlanSet, "_rounds_exactly",
                        lambda self, *a, **k: checks.append(a) or real_check(self, *a, **k))
    same_machine = fft.BandedFFT2(buffer, 5, 15, threads=1)
    assert checks == []  # a verdict reached here is not checked again
    machine, saved = fftw_plans._read_exact_file()
    verdict = saved[same_machine._plans._key(4)][0]
    assert same_machine._plans.level[4] == ("measure" if verdict == "measure" else "estimate")
    # The same file as written by another machine: its timed plans are checked before use, its rejections ignored.
    fftw_plans._exact_path().write_bytes(pickle.dumps({"machine": "another", "plans": saved}))
    fftw_plans._exact_plans.clear()
    fftw_plans._exact_checked.clear()
    fftw_plans._exact_loaded = False
    other = fft.BandedFFT2(buffer, 5, 15, threads=1)
    assert len(checks) == (1 if verdict == "measure" else 0)
    assert 4 not in other._plans.budget.stuck  # not rejected here, so still open to a search
    assert other._plans.level[4] == same_machine._plans.level[4]
    with fft.PLANNER_LOCK:
        fftw_plans._save_exact()
    assert fftw_plans._read_exact_file()[0] == fftw_plans._machine()  # replaced by what this machine checked


def test_a_damaged_exact_cache_only_costs_planning_time(cold_exact):
    fftw_plans._exact_path().parent.mkdir(parents=True, exist_ok=True)
    fftw_plans._exact_path().write_bytes(b"not a pickle")
    assert fftw_plans._read_exact_file() == (None, {})
    import pickle

    fftw_plans._exact_path().write_bytes(pickle.dumps({("a",): ("measure", "not bytes"), ("b",): ("rejected", "x")}))
    assert fftw_plans._read_exact_file() == (None, {})
    fftw_plans._exact_path().write_bytes(pickle.dumps({"machine": "m", "plans": {("a",): ("measure", "not bytes")}}))
    assert fftw_plans._read_exact_file() == ("m", {})
    transform = fft.BandedFFT2(fft.zeros((2, 16, 16)), 4, 12, threads=1)
    assert set(transform._plans.level) == {"estimate"}


CACHE_CHILD = textwrap.dedent('''
    import time
    from cca_cli.optics import fft
    start = time.perf_counter()
    transform = fft.BandedFFT2(fft.zeros((4, 20, 20)), 5, 15, threads=1)
    print(sorted(set(transform._plans.level)), round(fft.planning_seconds(), 3), round(time.perf_counter() - start, 3))
''')


@pytest.mark.slow
def test_a_new_process_reuses_the_plans_saved_in_the_cache(tmp_path):
    env = dict(os.environ, CCA_CACHE_DIR=str(tmp_path))
    first = subprocess.run([sys.executable, "-c", CACHE_CHILD], env=dict(env, CCA_FFTW_PLANNING="measure"),
                           capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    assert first.stdout.startswith("['measure']")
    second = subprocess.run([sys.executable, "-c", CACHE_CHILD], env=dict(env, CCA_FFTW_PLANNING="auto"),
                            capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr
    levels, timed, _ = second.stdout.rsplit(" ", 2)
    assert levels == "['measure']" and float(timed) == 0.0


INTERRUPT_CHILD = textwrap.dedent('''
    import numpy as np
    from cca_cli.optics import fft, fftw_plans
    fftw_plans.UPGRADE_SHARE = fftw_plans.LONG_RUN_SHARE = 1e6  # plan continuously: every call may take a planning step
    transform = fft.BandedFFT2(fft.zeros((64, 96, 96)), 24, 72, threads=1)
    transform.buffer[...] = 1
    print("planning", flush=True)
    while True:
        for count in (1, 2, 4, 8, 16, 32, 64):
            transform.inverse(count)
            transform.forward(count)
''')


@pytest.mark.slow
def test_ctrl_c_during_planning_is_answered_within_one_planning_step(tmp_path):
    env = dict(os.environ, CCA_CACHE_DIR=str(tmp_path), CCA_FFTW_PLANNING="auto")
    child = subprocess.Popen([sys.executable, "-c", INTERRUPT_CHILD], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "planning"
        time.sleep(1.0)
        assert child.poll() is None
        sent = time.perf_counter()
        child.send_signal(signal.SIGINT)
        _, stderr = child.communicate(timeout=60)
        answered = time.perf_counter() - sent
    finally:
        if child.poll() is None:
            child.kill()
    assert "KeyboardInterrupt" in stderr
    assert answered < fftw_plans.STEP_SECONDS + 1.5, answered


def test_an_unknown_planning_effort_is_one_line_naming_the_variable(tmp_path, write_config, monkeypatch):
    monkeypatch.setenv("CCA_FFTW_PLANNING", "bogus")
    captures = tmp_path / "captures.h5"
    result = CliRunner().invoke(app, ["simulate", str(write_config()), "-o", str(captures), "--quiet"])
    assert result.exit_code == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert lines == ["error: environment variable CCA_FFTW_PLANNING='bogus' is not one of exact, estimate, "
                     "auto, measure, patient; unset it or pick one"]
    assert not captures.exists()


def test_a_recovery_with_exact_planning_equals_the_estimated_one_bit_for_bit(cold_exact, monkeypatch):
    import cca_cli as cca

    geometry = cca.led_array(cca.led_grid_sines(5, pitch_m=4e-3, height_m=60e-3), wavelength_m=532e-9,
                             numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6, image_pixels=48)
    chart = cca.resolution_chart(48 * 3, widths=(6, 4, 3, 2)).image
    captures = cca.CaptureSet(cca.simulate(chart, geometry, snr_db=35), geometry, units="counts/s", boundary="open")
    runs = {}
    for effort in ("estimate", "exact"):
        monkeypatch.setenv("CCA_FFTW_PLANNING", effort)
        before = fft.planning_seconds()
        runs[effort] = cca.reconstruct(captures, engine="momentum", iterations=40, threads=1)
        runs[effort + " timed"] = fft.planning_seconds() - before
    assert runs["estimate timed"] == 0.0 and runs["exact timed"] > 0.0  # exact mode searched timed plans
    assert fftw_plans._exact_plans  # and decided on some
    assert runs["exact"].stopped_by == runs["estimate"].stopped_by
    np.testing.assert_array_equal(runs["exact"].spectrum, runs["estimate"].spectrum)
    np.testing.assert_array_equal(runs["exact"].object, runs["estimate"].object)
