"""Running every method of the real-data benchmark and converting its result to the common representation.

* peers run in their own virtual environments through ``real_peer_worker.py``;
* cca engines run through the command line (``cca reconstruct`` on the
  ``cca ingest`` output) with a config holding only the engine name and any
  options given to the benchmark, so each engine runs with its defaults; the
  recon.h5 it writes is read back, with the ``/calibration`` group when the
  installed cca writes one.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import yaml

from real_data import ROOT, Prepared, run_cca, tool_environment
from real_model import Recovery, circle_pupils, embed_centred

HERE = Path(__file__).resolve().parent
PEER_PYTHON = {"ptylab": ROOT / ".venv-peers/bin/python", "fpmrs": ROOT / ".venv-fpmrs/bin/python"}
INSTALL_HINT = {
    "ptylab": "~/.pyenv/versions/3.11.7/bin/python -m venv .venv-peers && .venv-peers/bin/pip install ptylab h5py",
    "fpmrs": "~/.pyenv/versions/3.13.0/bin/python -m venv .venv-fpmrs && .venv-fpmrs/bin/pip install fpm-rs numpy",
}


def peer_available(family: str) -> tuple[bool, str]:
    python = PEER_PYTHON[family]
    if not python.exists():
        return False, f"{python} missing; install with: {INSTALL_HINT[family]}"
    module = {"ptylab": "PtyLab", "fpmrs": "fpm_rs"}[family]
    probe = subprocess.run([str(python), "-c", f"import {module}"], capture_output=True, text=True)
    if probe.returncode != 0:
        return False, f"`import {module}` fails in {python}; {INSTALL_HINT[family]}"
    return True, str(python)


def _worker(python: str, args: list[str], timeout: float, log: Path) -> None:
    proc = subprocess.run([python, str(HERE / "real_peer_worker.py"), *args], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT, env=tool_environment(PYTHONPATH=str(HERE)))
    log.write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        lines = [line for line in (proc.stderr or proc.stdout).splitlines() if line.strip()]
        raise RuntimeError(lines[-1] if lines else f"exit {proc.returncode}")


# ----------------------------------------------------------------------------- forward-model check

def cca_integer_model(data: Prepared, hires: int):
    """cca's forward model on the data's geometry with whole-pixel pupil centres, on an M = ``hires`` grid."""
    from cca_cli.io.geometry import read_geometry
    from cca_cli.optics.forward import ForwardModel
    from cca_cli.optics.pupil import circular_pupils
    from cca_cli.library.recovery import build_model

    with h5py.File(data.raw_h5, "r") as handle:
        geometry = read_geometry(handle)
    geometry = replace(geometry, spectrum_centres_yx_px=np.rint(geometry.spectrum_centres_yx_px))
    layout = build_model(geometry, data.intensity.shape[-1], hires_size=hires).layout
    # The peers get a binary disc: compare operators with the same pupil (cca's own has an anti-aliased edge).
    return ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px,
                                                edge_px=0))


def relative_error(candidate: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """``‖a·x − y‖ / ‖y‖`` with the least-squares scale a (peers normalise FFTs their own way), and a."""
    x = np.asarray(candidate, np.float64).ravel()
    y = np.asarray(reference, np.float64).ravel()
    a = float(x @ y / (x @ x))
    return float(np.linalg.norm(a * x - y) / np.linalg.norm(y)), a


def forward_check(data: Prepared, families: list[str], workdir: Path, timeout: float) -> dict:
    """Each peer's forward operator against cca's on the data's geometry (same spectrum and pupil, whole pixels).

    The test spectrum is complex Gaussian noise over the whole M x M grid, so every
    spectrum pixel any window reads is exercised; the pupil is the disc of radius R.
    """
    workdir = workdir.resolve()
    m, n = data.spec.peer_hires, data.intensity.shape[-1]
    rng = np.random.default_rng(7)
    spectrum = (rng.standard_normal((m, m)) + 1j * rng.standard_normal((m, m))).astype(np.complex64)
    pupil = circle_pupils(n, [[0.0, 0.0]], data.radius)[0]
    model = cca_integer_model(data, m)
    reference = model.sensor_intensity(spectrum)
    if reference.shape[-1] != n:  # oversampled frames: cca models them on the intensity band's grid (exact)
        from cca_cli.optics.fft import fourier_resample

        reference = fourier_resample(reference, n)
    common = Recovery(spectrum, pupil[None], np.zeros(len(data.windows), int), data.windows)
    from real_model import predicted_fields

    mine = np.abs(predicted_fields(common)) ** 2
    err, scale = relative_error(mine, reference)
    out = {"test": "complex Gaussian spectrum on the peer's M grid, disc pupil of radius R, whole-pixel centres",
           "M": m, "n": n, "common_model_vs_cca": {"relative_error": err, "scale": scale}}
    test_path = workdir / "forward_test.npz"
    np.savez(test_path, spectrum=spectrum, pupil=pupil)
    for family in families:
        ok, python = peer_available(family)
        if not ok:
            out[family] = {"status": "skipped", "reason": python}
            continue
        result_path = workdir / f"forward_{family}.npz"
        try:
            _worker(python, ["check", family, str(data.peer_data), str(test_path), str(result_path)], timeout,
                    workdir / f"forward_{family}.log")
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            out[family] = {"status": "failed", "reason": str(exc)}
            continue
        with np.load(result_path) as res:
            intensity, default_pupil = res["intensity"], res["default_pupil"]
            default_intensity = res["default_intensity"]
            used = res["pupil_used"] if "pupil_used" in res else pupil
        err, scale = relative_error(intensity, reference)
        derr, _ = relative_error(default_intensity, reference)
        out[family] = {"status": "ok", "relative_error": err, "scale": scale,
                       "pupil_equals_disc": bool(np.allclose(used, pupil)),
                       "default_pupil_vs_disc": {
                           "support_px": int(np.sum(np.abs(default_pupil) > 0.5)), "disc_px": int(np.sum(pupil.real > 0.5)),
                           "max_abs_difference": float(np.max(np.abs(default_pupil - pupil))),
                           "intensity_relative_error": derr}}
    return out


# ----------------------------------------------------------------------------- peers

def run_peer(method: str, options: dict, iterations: int, data: Prepared, workdir: Path, timeout: float,
             *, reuse: bool = False, input_key: str | None = None) -> dict:
    """Run one peer configuration; returns its curve of common-representation snapshots.

    With ``reuse`` an output file left by an earlier run is read instead of running the peer again;
    with ``input_key`` too, only if that run recorded the same key (a digest of its inputs).
    The result's ``startup_s`` is the time from launching the worker to its first iteration
    (interpreter, imports, problem build), when the worker reports it.
    """
    workdir = workdir.resolve()
    family = method.split(":")[0]
    ok, python = peer_available(family)
    if not ok:
        return {"status": "skipped", "reason": python}
    out = workdir / f"{method.replace(':', '_')}_{options.get('label', 'default')}.npz"
    opts = {k: v for k, v in options.items() if k != "label"}
    record = out.with_suffix(".run.json")
    previous = json.loads(record.read_text()) if record.exists() else {}
    reused = reuse and out.exists() and (input_key is None or previous.get("input_key") == input_key)
    start = time.perf_counter()
    launch = time.time()
    try:
        if not reused:
            record.unlink(missing_ok=True)
            _worker(python, ["run", method, str(data.peer_data), str(out), "--iterations", str(iterations),
                             "--options", json.dumps(opts)], timeout, out.with_suffix(".log"))
            previous = {"input_key": input_key, "launch_epoch": launch, "wall_s": time.perf_counter() - start}
            record.write_text(json.dumps(previous))
    except (RuntimeError, subprocess.TimeoutExpired) as exc:
        return {"status": "failed", "reason": str(exc)[-400:]}
    wall = previous.get("wall_s", time.perf_counter() - start)
    with np.load(out) as res:
        raw = {k: res[k] for k in res.files}
    n = data.intensity.shape[-1]
    k = len(data.windows)
    snaps = []
    for i, spectrum, pupil in zip(raw["snap_iterations"], raw["snap_spectra"], raw["snap_pupils"]):
        snaps.append((int(i), float(raw["seconds"][int(i) - 1]),
                      Recovery(spectrum, pupil[None], np.zeros(k, int), data.windows)))
    assert all(s[2].n == n for s in snaps)
    startup = None
    if "clock_start_epoch" in raw and "launch_epoch" in previous:
        startup = float(raw["clock_start_epoch"]) - float(previous["launch_epoch"])
    return {"status": "ok", "seconds": raw["seconds"].tolist(), "snaps": snaps, "notes": str(raw["notes"]),
            "python": str(raw["python"]), "wall_s": wall, "startup_s": startup, "reused": reused,
            "own_intensity": raw.get("own_intensity"), "own_loss": float(raw["own_loss"]) if "own_loss" in raw else None}


# ----------------------------------------------------------------------------- cca

def read_cca_recovery(recon: Path, data: Prepared) -> tuple[Recovery, dict]:
    """recon.h5 → common representation (with /calibration when present) and its run facts."""
    from cca_cli.sampling.grid import band_layout

    from cca_cli.io.geometry import read_geometry
    from cca_cli.optics.pupil import circular_pupils as circular_pupils_cca

    n = data.intensity.shape[-1]
    radius = data.radius
    crop = None
    with h5py.File(recon, "r") as handle:
        if "/recon/region_px" in handle:  # recorded frames recovered on a padded grid (guard band)
            region = handle["/recon/region_px"]
            oy, ox, h, w = (int(v) for v in region[1])
            n = int(region.attrs["sensor_grid_px"])
            radius = read_geometry(handle).pupil_radius_px
            crop = (oy, ox, h, w)
        spectrum = np.asarray(handle["/recon/spectrum"])
        attrs = dict(handle["recon"].attrs)
        history = {name: np.asarray(handle[f"/history/{name}"]) for name in ("residual", "seconds")
                   if f"/history/{name}" in handle}
        centres = np.asarray(handle["/geometry/spectrum_centres_yx_px"], np.float64)
        cal = {name: np.asarray(handle[f"/calibration/{name}"]) for name in
               ("pupil", "pupil_map", "pupil_index", "spectrum_centres_yx_px", "brightness")
               if f"/calibration/{name}" in handle}
    m = spectrum.shape[-1]
    facts = {"engine": str(attrs.get("engine")), "iterations": int(attrs.get("iterations", 0)),
             "seconds": float(attrs.get("seconds", np.nan)), "hires": m,
             "engine_options": json.loads(attrs["engine_options"]) if "engine_options" in attrs else {},
             "history": {k: v.tolist() for k, v in history.items()}, "calibration": sorted(cal)}
    if "spectrum_centres_yx_px" in cal:
        centres = np.asarray(cal["spectrum_centres_yx_px"], np.float64)
    windows = np.rint(centres).astype(np.int64)
    if "pupil_map" in cal:
        # cca's model exactly: each capture's NA disc at its own fractional box centre × its pupil's map
        maps = np.asarray(cal["pupil_map"], np.complex64)
        b = maps.shape[-1]
        index = np.asarray(cal.get("pupil_index", np.zeros(len(centres), np.int32)), np.int64)
        discs = circular_pupils_cca(b, centres - windows + b // 2, radius)
        pupils = embed_centred(discs * maps[index], n)
        index = np.arange(len(centres))
        facts["pupil_source"] = "/calibration/pupil_map × each capture's disc"
    elif "pupil" in cal:
        # the engine's pupil(s) on its pupil-box grid, centred at each capture's box centre (the rounded centre)
        pupils = embed_centred(np.asarray(cal["pupil"], np.complex64), n)
        index = np.asarray(cal.get("pupil_index", np.zeros(len(centres), np.int32)), np.int64)
        facts["pupil_source"] = "/calibration/pupil"
    else:
        # no calibration saved: cca's fixed disc at each capture's (fractional) pupil centre, as its model draws it
        layout = band_layout(centres, radius, sensor_size=n, hires_size=m)
        pupils = circle_pupils(n, layout.centres_px - windows, radius, edge_px=1.0)
        index = np.arange(len(centres))
        facts["pupil_source"] = "disc of radius R at the nominal (fractional) centres"
    rec = Recovery(spectrum, pupils, index, windows, brightness=cal.get("brightness"), centres_yx_px=centres,
                   crop_yxhw=crop)
    facts["padded_grid_px"] = None if crop is None else n
    return rec, facts


def run_cca_engine(engine: str, options: dict, data: Prepared, workdir: Path, *, iterations: int | None = None,
                   reuse: bool = False) -> tuple[Recovery, dict]:
    """`cca reconstruct` with the engine's defaults (plus ``options``); ``iterations`` caps the run.

    With ``reuse`` a recon.h5 left by an earlier run with the same config is read instead.
    """
    workdir = workdir.resolve()
    suffix = "" if not options else "_" + hashlib.sha1(json.dumps(options, sort_keys=True).encode()).hexdigest()[:8]
    tag = f"{engine}{suffix}" + ("" if iterations is None else f"_it{iterations}")
    config = workdir / f"reconstruct_{tag}.yaml"
    text = yaml.safe_dump({"reconstruct": {"engine": engine, "options": options}}, sort_keys=False)
    recon = workdir / f"recon_{tag}.h5"
    same = config.exists() and config.read_text() == text
    config.write_text(text)
    args = ["reconstruct", str(data.raw_h5), "-o", str(recon), "--config", str(config), "--force"]
    if iterations is not None:
        args += ["--iterations", str(iterations)]
    start = time.perf_counter()
    if not (reuse and same and recon.exists()):
        run_cca(args, log=workdir / f"reconstruct_{tag}.log")
    rec, facts = read_cca_recovery(recon, data)
    facts["wall_s"] = time.perf_counter() - start
    facts["command"] = "cca " + " ".join(args)
    return rec, facts
