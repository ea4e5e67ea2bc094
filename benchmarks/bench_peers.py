"""Side-by-side benchmark of our engines against peer FPM codes on the headline data.

Data: the paper's Fig. 5 case made by our simulator (441 captures, 21 x 21 at
61% overlap, 512² output). Our engines get the band-stored captures (90²) and,
separately, the full-size sensor captures (512²); peers get the band captures
Fourier-interpolated to 128² (exact: the intensity band fits in 90², so every
method sees the same measurements and the same noise).

Every method runs in its own subprocess (``peer_worker.py``), in interleaved
order, so peak memory (``VmHWM``) is that method's own. Reported per
method: median s/iteration and its ratio to the FFTW floor at the method's own
grid (2 FFTs per capture per iteration), iterations and seconds to reach
MTF20 ≤ 2 px *and* amplitude RMSE (against the band-limited truth) within 10%
of the best peer's, peak memory, and the speed-up against the fastest peer.
A peer that is not installed is reported as skipped.

Errors are measured on the 512² truth grid: every object is Fourier
resampled (spectrum zero-padded or cropped, centred) to 512², aligned to the
truth by the flip/transpose and whole-pixel circular shift that best correlate
its amplitude with the truth's (peers use other FFT and sign conventions), and
compared with the band-limited truth (truth spectrum masked to the union of
pupil discs: :func:`cca_cli.report.summary.band_limited_truth`).

Usage::

    python benchmarks/bench_peers.py [--peers ptylab,fpmrs,fpmpy] [--iterations 20]
        [--ours-iterations 40] [--out benchmarks/results/peers.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from common import fft_floor_seconds  # noqa: E402

from cca_cli.config.load import load_config  # noqa: E402
from cca_cli.engines.registry import engine_names  # noqa: E402
from cca_cli.metrics import amplitude_rmse, contrast_table, mtf_limit, rmse  # noqa: E402
from cca_cli.optics import fft  # noqa: E402
from cca_cli.report.summary import band_limited_truth  # noqa: E402
from cca_cli.stages.simulate import simulate  # noqa: E402

#: Interpreter and import check of each peer family.
PEER_PYTHON = {
    "ptylab": (ROOT / ".venv-peers/bin/python", "import PtyLab"),
    "fpmrs": (ROOT / ".venv-fpmrs/bin/python", "import fpm_rs"),
    "fpmpy": (ROOT / ".venv-peers/bin/python", "import fpm_py"),
}
INSTALL_HINT = {
    "ptylab": "python -m venv --system-site-packages .venv-peers && .venv-peers/bin/pip install ptylab",
    "fpmrs": "~/.pyenv/versions/3.13.0/bin/python -m venv .venv-fpmrs && .venv-fpmrs/bin/pip install fpm-rs numpy",
    "fpmpy": ".venv-peers/bin/pip install torch==2.13.0 && .venv-peers/bin/pip install fpm-py",
}
PEER_SIZE = 128
MTF_TARGET_PX = 2
RMSE_SLACK = 1.10


# ----------------------------------------------------------------------------- data

def prepare_data(folder: Path, *, with_sensor: bool) -> dict:
    """Simulate the headline captures (band and, optionally, sensor store) and the peers' 128² file."""
    folder.mkdir(parents=True, exist_ok=True)
    base = load_config()
    out = {}
    for store in (["band", "sensor"] if with_sensor else ["band"]):
        config = base.model_copy(update={"simulate": base.simulate.model_copy(update={"store": store})})
        simulation = simulate(config)
        np.save(folder / f"{store}.npy", simulation.intensity)
        out[store] = {"path": folder / f"{store}.npy", "shape": simulation.intensity.shape,
                      "bytes": int(simulation.intensity.nbytes)}
        if store == "band":
            g = simulation.geometry
            peers = fft.fourier_resample(simulation.intensity, PEER_SIZE).astype(np.float32)
            np.savez(folder / "peers128.npz", images=peers, centres_yx_px=g.spectrum_centres_yx_px,
                     pupil_radius_px=g.pupil_radius_px, field_width_m=g.field_width_m,
                     wavelength_m=g.wavelength_m, hires_size=simulation.scene.field.shape[-1])
            out["peers"] = {"path": folder / "peers128.npz", "shape": peers.shape, "bytes": int(peers.nbytes)}
            out["scene"], out["geometry"] = simulation.scene, g
        del simulation
    return out


# ----------------------------------------------------------------------------- metrics

def to_grid(obj: np.ndarray, size: int) -> np.ndarray:
    """Fourier-resample a centred complex object to ``size x size`` (spectrum pad/crop about DC)."""
    n = obj.shape[-1]
    if n == size:
        return obj
    spectrum = fft.fft2c(obj.astype(np.complex64))
    out = np.zeros((size, size), np.complex64)
    if n < size:
        lo = size // 2 - n // 2
        out[lo:lo + n, lo:lo + n] = spectrum
    else:
        lo = n // 2 - size // 2
        out[:] = spectrum[lo:lo + size, lo:lo + size]
    return fft.ifft2c(out)


def _dihedral(image: np.ndarray, k: int) -> np.ndarray:
    out = np.rot90(image, k % 4)
    return out.T if k >= 4 else out


def alignment(obj: np.ndarray, reference: np.ndarray) -> tuple[int, tuple[int, int]]:
    """Flip/transpose and circular shift that best match ``|obj|`` to ``|reference|``."""
    ref = np.abs(reference) - np.abs(reference).mean()
    ref_f = np.conj(np.fft.fft2(ref))
    best = (-np.inf, 0, (0, 0))
    for k in range(8):
        a = np.abs(_dihedral(obj, k))
        corr = np.fft.ifft2(np.fft.fft2(a - a.mean()) * ref_f).real
        idx = np.unravel_index(int(np.argmax(corr)), corr.shape)
        if corr[idx] > best[0]:
            best = (float(corr[idx]), k, (-int(idx[0]), -int(idx[1])))
    return best[1], best[2]


def apply_alignment(obj: np.ndarray, how: tuple[int, tuple[int, int]]) -> np.ndarray:
    k, shift = how
    return np.roll(_dihedral(obj, k), shift, axis=(0, 1))


def evaluate(snaps: np.ndarray, truth: np.ndarray, band_truth: np.ndarray, bars) -> tuple[list, dict]:
    """Amplitude RMSE (band-limited truth), intensity RMSE (truth) and MTF20 of each snapshot."""
    size = truth.shape[-1]
    how = alignment(to_grid(snaps[-1], size), band_truth)
    rows = []
    truth_intensity = np.abs(truth) ** 2
    for snap in snaps:
        obj = apply_alignment(to_grid(snap, size), how)
        intensity = np.abs(obj) ** 2
        rows.append({"amplitude_rmse": amplitude_rmse(obj, band_truth),
                     "intensity_rmse": rmse(intensity, truth_intensity),
                     "mtf20_px": mtf_limit(contrast_table(intensity, bars), threshold=0.2)})
    return rows, {"dihedral": how[0], "shift_px": list(how[1])}


# ----------------------------------------------------------------------------- running

def peer_status(family: str) -> tuple[bool, str]:
    python, check = PEER_PYTHON[family]
    if not python.exists():
        return False, f"{python} missing; install with: {INSTALL_HINT[family]}"
    probe = subprocess.run([str(python), "-c", check], capture_output=True, text=True)
    if probe.returncode != 0:
        return False, f"`{check}` fails in {python}: {probe.stderr.strip().splitlines()[-1:]}; {INSTALL_HINT[family]}"
    return True, str(python)


def run_worker(method: str, python: str, data: Path, out: Path, iterations: int, timeout: float) -> dict:
    command = [python, str(HERE / "peer_worker.py"), method, str(data), str(out), "--iterations", str(iterations)]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    start = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True, env=env, cwd=ROOT, timeout=timeout)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        lines = [line for line in (proc.stderr or proc.stdout).strip().splitlines() if line.strip()]
        return {"status": "failed", "reason": lines[-1] if lines else f"exit {proc.returncode}",
                "log_tail": "\n".join(lines[-15:]), "wall_s": wall}
    return {"status": "ok", "wall_s": wall}


def summarise(name: str, raw, metrics: list, floors: dict, rounds: list[np.ndarray]) -> dict:
    """One method's row: the quality curve of its first round, timings pooled over all rounds."""
    seconds = np.asarray(raw["seconds"], np.float64)
    per_iteration = np.concatenate([np.diff(np.concatenate([[0.0], r])) for r in rounds])
    s_it = float(np.median(per_iteration))
    fft_size = int(raw["fft_size"])
    snap_iterations = [int(i) for i in raw["snap_iterations"]]
    curve = [{"iteration": i, "seconds": float(seconds[i - 1]), **m} for i, m in zip(snap_iterations, metrics)]
    return {"method": name, "notes": str(raw["notes"]), "python": str(raw["python"]),
            "iterations_run": int(len(seconds)), "s_per_iteration": s_it, "rounds": len(rounds),
            "s_per_iteration_by_round": [float(np.median(np.diff(np.concatenate([[0.0], r])))) for r in rounds],
            "round_seconds": [r.tolist() for r in rounds],
            "fft_size": fft_size, "floor_s": floors[fft_size], "ratio_to_floor": s_it / floors[fft_size],
            "peak_rss_bytes": int(raw["peak_rss_bytes"]), "baseline_rss_bytes": int(raw["baseline_rss_bytes"]),
            "best_amplitude_rmse": min(c["amplitude_rmse"] for c in curve),
            "final": curve[-1], "curve": curve}


def time_to_target(row: dict, rmse_target: float) -> None:
    row["rmse_target"] = rmse_target
    row["target_iteration"] = row["target_seconds"] = None
    for point in row["curve"]:
        mtf = point["mtf20_px"]
        if mtf is not None and mtf <= MTF_TARGET_PX and point["amplitude_rmse"] <= rmse_target:
            row["target_iteration"] = point["iteration"]
            row["target_seconds_by_round"] = [r[point["iteration"] - 1] for r in row["round_seconds"]]
            row["target_seconds"] = float(np.median(row["target_seconds_by_round"]))
            break


def interleave(ours: list, peers: list) -> list:
    order = []
    for i in range(max(len(ours), len(peers))):
        order += ours[i:i + 1] + peers[i:i + 1]
    return order


# ----------------------------------------------------------------------------- output

def fmt_bytes(n) -> str:
    return f"{n / 2**20:.0f} MiB"


def table(results: dict) -> str:
    head = ("| method | grid | s/iteration | × FFTW floor (min / median sample) | iterations to target | s to target | "
            "speed-up vs fastest peer | peak RSS (Δ over baseline) | amp. RMSE (best) | MTF20 final |")
    lines = [head, "|" + "---|" * 10]
    for row in results["methods"]:
        speedup = row.get("speedup_vs_fastest_peer")
        if row.get("status") != "ok":
            lines.append(f"| {row['method']} | {row['status']}: {row['reason'][:160]} |" + " |" * 8)
            continue
        t = row["target_seconds"]
        lines.append(
            f"| {row['method']} | {row['fft_size']}² | {row['s_per_iteration']:.3f} | "
            f"{row['ratio_to_floor']:.2f} / {row['ratio_to_median_floor']:.2f} | "
            f"{row['target_iteration'] or '—'} | {'—' if t is None else f'{t:.2f}'} | "
            f"{'—' if speedup is None else f'{speedup:.1f}×'} | "
            f"{fmt_bytes(row['peak_rss_bytes'])} ({fmt_bytes(row['peak_rss_bytes'] - row['baseline_rss_bytes'])}) | "
            f"{row['best_amplitude_rmse']:.4f} | {row['final']['mtf20_px']} |")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for row in results["methods"]:
        if row.get("status") != "ok":
            continue
        t = [p["seconds"] for p in row["curve"]]
        style = "-" if row["method"].startswith("ours") else "--"
        axes[0].plot(t, [p["amplitude_rmse"] for p in row["curve"]], style, marker=".", label=row["method"])
        axes[1].plot(t, [p["mtf20_px"] if p["mtf20_px"] is not None else np.nan for p in row["curve"]], style,
                     marker=".", label=row["method"])
        hit = [p for p in row["curve"] if p["iteration"] == row["target_iteration"]]
        if hit:
            axes[0].plot(hit[0]["seconds"], hit[0]["amplitude_rmse"], "k*", ms=10)
    axes[0].axhline(results["rmse_target"], color="grey", lw=0.8, ls=":", label="RMSE target")
    axes[0].set(xscale="log", yscale="log", xlabel="wall time (s)", ylabel="amplitude RMSE vs band-limited truth",
                title="error vs time (★ = MTF20 ≤ 2 px and RMSE target reached)")
    axes[1].axhline(MTF_TARGET_PX, color="grey", lw=0.8, ls=":")
    axes[1].set(xscale="log", xlabel="wall time (s)", ylabel="MTF20 limit (px, lower is better)", title="resolution")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--peers", default="ptylab,fpmrs,fpmpy", help="comma list of ptylab, fpmrs, fpmpy ('' for none)")
    parser.add_argument("--ptylab-engines", default="ePIE,mPIE,qNewton", help="also: mqNewton (about 20x slower)")
    parser.add_argument("--fpmrs-algorithms", default="ap,fpie")
    parser.add_argument("--engines", default=",".join(engine_names()), help="our registered engines to run")
    parser.add_argument("--iterations", type=int, default=20, help="iterations of each peer")
    parser.add_argument("--ours-iterations", type=int, default=40, help="iterations of each of our engines")
    parser.add_argument("--no-sensor", action="store_true", help="skip our engines on full-size 512² captures")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "peers.json")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds allowed per method")
    parser.add_argument("--rounds", type=int, default=2,
                        help="interleaved runs of every method; timings are medians over all rounds")
    args = parser.parse_args()

    workdir = args.out.parent / (args.out.stem + "_work")
    workdir.mkdir(parents=True, exist_ok=True)
    print("simulating the headline data ...", flush=True)
    data = prepare_data(workdir / "data", with_sensor=not args.no_sensor)
    truth, bars = data["scene"].field, data["scene"].bars
    # amplitude_rmse and alignment() read only |band truth|: the square root of its intensity
    band_truth = np.sqrt(band_limited_truth(truth, data["geometry"]))

    band_size = int(data["band"]["shape"][-1])  # our engines' per-capture grid (the band-stored captures)
    floor_samples = {band_size: [], PEER_SIZE: []}

    def measure_floors() -> None:  # interleaved with the methods; the floor is the fastest sample
        for size in floor_samples:
            floor_samples[size].append(fft_floor_seconds(data["geometry"].n_images, size, repeats=5)[0])

    measure_floors()

    ours = []
    for engine in [e for e in args.engines.split(",") if e]:
        ours.append((f"ours:{engine}", f"ours:{engine}", sys.executable, data["band"]["path"], args.ours_iterations))
        if not args.no_sensor:
            ours.append((f"ours:{engine}@sensor512", f"ours:{engine}", sys.executable, data["sensor"]["path"],
                         args.ours_iterations))
    peers, skipped = [], []
    families = [p for p in args.peers.split(",") if p]
    variants = {"ptylab": args.ptylab_engines.split(","), "fpmrs": args.fpmrs_algorithms.split(","), "fpmpy": [""]}
    for family in families:
        ok, python_or_reason = peer_status(family)
        for variant in variants[family]:
            method = f"{family}:{variant}" if variant else family
            if ok:
                peers.append((method, method, python_or_reason, data["peers"]["path"], args.iterations))
            else:
                skipped.append({"method": method, "status": "skipped", "reason": python_or_reason})

    failed, first, timings, peaks = {}, {}, {}, {}
    for round_index in range(args.rounds):
        for name, method, python, path, iterations in interleave(ours, peers):
            if name in failed:
                continue
            out = workdir / (name.replace(":", "_").replace("@", "_") + f"_r{round_index}.npz")
            print(f"round {round_index + 1}: running {name} ({iterations} iterations) ...", flush=True)
            try:
                status = run_worker(method, python, path, out, iterations, args.timeout)
            except subprocess.TimeoutExpired:
                status = {"status": "failed", "reason": f"timed out after {args.timeout:.0f} s"}
            measure_floors()
            if status["status"] != "ok":
                print(f"  {name} failed: {status['reason'][-300:]}", flush=True)
                failed[name] = {"method": name, **status}
                continue
            raw = np.load(out)
            timings.setdefault(name, []).append(np.asarray(raw["seconds"], np.float64))
            peaks[name] = max(peaks.get(name, 0), int(raw["peak_rss_bytes"]))
            print(f"  {np.median(np.diff(np.concatenate([[0.0], raw['seconds']]))):.3f} s/iteration, "
                  f"peak {fmt_bytes(raw['peak_rss_bytes'])}", flush=True)
            if round_index == 0:
                first[name] = (raw, status["wall_s"])

    floors = {size: min(v) for size, v in floor_samples.items()}
    rows = list(skipped)
    for name, *_ in interleave(ours, peers):
        if name in failed:
            rows.append(failed[name])
            continue
        raw, wall = first[name]
        metrics, how = evaluate(raw["snaps"], truth, band_truth, bars)
        row = {**summarise(name, raw, metrics, floors, timings[name]), "status": "ok", "alignment": how,
               "wall_s": wall}
        row["peak_rss_bytes"] = peaks[name]
        print(f"{name}: {row['s_per_iteration']:.3f} s/iteration, best amplitude RMSE "
              f"{row['best_amplitude_rmse']:.4f}, final MTF20 {row['final']['mtf20_px']}", flush=True)
        rows.append(row)
    ok_rows = [r for r in rows if r.get("status") == "ok"]
    for row in ok_rows:
        # summarise() gives the ratio to the fastest floor sample; this one is against the median sample,
        # so both sides see the machine's typical load
        row["ratio_to_median_floor"] = row["s_per_iteration"] / float(np.median(floor_samples[row["fft_size"]]))
    peer_rows = [r for r in ok_rows if not r["method"].startswith("ours")]
    reference = peer_rows or ok_rows
    rmse_target = RMSE_SLACK * min(r["best_amplitude_rmse"] for r in reference) if reference else float("nan")
    for row in ok_rows:
        time_to_target(row, rmse_target)
    peer_times = [r["target_seconds"] for r in peer_rows if r["target_seconds"] is not None]
    fastest_peer = min(peer_times) if peer_times else None
    for row in ok_rows:
        t = row["target_seconds"]
        row["speedup_vs_fastest_peer"] = None if (t is None or fastest_peer is None) else fastest_peer / t

    checks = {}
    by_name = {r["method"]: r for r in ok_rows}
    for engine in args.engines.split(","):
        band, sensor = by_name.get(f"ours:{engine}"), by_name.get(f"ours:{engine}@sensor512")
        if band and sensor:
            stack = data["sensor"]["bytes"]
            extra = sensor["peak_rss_bytes"] - sensor["baseline_rss_bytes"]
            checks[engine] = {
                "sensor_over_band_s_per_iteration": sensor["s_per_iteration"] / band["s_per_iteration"],
                "capture_stack_bytes": stack, "peak_rss_bytes": sensor["peak_rss_bytes"],
                "peak_over_baseline_bytes": extra, "peak_over_baseline_vs_stack": extra / stack,
                "peak_rss_vs_stack": sensor["peak_rss_bytes"] / stack}

    results = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load_avg": os.getloadavg(),
                    "fft_backend": fft.backend_name()},
        "data": {"n_images": data["geometry"].n_images, "ours_band_shape": list(data["band"]["shape"]),
                 "peers_shape": list(data["peers"]["shape"]),
                 "sensor_shape": list(data["sensor"]["shape"]) if "sensor" in data else None,
                 "output": list(truth.shape)},
        "fftw_floor_s": {str(k): v for k, v in floors.items()},
        "fftw_floor_samples_s": {str(k): v for k, v in floor_samples.items()},
        "rounds": args.rounds,
        "mtf_target_px": MTF_TARGET_PX, "rmse_target": rmse_target,
        "rmse_target_rule": f"{RMSE_SLACK:.2f} x best amplitude RMSE of {'the peers' if peer_rows else 'all methods'}",
        "fastest_peer_target_seconds": fastest_peer,
        "full_size_checks": checks,
        "methods": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1, default=float))
    plot(results, args.out.with_suffix(".png"))
    print()
    print(f"FFTW floor (2 FFTs x {data['geometry'].n_images}): "
          + ", ".join(f"{k}²: {1e3 * v:.1f} ms" for k, v in floors.items()))
    print(f"target: MTF20 ≤ {MTF_TARGET_PX} px and amplitude RMSE ≤ {rmse_target:.4f} ({results['rmse_target_rule']})")
    print(table(results))
    for engine, c in checks.items():
        print(f"full-size ({engine}): s/iteration sensor/band = {c['sensor_over_band_s_per_iteration']:.2f}; "
              f"peak RSS {fmt_bytes(c['peak_rss_bytes'])} = {c['peak_rss_vs_stack']:.2f}x the "
              f"{fmt_bytes(c['capture_stack_bytes'])} capture stack ({c['peak_over_baseline_vs_stack']:.2f}x "
              f"over the process baseline)")
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
