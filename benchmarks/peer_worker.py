"""Run one reconstruction method on a benchmark data file in its own process.

Started by ``bench_peers.py`` once per method so that peak memory
(``VmHWM``) belongs to that method alone. Peers run in their own virtual
environments (``.venv-peers`` for PtyLab and fpm-py, ``.venv-fpmrs`` for
fpm-rs, Python ≥ 3.13), so this file imports only numpy at module level.

Usage::

    python peer_worker.py METHOD DATA OUT.npz --iterations N

METHOD is ``ours:<engine>`` (DATA: a ``.npy`` capture stack on the sensor or
band grid; the geometry is the headline preset's), ``ptylab:<engine>``,
``fpmrs:<algorithm>`` or ``fpmpy`` (DATA: the ``peers128.npz`` file written by
``bench_peers.py``).

OUT.npz holds ``seconds`` (cumulative wall time after each iteration, with
snapshot copies excluded), ``snap_iterations``, ``snaps`` (complex64 objects in
real space on the method's output grid, centred), ``peak_rss_bytes``,
``baseline_rss_bytes`` (after imports, before the data is loaded), ``fft_size``
and ``notes``.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np


def rss_peak_bytes() -> int:
    """Peak resident set size of this process so far (``VmHWM``).

    ``ru_maxrss`` is not used: Linux carries it over from the parent across
    fork and exec, so every worker would report at least the parent's peak.
    """
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def rss_now_bytes() -> int:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * resource.getpagesize()


def snapshot_iterations(n: int, cap: int = 60) -> set[int]:
    """Every iteration up to ``cap`` snapshots, log-spaced beyond; always the last."""
    if n <= cap:
        return set(range(1, n + 1))
    return set(np.unique(np.round(np.geomspace(1, n, cap)).astype(int)).tolist()) | {n}


class Recorder:
    """Per-iteration clock that excludes the time spent copying snapshots."""

    def __init__(self, iterations: int):
        self.wanted = snapshot_iterations(iterations)
        self.seconds: list[float] = []
        self.snap_iterations: list[int] = []
        self.snaps: list[np.ndarray] = []
        self._excluded = 0.0
        self._start = time.perf_counter()

    def restart(self) -> None:
        self._start, self._excluded = time.perf_counter(), 0.0

    def iteration_done(self, get_object) -> None:
        now = time.perf_counter()
        self.seconds.append(now - self._start - self._excluded)
        iteration = len(self.seconds)
        if iteration in self.wanted:
            self.snap_iterations.append(iteration)
            self.snaps.append(np.asarray(get_object(), dtype=np.complex64).copy())
        self._excluded += time.perf_counter() - now


def load_peer_data(data: Path, dtype) -> tuple[np.ndarray, dict]:
    """Captures (clipped at zero, as ``dtype``) and geometry of a ``peers128.npz`` file.

    The geometry holds ``width`` (field width, m), ``wavelength`` (m), ``radius``
    (pupil radius, spectrum px), ``hires`` (output grid) and ``centres`` ((K, 2)
    pupil centres ``[y, x]`` in spectrum px relative to DC).
    """
    with np.load(data) as d:
        images = np.clip(d["images"], 0, None).astype(dtype)
        geometry = dict(width=float(d["field_width_m"]), wavelength=float(d["wavelength_m"]),
                        radius=float(d["pupil_radius_px"]), hires=int(d["hires_size"]),
                        centres=np.asarray(d["centres_yx_px"], np.float64))
    return images, geometry


def centred_ifft2(spectrum: np.ndarray) -> np.ndarray:
    return np.fft.fftshift(np.fft.ifft2(np.fft.ifftshift(spectrum, axes=(-2, -1))), axes=(-2, -1))


def run_ours(engine_name: str, data: Path, iterations: int) -> dict:
    from cca_cli.config.load import load_config
    from cca_cli.engines.problem import PhaseRetrievalProblem
    from cca_cli.engines.registry import get_engine
    from cca_cli.optics import fft
    from cca_cli.library.recovery import build_model
    from cca_cli.stages.simulate import simulation_geometry

    geometry, _ = simulation_geometry(load_config())
    entry = get_engine(engine_name)
    baseline = rss_now_bytes()
    images = np.load(data)
    input_size = images.shape[-1]
    model = build_model(geometry, input_size)
    problem = PhaseRetrievalProblem.from_sensor_images(model, images)
    del images
    names = entry.option_names()
    options = entry.options(**{k: v for k, v in (("max_iterations", 10**6), ("tol", 0.0)) if k in names})
    engine = entry.engine_class()(problem, options)
    recorder = Recorder(iterations)
    try:
        for _ in range(iterations):
            engine.update()
            recorder.iteration_done(lambda: fft.ifft2c(engine.spectrum()))
    finally:
        engine.close()
    notes = (f"our {engine_name} engine, {model.n_images} captures on a {model.layout.lowres_size}² grid "
             f"from {input_size}² input, output {model.layout.hires_size}², "
             f"FFT backend {fft.backend_name()}")
    return dict(recorder=recorder, baseline=baseline, fft_size=model.layout.lowres_size, notes=notes)


def run_ptylab(engine_name: str, data: Path, iterations: int, workdir: Path) -> dict:
    import h5py
    import PtyLab
    from PtyLab import Engines
    from PtyLab.Monitor.Monitor import DummyMonitor

    baseline = rss_now_bytes()
    images, g = load_peer_data(data, np.float32)
    k, n = images.shape[0], images.shape[-1]
    width, wavelength, radius, hires = g["width"], g["wavelength"], g["radius"], g["hires"]
    # PtyLab places capture i's pupil at No//2 - round(W sinθ_i / λ) (rows, columns) for dxd/magnification = W/n;
    # with zled = 1 m the encoder is the LED offset that gives sinθ_i = -c_i λ / W.
    sin_theta = -g["centres"] * wavelength / width
    encoder = sin_theta / np.sqrt(1.0 - np.sum(sin_theta ** 2, axis=1, keepdims=True))
    path = workdir / "ptylab_input.hdf5"
    with h5py.File(path, "w") as handle:
        handle["ptychogram"] = images
        handle["wavelength"] = wavelength
        handle["encoder"] = encoder
        handle["dxd"] = width / n
        handle["zled"] = 1.0
        handle["magnification"] = 1.0
        handle["NA"] = radius * wavelength / width
    del images

    data_obj = PtyLab.ExperimentalData(str(path), "FPM")
    params = PtyLab.Params()
    reconstruction = PtyLab.Reconstruction(data_obj, params)
    reconstruction.No = hires
    reconstruction.initializeObjectProbe()
    params.gpuSwitch = False
    params.positionOrder = "NA"
    params.probeBoundary = True
    recorder = Recorder(iterations)

    def get_object():
        spectrum = np.asarray(reconstruction.object)
        return centred_ifft2(spectrum.reshape(-1, *spectrum.shape[-2:])[0])

    class SnapshotMonitor(DummyMonitor):
        figureUpdateFrequency = 1
        verboseLevel = "low"

        started = False

        def update(self, frame):
            if not self.started:  # the first call shows the initial guesses, before iteration 1
                self.started = True
                recorder.restart()
                return
            recorder.iteration_done(get_object)

    engine = getattr(Engines, engine_name)(reconstruction, data_obj, params, SnapshotMonitor())
    engine.numIterations = iterations
    engine.betaProbe = 0.0  # the pupil is known exactly, as it is for our engines
    recorder.restart()
    engine.reconstruct()
    notes = (f"PtyLab {engine_name} (FPM mode, known circular pupil: betaProbe = 0, positionOrder NA), "
             f"{k} captures at {n}², object {hires}²; spectrum positions rounded to whole pixels by PtyLab")
    return dict(recorder=recorder, baseline=baseline, fft_size=n, notes=notes)


def run_fpmrs(algorithm: str, data: Path, iterations: int, workdir: Path) -> dict:
    import fpm_rs

    baseline = rss_now_bytes()
    images, g = load_peer_data(data, np.float64)
    k, n = images.shape[0], images.shape[-1]
    width, wavelength, radius, hires, centres = g["width"], g["wavelength"], g["radius"], g["hires"], g["centres"]
    optics = fpm_rs.Optics(wavelength, radius * wavelength / width, 1.0, width / n)
    k_vectors = 2 * np.pi * centres[:, ::-1] / width  # (kx, ky) in rad/m
    model = fpm_rs.compile_model(optics, fpm_rs.KVectorList(k_vectors), (n, n), (hires, hires))
    problem = fpm_rs.ReconstructionProblem(images, model)
    del images
    make = {"ap": fpm_rs.AlternatingProjection, "fpie": fpm_rs.Fpie}[algorithm]

    # fpm-rs runs a whole schedule in one call; per-iteration objects come from its
    # checkpoints, so the clock comes from a separate run without callbacks.
    clean = make(iterations=iterations).run(problem)
    stamps = np.array([t for _, _, t in clean.history], np.float64)
    peak_clean = rss_peak_bytes()
    checkpoints = workdir / f"fpmrs_{algorithm}_checkpoints"
    checkpoints.mkdir(parents=True, exist_ok=True)
    make(iterations=iterations).run(problem, callbacks=[fpm_rs.CheckpointEvery(1, str(checkpoints))])
    recorder = Recorder(iterations)
    for i in range(1, iterations + 1):
        recorder.seconds.append(float(stamps[i - 1]))
        if i in recorder.wanted:
            files = sorted(checkpoints.glob(f"checkpoint_{i:05d}*"))
            checkpoint = fpm_rs.ReconstructionCheckpoint.load(str(files[0]))
            state = make(iterations=i).run(problem, resume_from=checkpoint)
            recorder.snap_iterations.append(i)
            recorder.snaps.append(np.asarray(state.object, np.complex64))
            files[0].unlink()
    notes = (f"fpm-rs {fpm_rs.__version__} {make.__name__} (defaults), {k} captures at {n}², object {hires}²; "
             "time per iteration from a run without callbacks")
    return dict(recorder=recorder, baseline=baseline, fft_size=n, notes=notes, peak=peak_clean)


def run_fpmpy(data: Path, iterations: int) -> dict:
    import torch
    import fpm_py
    from fpm_py.core import forward
    from fpm_py.core.structs import AcquisitionSettings, ImageCapture, ImageSeries

    baseline = rss_now_bytes()
    images, g = load_peer_data(data, np.float32)
    k, n = images.shape[0], images.shape[-1]
    radius, hires, centres = g["radius"], g["hires"], g["centres"]
    # fpm-py centres capture i's crop at (H//2, W//2) + round(k_i / du): with du = 1, k_i is the centre in pixels.
    captures = [ImageCapture(image=torch.from_numpy(images[i]), k_vector=torch.tensor(centres[i], dtype=torch.float32))
                for i in range(k)]
    series = ImageSeries(captures=captures, settings=AcquisitionSettings(du=1.0, pixel_size=1.0, wavelength=1.0))
    yy, xx = np.mgrid[:n, :n] - n // 2
    pupil = torch.from_numpy((np.hypot(yy, xx) <= radius).astype(np.complex64))

    recorder = Recorder(iterations)
    original = forward._single_capture_update
    calls = [0]
    state = {}

    def counting_update(obj_est, *args, **kwargs):
        out = original(obj_est, *args, **kwargs)
        calls[0] += 1
        state["obj"] = out[0]
        if calls[0] % k == 0:
            recorder.iteration_done(lambda: forward.ift(state["obj"]).numpy())
        return out

    forward._single_capture_update = counting_update
    import contextlib
    import io

    recorder.restart()
    with contextlib.redirect_stdout(io.StringIO()):
        fpm_py.reconstruct(series, output_image_size=(hires, hires), pupil_0=pupil, max_iters=iterations)
    notes = (f"fpm-py 2.0.1 reconstruct (its quasi-Newton object+pupil update), {k} captures at {n}², "
             f"object {hires}², pupil_0 = the true disc (radius {radius:.1f} px); torch {torch.__version__} CPU")
    return dict(recorder=recorder, baseline=baseline, fft_size=n, notes=notes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("method")
    parser.add_argument("data", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--iterations", type=int, default=30)
    args = parser.parse_args()
    family, _, variant = args.method.partition(":")
    workdir = args.out.parent
    if family == "ours":
        result = run_ours(variant, args.data, args.iterations)
    elif family == "ptylab":
        result = run_ptylab(variant, args.data, args.iterations, workdir)
    elif family == "fpmrs":
        result = run_fpmrs(variant, args.data, args.iterations, workdir)
    elif family == "fpmpy":
        result = run_fpmpy(args.data, args.iterations)
    else:
        sys.exit(f"unknown method {args.method!r}")
    recorder = result["recorder"]
    np.savez(args.out, seconds=np.array(recorder.seconds), snap_iterations=np.array(recorder.snap_iterations),
             snaps=np.stack(recorder.snaps), peak_rss_bytes=result.get("peak", rss_peak_bytes()),
             baseline_rss_bytes=result["baseline"], fft_size=result["fft_size"], notes=result["notes"],
             python=sys.version.split()[0])


if __name__ == "__main__":
    main()
