"""Wide-field tiled reconstruction: per-tile pupils against one pupil, seams, Dask scaling, memory per worker.

Run: ``python benchmarks/widefield.py [--config configs/widefield.yaml] [--sizes 1024,2048,4096]
[--quality-size 2048] [--repeats 1] [--out benchmarks/results/widefield]``

1. **Quality** (``--quality-size``): the config's simulated frame (a field-varying aberration) recovered
   in tiles with per-tile pupils and with one pupil (the centre tile's, held fixed on every tile,
   ``tiles.pupil: global``): band-limited RMSE of each against the truth, and the seam check (RMSE inside
   tile overlaps over RMSE at tile centres); per-tile Zernike coefficients against the truth at the tile
   centres.
2. **Scaling**: the same per-tile run on a LocalCluster of 1 and of 2 single-threaded workers started
   beforehand (the time covers the tiles' work, Dask's scheduling and the blend, not the cluster start-up).
3. **Memory per worker**: the per-tile run on frames of each ``--sizes`` (same optics and tiles, the field
   widened; a perfect lens and ``--memory-iterations`` passes per tile, so that 4096² takes minutes, not
   an hour: a worker holds one tile at a time either way), the peak resident memory of each worker
   process read from the workers when the run ends, and the client's own peak.

Writes ``widefield.json`` and PNG panels (recovered, truth, error maps) under ``--out``.
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import time
from pathlib import Path

import numpy as np
import yaml

from cca_cli.config.load import parse_config
from cca_cli.io.h5 import Provenance


def config_at(data: dict, size: int, reference: int, *, aberration: bool = True, iterations: int | None = None):
    """The config with a ``size``-px frame: the scene widened at the same pixel pitch.

    ``aberration=False`` drops the aberration section (a perfect lens simulates much faster; a worker's
    memory does not depend on it); ``iterations`` caps every tile's passes.
    """
    data = copy.deepcopy(data)
    if not aberration:
        data.pop("aberration", None)
    if iterations is not None:
        data["reconstruct"]["iterations"] = iterations
    scene = data["scene"]
    scene["field_width_m"] = float(scene["field_width_m"]) * size / reference
    scene["size_px"] = size
    return parse_config(data, source=f"widefield-{size}")


def simulate(config, path: Path) -> Path:
    from cca_cli.stages import simulate as stage

    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        stage.run(config, path, provenance=Provenance.make("simulate", "", ""))
        print(f"simulated {path} in {time.perf_counter() - start:.1f} s", flush=True)
    return path


def run_tiles(captures: Path, section, out: Path, client) -> tuple[object, float]:
    from cca_cli.workflows.tiled import reconstruct_tiled

    from cca_cli.io.tiles import remove_tile_folder

    remove_tile_folder(out)
    start = time.perf_counter()
    tiled = reconstruct_tiled(captures, section, out, run_fingerprint=f"bench-{time.time_ns()}",
                              provenance=Provenance.make("reconstruct", "", "", [captures]), client=client)
    seconds = time.perf_counter() - start
    remove_tile_folder(out)
    return tiled, seconds


def _reset_peak() -> bool:
    """Reset this process's peak resident memory (Linux: ``/proc/self/clear_refs``), so that what a forked
    worker inherited from its parent's peak does not count."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_mb() -> float:
    """This process's peak resident memory since the last reset (``VmHWM``), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024.0
    return float("nan")


def worker_peak_rss(client) -> list[float]:
    """Peak resident memory (MB) of each worker process since :func:`_reset_peak` ran on it."""
    return sorted(float(v) for v in client.run(_peak_mb).values())


def band_truth(captures: Path):
    import h5py

    from cca_cli.io.geometry import read_geometry
    from cca_cli.report.summary import band_limited_truth

    with h5py.File(captures, "r") as f:
        truth = np.asarray(f["/truth/object"])
        geometry = read_geometry(f)
        aberration = {name: np.asarray(f[f"/truth/{name}"]) for name in ("aberration_waves", "aberration_nodes_px")
                      if f"/truth/{name}" in f}
    return band_limited_truth(truth, geometry), aberration


def error_maps(tiled, band: np.ndarray) -> dict:
    """Band-limited RMSE, and RMSE inside overlaps against at tile centres, on the truth grid."""
    from cca_cli.metrics import rmse
    from cca_cli.report.summary import on_grid

    intensity = np.abs(tiled.object) ** 2
    h, w = intensity.shape
    recovered = on_grid(intensity, band.shape[-1])
    total = rmse(recovered, band)
    scale = float(np.vdot(recovered, band).real / np.vdot(recovered, recovered).real)
    error = (scale * recovered - band) / float(band.max())
    plan = tiled.plan
    factor = band.shape[-1] / plan.frame.frame_shape[1]
    coverage = np.zeros(plan.frame.frame_shape, np.int32)
    centres = np.zeros(plan.frame.frame_shape, bool)
    for tile in plan.tiles.tiles:
        coverage[tile.y0:tile.y0 + tile.size, tile.x0:tile.x0 + tile.size] += 1
        quarter = tile.size // 4
        centres[tile.y0 + quarter:tile.y0 + tile.size - quarter, tile.x0 + quarter:tile.x0 + tile.size - quarter] = True
    overlaps = coverage > 1
    centres &= coverage == 1
    up = lambda mask: np.kron(mask, np.ones((int(factor), int(factor)), bool)) if factor >= 1 else mask
    overlap_rmse = float(np.sqrt(np.mean(error[up(overlaps)] ** 2)))
    centre_rmse = float(np.sqrt(np.mean(error[up(centres)] ** 2)))
    return {"rmse_band": total, "rmse_overlaps": overlap_rmse, "rmse_tile_centres": centre_rmse,
            "seam_ratio": overlap_rmse / centre_rmse, "_error": error, "_recovered": scale * recovered}


def zernike_error(tiled, aberration: dict) -> dict | None:
    """RMS difference of the tiles' defocus and astigmatism from the truth at each tile centre (waves)."""
    if "aberration_waves" not in aberration:
        return None
    from cca_cli.optics.field_aberration import aberration_at

    found, truth = [], []
    for result, tile in zip(tiled.results, tiled.plan.tiles.tiles):
        if result.zernike_waves is None:
            return None
        found.append(np.atleast_2d(result.zernike_waves)[0, :3])
        truth.append(aberration_at(aberration["aberration_waves"], aberration["aberration_nodes_px"],
                                   np.array([tile.centre_yx]))[0, :3])
    found, truth = np.array(found), np.array(truth)
    return {"rms_error_waves": [round(float(v), 4) for v in np.sqrt(np.mean((found - truth) ** 2, axis=0))],
            "truth_range_waves": [[round(float(truth[:, j].min()), 3), round(float(truth[:, j].max()), 3)]
                                  for j in range(3)],
            "modes": ["defocus", "astigmatism_0", "astigmatism_45"]}


def panels(path: Path, runs: dict, band: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = band.shape[-1]
    zoom = (slice(n // 2 - n // 8, n // 2 + n // 8),) * 2
    fig, axes = plt.subplots(2, len(runs) + 1, figsize=(4.2 * (len(runs) + 1), 8.4))
    axes[0, 0].imshow(band, cmap="gray")
    axes[0, 0].set_title("band-limited truth")
    axes[1, 0].imshow(band[zoom], cmap="gray")
    axes[1, 0].set_title("truth, centre zoom")
    for j, (name, maps) in enumerate(runs.items(), start=1):
        axes[0, j].imshow(np.abs(maps["_error"]), cmap="magma", vmin=0, vmax=0.1)
        axes[0, j].set_title(f"{name}: |error| (RMSE {maps['rmse_band']:.4f})")
        axes[1, j].imshow(maps["_recovered"][zoom], cmap="gray")
        axes[1, j].set_title(f"{name}: recovered, centre zoom")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("configs/widefield.yaml"))
    parser.add_argument("--sizes", default="1024,2048,4096")
    parser.add_argument("--quality-size", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--memory-iterations", type=int, default=20)
    parser.add_argument("--skip", default="", help="comma list of parts to skip: quality, scaling, memory")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/widefield"))
    args = parser.parse_args()
    from cca_cli.workflows.cluster import open_client

    data = yaml.safe_load(args.config.read_text())
    reference = int(data["scene"]["size_px"])
    args.out.mkdir(parents=True, exist_ok=True)
    skip = set(filter(None, args.skip.split(",")))
    record: dict = {"config": str(args.config), "machine_cores": __import__("os").cpu_count()}
    config = config_at(data, args.quality_size, reference)
    captures = simulate(config, args.out / f"captures_{args.quality_size}.h5")
    section = config.reconstruct
    if "quality" not in skip:
        band, aberration = band_truth(captures)
        runs = {}
        with open_client(workers=2) as client:
            for mode in ("per_tile", "global"):
                tiles = section.tiles.model_copy(update={"pupil": mode})
                tiled, seconds = run_tiles(captures, section.model_copy(update={"tiles": tiles}),
                                           args.out / f"recon_{mode}.h5", client)
                maps = error_maps(tiled, band)
                maps["seconds"] = round(seconds, 2)
                maps["tiles"] = len(tiled.results)
                maps["zernike"] = zernike_error(tiled, aberration)
                runs[mode] = maps
                print(mode, {k: v for k, v in maps.items() if not k.startswith("_")}, flush=True)
        panels(args.out / "widefield_quality.png", runs, band)
        record["quality"] = {mode: {k: v for k, v in maps.items() if not k.startswith("_")}
                             for mode, maps in runs.items()}
    if "scaling" not in skip:
        times = {}
        for workers in (1, 2):
            with open_client(workers=workers) as client:
                times[workers] = [run_tiles(captures, section, args.out / "recon_scaling.h5", client)[1]
                                  for _ in range(args.repeats)]
            print(f"{workers} worker(s): {times[workers]}", flush=True)
        record["scaling"] = {"seconds": {str(k): v for k, v in times.items()},
                             "median_s": {str(k): statistics.median(v) for k, v in times.items()},
                             "speedup": statistics.median(times[1]) / statistics.median(times[2])}
        print("speed-up 2 vs 1 worker:", record["scaling"]["speedup"], flush=True)
    if "memory" not in skip:
        memory = {}
        for size in (int(v) for v in args.sizes.split(",")):
            sized = config_at(data, size, reference, aberration=False, iterations=args.memory_iterations)
            path = simulate(sized, args.out / f"captures_perfect_{size}.h5")
            with open_client(workers=2) as client:
                client.run(_reset_peak)
                before = worker_peak_rss(client)
                _reset_peak()
                tiled, seconds = run_tiles(path, sized.reconstruct, args.out / f"recon_{size}.h5", client)
                after = worker_peak_rss(client)
            memory[str(size)] = {"tiles": len(tiled.results), "seconds": round(seconds, 1),
                                 "worker_rss_mb_after_reset": before, "worker_peak_rss_mb": after,
                                 "captures_file_mb": round(path.stat().st_size / 1e6, 1),
                                 "client_peak_rss_mb": _peak_mb()}
            print(size, memory[str(size)], flush=True)
        record["memory_per_worker"] = memory
    (args.out / "widefield.json").write_text(json.dumps(record, indent=2))
    print(f"wrote {args.out / 'widefield.json'}")


if __name__ == "__main__":
    main()
