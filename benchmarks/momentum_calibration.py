"""Sequential momentum engine vs alternating minimization; pupil and position calibration.

Usage::

    python benchmarks/momentum_calibration.py convergence   # iterations to a target RMSE, small headline
    python benchmarks/momentum_calibration.py calibration   # RMSE with/without position refinement
    python benchmarks/momentum_calibration.py speed         # s/iteration vs the raw-FFT floor, headline sizes
    python benchmarks/momentum_calibration.py pupil         # RMSE with/without shared-pupil recovery

The small headline is a 128-pixel resolution chart (bar widths 8 … 1 px) seen
through a 9 x 9 grid of apertures at 61% overlap whose centre image resolves
~8 px bars, with 30 dB Gaussian noise.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions
from cca_cli.engines.base import run_engine
from cca_cli.engines.momentum import MomentumOptions, SequentialMomentum
from cca_cli.engines.problem import PhaseRetrievalProblem
from cca_cli.metrics import rmse
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel, chunk_slices
from cca_cli.optics.noise import add_gaussian_noise
from cca_cli.optics.pupil import circular_pupils
from cca_cli.optics.zernike import zernike_phase
from cca_cli.sampling.grid import band_layout, square_scan
from cca_cli.sampling.overlap import step_m
from cca_cli.targets import resolution_chart


def small_case(*, size=128, grid=9, overlap=0.61, radius=9.0, snr_db=30.0, defocus=0.0, astigmatism=0.0,
               position_error=0.0, seed=0):
    """Captures of a chart under optional pupil/position errors, and the ideal model to reconstruct with."""
    chart = resolution_chart(size, widths=(8, 6, 4, 3, 2, 1)).image
    centres = square_scan(grid, step_m(2 * radius, overlap)).centres_yx_m
    layout = band_layout(centres, radius, hires_size=size)
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(-position_error, position_error, centres.shape) if position_error else 0.0
    true_centres = layout.box_centres + offsets
    pupils = circular_pupils(layout.box_size, true_centres, radius).astype(np.complex64)
    if defocus or astigmatism:
        pupils *= np.exp(1j * zernike_phase(layout.box_size, true_centres, radius, [defocus, astigmatism]))
    truth_model = ForwardModel(layout, pupils)
    images = truth_model.sensor_intensity(fft.fft2c(chart.astype(np.complex64)).astype(np.complex64))
    if snr_db is not None:
        images = add_gaussian_noise(images, snr_db, rng)
    ideal = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, radius))
    return PhaseRetrievalProblem.from_sensor_images(ideal, images), chart ** 2


def band_limited(problem, truth):
    """The truth seen through the synthetic aperture (what a perfect recovery can reach)."""
    support = problem.model.normal_diagonal() > 0
    return np.abs(fft.ifft2c(fft.fft2c(np.sqrt(truth).astype(np.complex64)) * support)) ** 2


def recovered_rmse(spectrum, truth):
    return rmse(np.abs(fft.ifft2c(spectrum)) ** 2, truth)


def trace(engine, truth):
    """Run an engine, recording the RMSE after each iteration."""
    curve = []
    while not engine.done():
        engine.update()
        curve.append(recovered_rmse(engine.spectrum(), truth))
    engine.close()
    return np.array(curve)


def convergence(iterations=200):
    problem, truth = small_case()
    truth = band_limited(problem, truth)
    print("RMSE against the band-limited truth")
    am = trace(AlternatingMinimization(problem, AltMinOptions(max_iterations=iterations, tol=0)), truth)
    mo = trace(SequentialMomentum(problem, MomentumOptions(max_iterations=iterations, tol=0)), truth)
    rp = trace(SequentialMomentum(problem, MomentumOptions(max_iterations=iterations, tol=0, eta=0)), truth)
    print(f"final RMSE: altmin {am[-1]:.4f}  momentum {mo[-1]:.4f}  rPIE (η=0) {rp[-1]:.4f}")
    for target in (0.08, 0.05, 1.05 * am[-1]):
        first = [int(np.argmax(c <= target)) + 1 if np.any(c <= target) else None for c in (am, mo, rp)]
        print(f"iterations to RMSE ≤ {target:.4f}: altmin {first[0]}  momentum {first[1]}  rPIE {first[2]}")


def calibration(iterations=40):
    """RMSE (against the chart) without and with position refinement."""
    error_free, truth = small_case()
    perturbed, _ = small_case(position_error=1.0)
    plain = MomentumOptions(max_iterations=iterations, tol=0)
    refine = MomentumOptions(max_iterations=iterations, tol=0, position_refinement=True)
    for label, problem, options in (("error-free, no refinement", error_free, plain),
                                    ("error-free, refinement", error_free, refine),
                                    ("positions ±1 px, no refinement", perturbed, plain),
                                    ("positions ±1 px, refinement", perturbed, refine)):
        start = time.perf_counter()
        engine = SequentialMomentum(problem, options)
        spectrum, _ = run_engine(engine)
        print(f"{label:34s} RMSE {recovered_rmse(spectrum, truth):.4f}  "
              f"mean |offset| {np.abs(engine.calibration().offsets).mean():.3f} px  "
              f"({time.perf_counter() - start:.1f} s)", flush=True)


def pupil(iterations=30):
    """RMSE (against the chart) without and with shared-pupil recovery, for several aberrations."""
    from cca_cli.engines import calibration as cal

    error_free, truth = small_case()
    seidel = (1 / (2 * np.sqrt(3)), 1 / (2 * np.sqrt(6)))  # 1 wave at the pupil edge, as RMS Zernike
    cases = (("perfect pupil", 0.0, 0.0), ("Seidel 1 wave defocus + astig", *seidel),
             ("0.4 + 0.4 waves RMS", 0.4, 0.4), ("1 + 1 waves RMS (aliased)", 1.0, 1.0))
    for label, defocus, astigmatism in cases:
        problem, _ = small_case(defocus=defocus, astigmatism=astigmatism)
        estimate = cal.estimate_quadratic_aberration(problem.model.layout, problem.amplitudes)
        results = []
        for mode in ("none", "shared"):
            start = time.perf_counter()
            engine = SequentialMomentum(problem, MomentumOptions(max_iterations=iterations, tol=0,
                                                                 pupil_recovery=mode))
            spectrum, _ = run_engine(engine)
            results.append((recovered_rmse(spectrum, truth), engine.calibration().coefficients,
                            time.perf_counter() - start))
        print(f"{label:31s} true ({defocus:.3f}, {astigmatism:.3f})  estimate {np.round(estimate, 3)}  "
              f"RMSE off {results[0][0]:.4f}  on {results[1][0]:.4f}  recovered {np.round(results[1][1], 3)}  "
              f"({results[1][2]:.1f} s)", flush=True)


def speed(repeats=3):
    from cca_cli.config.load import load_config
    from cca_cli.stages.simulate import simulation_geometry

    geometry, sensor = simulation_geometry(load_config())
    layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, sensor_size=sensor)
    model = ForwardModel.unaberrated(layout)
    rng = np.random.default_rng(0)
    amplitudes = rng.uniform(0.5, 1.5, (layout.n_images,) + model.field_shape).astype(np.float32)
    problem = PhaseRetrievalProblem(model=model, amplitudes=amplitudes)
    k, m = layout.n_images, layout.lowres_size

    def floor(chunk=16, threads=2):
        workspaces = [model.workspace(chunk, threads=1) for _ in range(threads)]
        from concurrent.futures import ThreadPoolExecutor

        slices = chunk_slices(k, chunk)
        with ThreadPoolExecutor(threads) as pool:
            def work(t):
                for _ in slices[t::threads]:
                    workspaces[t].fft.inverse()
                    workspaces[t].fft.forward()
            best = np.inf
            for _ in range(repeats):
                start = time.perf_counter()
                list(pool.map(work, range(threads)))
                best = min(best, time.perf_counter() - start)
        return best

    def per_iteration(engine):
        engine.update()
        best = np.inf
        for _ in range(repeats):
            start = time.perf_counter()
            engine.update()
            best = min(best, time.perf_counter() - start)
        engine.close()
        return best

    t_floor = floor()
    t_am = per_iteration(AlternatingMinimization(problem, AltMinOptions()))
    t_mo = per_iteration(SequentialMomentum(problem, MomentumOptions(batch=8)))
    t_mo16 = per_iteration(SequentialMomentum(problem, MomentumOptions(batch=16)))
    print(f"headline sizes: K={k}, m={m}, M={layout.hires_size}, {fft.cpu_count()} cores, backend {fft.backend_name()}")
    print(f"FFT floor (2 raw FFTs per capture) {t_floor * 1e3:.1f} ms")
    print(f"altmin          {t_am * 1e3:.1f} ms/iteration  ({t_am / t_floor:.2f} x floor)")
    print(f"momentum b=8    {t_mo * 1e3:.1f} ms/iteration  ({t_mo / t_floor:.2f} x floor)")
    print(f"momentum b=16   {t_mo16 * 1e3:.1f} ms/iteration  ({t_mo16 / t_floor:.2f} x floor)")


if __name__ == "__main__":
    studies = {"convergence": convergence, "calibration": calibration, "speed": speed, "pupil": pupil}
    studies[sys.argv[1] if len(sys.argv) > 1 else "convergence"]()
