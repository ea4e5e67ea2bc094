"""Calibration on simulated captures with known errors: LED-array geometry, per-camera pupils, full pupil maps."""

import numpy as np
import pytest

from cca_cli.engines import calibration as cal
from cca_cli.engines.base import run_engine
from cca_cli.engines.fit import fit_report
from cca_cli.engines.illumination import LedArrayModel, StageModel
from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.metrics import rmse
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.noise import add_gaussian_noise
from cca_cli.sampling.grid import band_layout, square_scan
from cca_cli.sampling.overlap import step_m
from cca_cli.targets import resolution_chart

#: A 7 x 7 LED array at unit height seen by an objective of pupil radius 10 px; 200 spectrum px per unit sin θ.
LED_RADIUS, PIXELS_PER_SINE, LED_SIZE = 10.0, 200.0, 160


def led_nominal_px():
    pitch = (np.arange(7) - 3) * 0.04
    tangent = np.stack(np.meshgrid(pitch, pitch, indexing="ij"), -1).reshape(-1, 2)
    return PIXELS_PER_SINE * tangent / np.sqrt(1 + np.sum(tangent ** 2, axis=1, keepdims=True))


def led_case(parameters=(0.0, 0.0, 0.0, 0.0), *, seed=0):
    """Captures of a chart lit by an LED array whose shift, rotation and height differ from the nominal."""
    chart = resolution_chart(LED_SIZE, widths=(8, 6, 4, 3, 2)).image.astype(np.complex64)
    spectrum = fft.fft2c(chart).astype(np.complex64)
    nominal = led_nominal_px()
    true_centres = LedArrayModel(nominal, PIXELS_PER_SINE).centres(np.asarray(parameters, float))
    layout = band_layout(true_centres, LED_RADIUS, hires_size=LED_SIZE)
    images = ForwardModel(layout, cal.pupil_functions(layout)).sensor_intensity(spectrum)
    images = add_gaussian_noise(images, 30.0, np.random.default_rng(seed))
    ideal_layout = band_layout(nominal, LED_RADIUS, hires_size=LED_SIZE)
    problem = PhaseRetrievalProblem.from_sensor_images(ForwardModel(ideal_layout, cal.pupil_functions(ideal_layout)),
                                                       images, position_model=LedArrayModel(nominal, PIXELS_PER_SINE))
    return problem, true_centres, spectrum


def recover(problem, iterations=40, **options):
    engine = SequentialMomentum(problem, MomentumOptions(max_iterations=iterations, tol=0, **options))
    spectrum, history = run_engine(engine)
    return spectrum, engine.calibration(), history


def test_global_led_array_shift_rotation_and_height_are_recovered():
    true = np.array([0.006, -0.004, 0.03, 0.04])  # shift (in heights), rotation 1.7°, height +4 %
    problem, true_centres, _ = led_case(true)
    assert np.abs(true_centres - problem.model.layout.centres_px).max() > 1.5  # the errors are large ...
    plain, _, _ = recover(problem)
    spectrum, calibration, _ = recover(problem, position_refinement="global")
    assert np.abs(calibration.centres_px - true_centres).max() < 0.2  # ... and found to a fraction of a pixel
    found = calibration.position_parameters
    assert found["rotation_rad"] == pytest.approx(true[2], abs=0.003)
    assert found["height"] == pytest.approx(true[3], abs=0.004)
    assert fit_report(problem, spectrum, calibration).all < 0.8 * fit_report(problem, plain).all


def test_position_models_leave_the_mean_position_to_the_object():
    nominal = led_nominal_px()
    for model, parameters in ((LedArrayModel(nominal, PIXELS_PER_SINE), [0.01, -0.02, 0.05, 0.1]),
                              (StageModel(nominal), [0.05, 0.1])):
        np.testing.assert_allclose(model.centres(model.initial), nominal, atol=1e-9)
        moved = model.centres(np.asarray(parameters, float))
        np.testing.assert_allclose(moved.mean(axis=0), nominal.mean(axis=0), atol=1e-9)
        assert np.abs(moved - nominal).max() > 1.0


def camera_array_case(coefficients, *, seed=0):
    """A 9 x 9 camera array (lattice at 61 % overlap) whose cameras each have their own aberration."""
    radius, size = 9.0, 128
    chart = resolution_chart(size, widths=(8, 6, 4, 3, 2, 1)).image
    layout = band_layout(square_scan(9, step_m(2 * radius, 0.61)).centres_yx_m, radius, hires_size=size)
    truth = ForwardModel(layout, cal.pupil_functions(layout, coefficients=coefficients, order=2))
    images = truth.sensor_intensity(fft.fft2c(chart.astype(np.complex64)).astype(np.complex64))
    images = add_gaussian_noise(images, 30.0, np.random.default_rng(seed))
    ideal = ForwardModel(layout, cal.pupil_functions(layout))
    problem = PhaseRetrievalProblem.from_sensor_images(ideal, images, pupil_index=np.arange(layout.n_images))
    return problem, chart ** 2


def test_per_camera_pupils_are_recovered():
    rng = np.random.default_rng(3)
    true = rng.normal(0.0, 0.1, (81, 3))  # defocus and astigmatism, 0.1 waves RMS, different in every camera
    perfect, truth = camera_array_case(None)
    reference = rmse(np.abs(fft.ifft2c(recover(perfect)[0])) ** 2, truth)
    problem, _ = camera_array_case(true)
    plain = rmse(np.abs(fft.ifft2c(recover(problem)[0])) ** 2, truth)
    spectrum, calibration, _ = recover(problem, iterations=60, pupil_recovery="per_camera", pupil_order=2)
    assert calibration.pupil.coefficients.shape == (81, 3)
    assert plain > 2.0 * reference  # the aberrations matter ...
    assert rmse(np.abs(fft.ifft2c(spectrum)) ** 2, truth) < 1.25 * reference  # ... and recovery removes them
    # Cameras that see much light have well-determined pupils; far dark-field ones matter (and show) little.
    energy = np.sum(problem.amplitudes.astype(np.float64) ** 2, axis=(1, 2))
    error = np.sqrt(np.sum(energy[:, None] * (calibration.pupil.coefficients - true) ** 2) / (3 * energy.sum()))
    assert error < 0.05


def test_per_camera_recovery_leaves_perfect_pupils_alone():
    problem, truth = camera_array_case(None)
    reference = rmse(np.abs(fft.ifft2c(recover(problem)[0])) ** 2, truth)
    spectrum, calibration, _ = recover(problem, pupil_recovery="per_camera", pupil_order=2)
    assert rmse(np.abs(fft.ifft2c(spectrum)) ** 2, truth) <= 1.05 * reference
    assert np.abs(calibration.pupil.coefficients).max() < 0.05


def aberrated_objective_case(coefficients, apodisation, seed):
    """The LED case seen through an aberrated (order-3 Zernike) objective apodised by ``1 − a r²``.

    Returns the problem built on the ideal disc pupil and the truth spectrum.
    """
    problem, _, spectrum = led_case()
    layout = problem.model.layout
    radius = np.hypot(*np.meshgrid(np.arange(layout.box_size) - layout.box_centres[0, 0],
                                   np.arange(layout.box_size) - layout.box_centres[0, 1], indexing="ij"))
    objective = cal.pupil_functions(layout, coefficients=coefficients, order=3)
    objective = objective * (1 - apodisation * (radius / LED_RADIUS) ** 2)[None].astype(np.float32)
    images = ForwardModel(layout, objective).sensor_intensity(spectrum)
    noisy = add_gaussian_noise(images, 30.0, np.random.default_rng(seed))
    return PhaseRetrievalProblem.from_sensor_images(ForwardModel(layout, cal.pupil_functions(layout)), noisy), spectrum


def test_full_pupil_map_takes_amplitude_and_phase_of_an_led_array_objective():
    # An apodised, aberrated objective: the full map recovers what Zernike phase modes cannot hold.
    aberrated, _ = aberrated_objective_case([0.1, 0.05, 0.0, 0.05, 0.0, 0.0, 0.0], 0.4, seed=1)
    residual = {}
    for name, options in (("plain", {}), ("zernike", dict(pupil_model="zernike", pupil_order=3)),
                          ("full", dict(pupil_model="full"))):
        shared = dict(pupil_recovery="shared", **options) if options else {}
        spectrum_found, calibration, _ = recover(aberrated, **shared)
        residual[name] = fit_report(aberrated, spectrum_found, calibration if options else None).all
    assert residual["full"] < residual["zernike"] < residual["plain"]
    assert residual["full"] < 0.5 * residual["plain"]
    np.testing.assert_allclose(calibration.pupil.coefficients[0, :2], [0.1, 0.05], atol=0.02)


def _subpixel_shift(image, reference, upsample=20):
    """Shift (rows, cols) that best aligns ``image`` to ``reference``: phase correlation refined by a DFT zoom."""
    cross = np.fft.fft2(reference) * np.conj(np.fft.fft2(image))
    cross /= np.maximum(np.abs(cross), 1e-12)
    n = image.shape[0]
    peak = np.array(np.unravel_index(np.argmax(np.abs(np.fft.ifft2(cross))), cross.shape), float)
    peak[peak > n // 2] -= n
    offsets = np.arange(-1.0, 1.0 + 1e-9, 1.0 / upsample)
    freqs = np.fft.fftfreq(n)
    best, where = -1.0, peak
    for dy in offsets:
        for dx in offsets:
            shift = peak + (dy, dx)
            value = abs(np.sum(cross * np.exp(2j * np.pi * (freqs[:, None] * shift[0] + freqs[None, :] * shift[1]))))
            if value > best:
                best, where = value, shift
    return where


def test_smooth_pinned_pupil_takes_the_aberration_and_leaves_the_object_in_place():
    # Zernike modes plus a smooth remainder. On an apodised, aberrated objective it must fit about as well as a
    # free per-pixel map, recover the object with the truth's error level and, with the tilt pinned or handed
    # to the object after each step, keep it registered to the truth (no drift). Defocus, astigmatism and
    # trefoil: none has a mean phase gradient, so "registered to the centre capture" and "where the truth is"
    # are the same place (coma's gradient would move the former). Kept in the pupil (the default), the tilt is
    # the data's to choose: the fit is as good, the object is not pinned.
    problem, spectrum = aberrated_objective_case([0.1, 0.05, 0.0, 0.0, 0.0, 0.05, 0.0], 0.3, seed=2)
    truth = np.abs(fft.ifft2c(spectrum)) ** 2
    error, shift = {}, {}
    smooth = dict(pupil_recovery="shared", pupil_model="smooth")
    for name, options in (("plain", {}), ("full", dict(pupil_recovery="shared", pupil_model="full")),
                          ("smooth", dict(smooth, pupil_tilt="pinned")), ("tilt kept", smooth),
                          ("tilt to object", dict(smooth, pupil_tilt="object"))):
        found, _, _ = recover(problem, iterations=60, **options)
        intensity = np.abs(fft.ifft2c(found)) ** 2
        error[name] = rmse(intensity, truth)
        shift[name] = np.hypot(*_subpixel_shift(intensity, truth))
    assert error["smooth"] < 0.6 * error["plain"]          # the aberration is taken out of the object ...
    assert error["smooth"] < 1.05 * error["full"]          # ... as well as a free per-pixel map does it,
    assert error["tilt kept"] < 1.05 * error["full"]       # wherever the tilt goes;
    assert error["tilt to object"] < 1.05 * error["full"]
    assert shift["smooth"] <= 0.15                         # and the object stays where the truth is
    assert shift["tilt to object"] <= 0.3


def test_the_fit_report_reads_alike_on_any_number_of_threads():
    from cca_cli.engines.illumination import capture_statistics

    problem, _, spectrum = led_case()   # 49 captures: two chunks of 32 and 17
    one = capture_statistics(problem.model, spectrum, problem.amplitudes, threads=1)
    for threads in (2, 3):
        many = capture_statistics(problem.model, spectrum, problem.amplitudes, threads=threads)
        for name in ("misfit", "power", "cross", "energy"):
            assert np.allclose(getattr(many, name), getattr(one, name), rtol=1e-6, atol=0)
    assert np.all(one.energy > 0) and np.all(one.misfit > 0)   # every capture's rows were filled
    assert fit_report(problem, spectrum, threads=2).all == pytest.approx(fit_report(problem, spectrum).all, rel=1e-6)


def test_the_fit_report_plans_a_workspace_only_for_threads_with_work_enough(monkeypatch):
    from cca_cli.engines import illumination
    from cca_cli.optics.forward import ForwardModel, chunk_slices

    problem, _, spectrum = led_case()
    one = illumination.capture_statistics(problem.model, spectrum, problem.amplitudes, threads=1)
    # chunks of 4 captures: 13 chunks, which 16 threads would each have taken one of
    monkeypatch.setattr(illumination, "chunk_slices", lambda k, chunk: chunk_slices(k, 4))
    planned = []
    made = ForwardModel.workspace
    monkeypatch.setattr(ForwardModel, "workspace", lambda self, *a, **k: planned.append(1) or made(self, *a, **k))
    many = illumination.capture_statistics(problem.model, spectrum, problem.amplitudes, threads=16)
    assert len(planned) == 13 // illumination.SLICES_PER_THREAD   # 3 workspaces, each thread 4 or 5 chunks
    for name in ("misfit", "power", "cross", "energy"):
        assert np.allclose(getattr(many, name), getattr(one, name), rtol=1e-6, atol=0)


def test_capture_statistics_read_a_recorded_mask_as_weights_of_one_and_zero():
    """The fit report passes a boolean mask of recorded pixels (a quarter of float32's memory): the
    figures are exactly those of float weights 1 and 0, and the masked pixels do not count."""
    from cca_cli.engines.illumination import capture_statistics

    problem, _, spectrum = led_case()
    recorded = np.ones_like(problem.amplitudes, dtype=bool)
    recorded[:, :3] = False   # a guard band along one edge
    as_bool = capture_statistics(problem.model, spectrum, problem.amplitudes, recorded, threads=2)
    as_float = capture_statistics(problem.model, spectrum, problem.amplitudes, recorded.astype(np.float32), threads=2)
    every = capture_statistics(problem.model, spectrum, problem.amplitudes, threads=2)
    for name in ("misfit", "power", "cross", "energy"):
        assert np.array_equal(getattr(as_bool, name), getattr(as_float, name))
        assert np.all(getattr(as_bool, name) < getattr(every, name))


@pytest.mark.parametrize("masked", [False, True])
def test_the_device_fit_statistics_are_the_cpu_s(masked, monkeypatch):
    """The GPU's fit report (here its arithmetic on numpy arrays) sums what the CPU's does, with or without a
    mask of recorded pixels, and the report built on it reads the same."""
    from cca_cli.engines.fit import device_statistics
    from cca_cli.engines.illumination import capture_statistics

    problem, _, spectrum = led_case()
    recorded = None
    if masked:
        recorded = np.ones_like(problem.amplitudes, dtype=bool)
        recorded[:, :3] = False
    cpu = capture_statistics(problem.model, spectrum, problem.amplitudes, recorded, threads=1)
    device = device_statistics(np, problem.model, spectrum, problem.amplitudes, recorded)
    for name in ("misfit", "power", "cross", "energy"):
        assert np.allclose(getattr(device, name), getattr(cpu, name), rtol=1e-5, atol=0)
    assert device.gradient is None and device.curvature is None
    from cca_cli.engines import fit
    from cca_cli.optics import backend

    taken = []
    monkeypatch.setattr(backend, "array_module", lambda device: taken.append(device) or np)
    monkeypatch.setattr(fit, "capture_statistics", None)   # the CPU's path is not taken
    on_device = fit_report(problem, spectrum, device="cuda", threads=2)
    monkeypatch.undo()
    assert taken == ["cuda"]
    assert on_device.all == pytest.approx(fit_report(problem, spectrum).all, rel=1e-5)
