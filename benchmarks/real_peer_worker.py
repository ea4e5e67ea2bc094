"""Run a peer FPM code on real LED-array data in its own process (own virtual environment).

Started by ``bench_real.py``. Imports numpy (and ``real_model``, numpy only)
at module level; the peer is imported inside its functions, so this file runs
under ``.venv-peers`` (PtyLab, Python 3.11) and ``.venv-fpmrs`` (fpm-rs,
Python ≥ 3.13).

Usage::

    python real_peer_worker.py check FAMILY DATA.npz TEST.npz OUT.npz
    python real_peer_worker.py run METHOD DATA.npz OUT.npz --iterations N [--options JSON]

DATA.npz (written by ``bench_real.py``) holds ``images`` (K, n, n) float32
intensities after the common preprocessing, ``windows`` (K, 2) int — the
spectrum pixel [y, x] relative to DC at the centre of each capture's window in
the common convention (:mod:`real_model`) —, ``radius`` (pupil radius, spectrum
px), ``wavelength``, ``field_width`` (m), ``hires`` (the peer's object grid M).

``check`` evaluates the peer's own forward operator on TEST.npz's
``spectrum`` (M, M) and ``pupil`` (n, n), given in the common convention, and
writes ``intensity`` (K, n, n); also ``default_pupil`` (the peer's own initial
pupil, common convention) and ``default_intensity`` (its forward with it).

``run`` reconstructs and writes ``seconds`` (cumulative, snapshot copies
excluded, from ``clock_start_epoch``: the wall-clock time, ``time.time()``, at which
the first iteration starts, so a caller can add the start-up before it), ``snap_iterations``, ``snap_spectra`` (S, M, M), ``snap_pupils``
(S, n, n) in the common convention, ``own_check`` (the peer's own figure for
its final state: PtyLab's predicted intensities, fpm-rs's loss), ``notes``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_model import fft2c, ifft2c  # noqa: E402


def snapshot_iterations(n: int, cap: int = 40) -> set[int]:
    """Up to ``cap`` log-spaced iterations, always the first and the last."""
    if n <= cap:
        return set(range(1, n + 1))
    return set(np.unique(np.round(np.geomspace(1, n, cap)).astype(int)).tolist()) | {n}


class Recorder:
    """Per-iteration clock that excludes the time spent copying snapshots."""

    def __init__(self, iterations: int):
        self.wanted = snapshot_iterations(iterations)
        self.seconds: list[float] = []
        self.snaps: list[tuple[int, np.ndarray, np.ndarray]] = []
        self._excluded = 0.0
        self._start = time.perf_counter()
        self.start_epoch = time.time()

    def restart(self) -> None:
        self._start, self._excluded = time.perf_counter(), 0.0
        self.start_epoch = time.time()

    def iteration_done(self, get_state) -> None:
        now = time.perf_counter()
        self.seconds.append(now - self._start - self._excluded)
        if len(self.seconds) in self.wanted:
            spectrum, pupil = get_state()
            self.snaps.append((len(self.seconds), np.array(spectrum, np.complex64), np.array(pupil, np.complex64)))
        self._excluded += time.perf_counter() - now


def load_data(path: Path) -> dict:
    with np.load(path) as d:
        return {k: d[k] for k in d.files}


# ----------------------------------------------------------------------------- PtyLab
#
# PtyLab's FPM mode keeps the object *spectrum* (No x No) and the pupil ("probe", Np x Np = n x n)
# and models frame j as |fft2c(O[patch_j] · P)|², patch_j's top-left corner at
# round(−(W/λ)·sinθ_j) + No//2 − Np//2 (W = Np·dxd/magnification). Since
# |fft2c(X)|² = |ifft2c(conj X)|², that is the common model with S = conj(O), P_common = conj(P)
# and the window centre c_j = round(−(W/λ)·sinθ_j): we give it sinθ_j = −c_j λ / W.

def _ptylab_setup(data: dict, workdir: Path):
    import h5py
    import PtyLab

    images = np.asarray(data["images"], np.float32)
    k, n = images.shape[0], images.shape[-1]
    width, wavelength = float(data["field_width"]), float(data["wavelength"])
    sin_theta = -np.asarray(data["windows"], np.float64) * wavelength / width
    encoder = sin_theta / np.sqrt(1.0 - np.sum(sin_theta ** 2, axis=1, keepdims=True))   # zled = 1 m
    path = workdir / "ptylab_input.hdf5"
    with h5py.File(path, "w") as handle:
        handle["ptychogram"] = images
        handle["wavelength"] = wavelength
        handle["encoder"] = encoder
        handle["dxd"] = width / n
        handle["zled"] = 1.0
        handle["magnification"] = 1.0
        handle["NA"] = float(data["radius"]) * wavelength / width
    experimental = PtyLab.ExperimentalData(str(path), "FPM")
    params = PtyLab.Params()
    params.gpuSwitch = False
    reconstruction = PtyLab.Reconstruction(experimental, params)
    reconstruction.No = int(data["hires"])
    reconstruction.initializeObjectProbe()
    positions = np.asarray(reconstruction.positions) - reconstruction.No // 2 + n // 2
    if not np.array_equal(positions, np.asarray(data["windows"])):
        raise RuntimeError("PtyLab places the windows elsewhere than requested: "
                           f"max offset {np.abs(positions - data['windows']).max()} px")
    return experimental, params, reconstruction


def _ptylab_state(reconstruction) -> tuple[np.ndarray, np.ndarray]:
    obj = np.asarray(reconstruction.object)
    probe = np.asarray(reconstruction.probe)
    return np.conj(obj.reshape(-1, *obj.shape[-2:])[0]), np.conj(probe.reshape(-1, *probe.shape[-2:])[0])


def _ptylab_set_state(reconstruction, spectrum: np.ndarray, pupil: np.ndarray) -> None:
    obj = np.asarray(reconstruction.object)
    probe = np.asarray(reconstruction.probe)
    reconstruction.object = np.broadcast_to(np.conj(spectrum).astype(obj.dtype), obj.shape).copy()
    reconstruction.probe = np.broadcast_to(np.conj(pupil).astype(probe.dtype), probe.shape).copy()


def _ptylab_predict(engine, reconstruction, k: int) -> np.ndarray:
    """PtyLab's own predicted intensities: its patch extraction and its object→detector operator."""
    n = reconstruction.Np
    out = np.empty((k, n, n), np.float64)
    for j in range(k):
        row, col = reconstruction.positions[j]
        patch = reconstruction.object[..., row:row + n, col:col + n]
        esw = patch * reconstruction.probe
        reconstruction.esw = esw
        _, detector = engine_operators().object2detector(esw, engine.params, reconstruction)
        out[j] = np.sum(np.abs(detector) ** 2, axis=(0, 1, 2))[-1]
    return out


def engine_operators():
    from PtyLab.Operators import Operators

    return Operators


def _ptylab_engine(name, reconstruction, experimental, params, monitor):
    from PtyLab import Engines

    return getattr(Engines, name)(reconstruction, experimental, params, monitor)


def ptylab_check(data: dict, test: dict, workdir: Path) -> dict:
    from PtyLab.Monitor.Monitor import DummyMonitor

    experimental, params, reconstruction = _ptylab_setup(data, workdir)
    engine = _ptylab_engine("mPIE", reconstruction, experimental, params, DummyMonitor())
    k = len(data["windows"])
    default_pupil = _ptylab_state(reconstruction)[1].copy()
    _ptylab_set_state(reconstruction, test["spectrum"], default_pupil)
    default_intensity = _ptylab_predict(engine, reconstruction, k)
    _ptylab_set_state(reconstruction, test["spectrum"], test["pupil"])
    return {"intensity": _ptylab_predict(engine, reconstruction, k), "default_pupil": default_pupil,
            "default_intensity": default_intensity}


def ptylab_run(engine_name: str, data: dict, iterations: int, options: dict, workdir: Path) -> dict:
    import PtyLab
    from PtyLab.Monitor.Monitor import DummyMonitor

    np.random.seed(int(options.pop("seed", 0)))  # mPIE's momentum steps are random
    experimental, params, reconstruction = _ptylab_setup(data, workdir)
    k = len(data["windows"])
    pupil_init = options.pop("pupil_init", "circle")
    if pupil_init == "circle":  # the same pupil as every other method starts from
        n = reconstruction.Np
        yy, xx = np.mgrid[:n, :n] - n // 2
        _ptylab_set_state(reconstruction, _ptylab_state(reconstruction)[0],
                          (np.hypot(yy, xx) <= float(data["radius"])).astype(np.complex64))
    params.positionOrder = options.pop("positionOrder", "NA")
    params.probeBoundary = options.pop("probeBoundary", True)
    engine_fields = {key: options.pop(key) for key in list(options) if key in (
        "betaProbe", "betaObject", "alphaProbe", "alphaObject", "feedbackM", "frictionM")}
    for key, value in options.items():  # the rest are PtyLab Params
        if not hasattr(params, key):
            raise ValueError(f"PtyLab Params has no attribute {key!r}")
        setattr(params, key, value)
    recorder = Recorder(iterations)

    class SnapshotMonitor(DummyMonitor):
        figureUpdateFrequency = 1
        started = False

        def update(self, frame):
            if not self.started:  # the first call shows the initial guesses, before iteration 1
                self.started = True
                recorder.restart()
                return
            recorder.iteration_done(lambda: _ptylab_state(reconstruction))

    engine = _ptylab_engine(engine_name, reconstruction, experimental, params, SnapshotMonitor())
    engine.numIterations = iterations
    for key, value in engine_fields.items():
        setattr(engine, key, value)
    recorder.restart()
    engine.reconstruct()
    if len(recorder.seconds) != iterations:
        raise RuntimeError(f"PtyLab reported {len(recorder.seconds)} iterations, expected {iterations}")
    own = _ptylab_predict(engine, reconstruction, k)
    notes = (f"PtyLab {engine_name}, {k} frames at {reconstruction.Np}², object spectrum {reconstruction.No}²; "
             f"betaProbe {engine.betaProbe}, betaObject {engine.betaObject}, alphaProbe {engine.alphaProbe}, "
             f"alphaObject {engine.alphaObject}, probeBoundary {params.probeBoundary}, positionOrder "
             f"{params.positionOrder}, weigh_probe_updates_by_intensity {params.weigh_probe_updates_by_intensity}, "
             f"initial pupil {pupil_init}; PtyLab {getattr(PtyLab, '__version__', '0.3.7')}")
    return {"recorder": recorder, "own_intensity": own, "notes": notes}


# ----------------------------------------------------------------------------- fpm-rs
#
# fpm-rs models frame j as |ifft2c(S[window_j] · P)|² with S = fft2c(object), the window centred at
# +k_j·W/(2π) (k_j in rad/m, sub-pixel positions handled by the peer). We give it the whole-pixel
# centres: k_j = 2π c_j / W (x, y order), so its windows are exactly ours.

def _fpmrs_model(data: dict):
    import fpm_rs

    images = np.asarray(data["images"], np.float64)
    n, hires = images.shape[-1], int(data["hires"])
    width, wavelength = float(data["field_width"]), float(data["wavelength"])
    optics = fpm_rs.Optics(wavelength, float(data["radius"]) * wavelength / width, 1.0, width / n)
    k_vectors = 2 * np.pi * np.asarray(data["windows"], np.float64)[:, ::-1] / width
    model = fpm_rs.compile_model(optics, fpm_rs.KVectorList(k_vectors), (n, n), (hires, hires))
    return images, model


def fpmrs_check(data: dict, test: dict, workdir: Path) -> dict:
    import fpm_rs

    _, model = _fpmrs_model(data)
    default_pupil = np.asarray(model.pupil)
    if not np.allclose(np.asarray(test["pupil"]), default_pupil):
        # fpm-rs compiles its pupil from the optics; it cannot be given one, so the check uses its own disc
        pass
    obj = ifft2c(np.asarray(test["spectrum"], np.complex128))
    intensity = np.asarray(fpm_rs.simulate(model, obj).measurements.array)
    return {"intensity": intensity, "default_pupil": default_pupil, "default_intensity": intensity,
            "pupil_used": default_pupil}


def fpmrs_run(algorithm: str, data: dict, iterations: int, options: dict, workdir: Path) -> dict:
    import fpm_rs

    images, model = _fpmrs_model(data)
    problem = fpm_rs.ReconstructionProblem(images, model)
    make = {"epry": fpm_rs.Epry, "ap": fpm_rs.AlternatingProjection, "fpie": fpm_rs.Fpie}[algorithm]

    # fpm-rs runs a whole schedule in one call: the clock comes from a run without callbacks,
    # per-iteration states from its checkpoints, resumed for one step each.
    start_epoch = time.time()
    clean = make(iterations=iterations, **options).run(problem)
    stamps = np.array([t for _, _, t in clean.history], np.float64)
    checkpoints = workdir / f"fpmrs_{algorithm}_checkpoints"
    checkpoints.mkdir(parents=True, exist_ok=True)
    for old in checkpoints.glob("*"):
        old.unlink()
    recorder = Recorder(iterations)
    wanted = sorted(recorder.wanted)
    make(iterations=iterations, **options).run(problem, callbacks=[fpm_rs.CheckpointEvery(1, str(checkpoints))])
    recorder.seconds = [float(t) for t in stamps]
    recorder.start_epoch = start_epoch
    zero = dict(options, object_step=1e-12)
    if algorithm == "epry":
        zero["pupil_step"] = 1e-12
    own = None
    for i in wanted:
        files = sorted(checkpoints.glob(f"checkpoint_{i:05d}*"))
        checkpoint = fpm_rs.ReconstructionCheckpoint.load(str(files[0]))
        # one more pass with vanishing steps reads the state back (and fpm-rs's own loss of it)
        state = make(iterations=i + 1, **zero).run(problem, resume_from=checkpoint)
        recorder.snaps.append((i, fft2c(np.asarray(state.object, np.complex128)).astype(np.complex64),
                               np.asarray(state.recovered_pupil, np.complex64)))
        own = float(state.history[-1][1])
    for old in checkpoints.glob("*"):
        old.unlink()
    notes = (f"fpm-rs {fpm_rs.__version__} {make.__name__}({', '.join(f'{k}={v}' for k, v in options.items())}), "
             f"{images.shape[0]} frames at {images.shape[-1]}², object {int(data['hires'])}², whole-pixel windows; "
             f"s/iteration from a run without callbacks")
    return {"recorder": recorder, "own_loss": own, "notes": notes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    check = sub.add_parser("check")
    check.add_argument("family", choices=["ptylab", "fpmrs"])
    check.add_argument("data", type=Path)
    check.add_argument("test", type=Path)
    check.add_argument("out", type=Path)
    run = sub.add_parser("run")
    run.add_argument("method")
    run.add_argument("data", type=Path)
    run.add_argument("out", type=Path)
    run.add_argument("--iterations", type=int, default=50)
    run.add_argument("--options", default="{}")
    args = parser.parse_args()
    workdir = args.out.parent
    data = load_data(args.data)
    if args.mode == "check":
        test = load_data(args.test)
        result = (ptylab_check if args.family == "ptylab" else fpmrs_check)(data, test, workdir)
        np.savez(args.out, **result)
        return
    family, _, variant = args.method.partition(":")
    options = json.loads(args.options)
    if family == "ptylab":
        result = ptylab_run(variant, data, args.iterations, options, workdir)
    elif family == "fpmrs":
        result = fpmrs_run(variant, data, args.iterations, options, workdir)
    else:
        sys.exit(f"unknown method {args.method!r}")
    rec = result["recorder"]
    extra = {}
    if "own_intensity" in result:
        extra["own_intensity"] = result["own_intensity"]
    if result.get("own_loss") is not None:
        extra["own_loss"] = result["own_loss"]
    np.savez(args.out, seconds=np.array(rec.seconds), snap_iterations=np.array([s[0] for s in rec.snaps]),
             snap_spectra=np.stack([s[1] for s in rec.snaps]), snap_pupils=np.stack([s[2] for s in rec.snaps]),
             notes=result["notes"], python=sys.version.split()[0], clock_start_epoch=rec.start_epoch, **extra)


if __name__ == "__main__":
    main()
