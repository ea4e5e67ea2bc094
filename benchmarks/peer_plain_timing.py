"""Plain runs of the peers, outside the benchmark harness, to check their time per iteration.

Runs each peer the way its own documentation shows (no snapshot monitor, no
checkpoints, no harness code) on a data file written by ``bench_real.py`` and
prints the seconds per iteration: PtyLab's own progress bar rate and the wall
clock, fpm-rs's own ``runtime.elapsed_seconds``.

Usage (with the peer's own interpreter)::

    .venv-peers/bin/python benchmarks/peer_plain_timing.py ptylab benchmarks/results/real_work/usaf_aidukas32/peer_data.npz 50
    .venv-fpmrs/bin/python benchmarks/peer_plain_timing.py fpmrs benchmarks/results/real_work/usaf_aidukas32/peer_data.npz 50
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def ptylab(d, iterations: int) -> None:
    import h5py
    import PtyLab
    from PtyLab import Engines
    from PtyLab.Monitor.Monitor import DummyMonitor

    images = d["images"].astype(np.float32)
    n, width, lam = images.shape[-1], float(d["field_width"]), float(d["wavelength"])
    s = -d["windows"] * lam / width
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "data.hdf5"
        with h5py.File(path, "w") as f:
            f["ptychogram"], f["wavelength"], f["dxd"], f["zled"], f["magnification"] = images, lam, width / n, 1.0, 1.0
            f["encoder"] = s / np.sqrt(1 - (s ** 2).sum(1, keepdims=True))
            f["NA"] = float(d["radius"]) * lam / width
        data = PtyLab.ExperimentalData(str(path), "FPM")
        params = PtyLab.Params()
        params.gpuSwitch = False
        params.positionOrder = "NA"
        params.probeBoundary = True
        params.weigh_probe_updates_by_intensity = True
        rec = PtyLab.Reconstruction(data, params)
        rec.No = int(d["hires"])
        rec.initializeObjectProbe()
        engine = Engines.mPIE(rec, data, params, DummyMonitor())
        engine.numIterations = iterations
        start = time.perf_counter()
        engine.reconstruct()
        wall = time.perf_counter() - start
    rate = engine.pbar.format_dict
    own = rate["elapsed"] / max(rate["n"], 1)
    print(f"PtyLab mPIE + pupil, {images.shape[0]} frames of {n}², object {int(d['hires'])}²: "
          f"{wall / iterations:.4f} s/iteration (wall), {own:.4f} s/iteration (PtyLab's progress bar)")


def fpmrs(d, iterations: int) -> None:
    import fpm_rs

    images = d["images"].astype(np.float64)
    n, width, lam = images.shape[-1], float(d["field_width"]), float(d["wavelength"])
    optics = fpm_rs.Optics(lam, float(d["radius"]) * lam / width, 1.0, width / n)
    model = fpm_rs.compile_model(optics, fpm_rs.KVectorList(2 * np.pi * d["windows"][:, ::-1] / width), (n, n),
                                 (int(d["hires"]),) * 2)
    problem = fpm_rs.ReconstructionProblem(images, model)
    start = time.perf_counter()
    result = fpm_rs.Epry(iterations=iterations).run(problem)
    wall = time.perf_counter() - start
    print(f"fpm-rs Epry, {images.shape[0]} frames of {n}², object {int(d['hires'])}²: "
          f"{wall / iterations:.4f} s/iteration (wall), "
          f"{result.runtime.elapsed_seconds / iterations:.4f} s/iteration (fpm-rs runtime)")


if __name__ == "__main__":
    family, data_path, its = sys.argv[1], sys.argv[2], int(sys.argv[3])
    with np.load(data_path) as handle:
        values = {k: handle[k] for k in handle.files}
    {"ptylab": ptylab, "fpmrs": fpmrs}[family](values, its)
