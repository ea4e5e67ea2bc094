"""Speed-up of `cca sweep` with 1 and 2 Dask workers on the same 8-point sweep.

Run: ``python benchmarks/sweep_scaling.py [--repeats 3] [--iterations 60]``

Each repeat recomputes every point (``force=True``) on a LocalCluster started
beforehand, so the timing covers the points' work and Dask's scheduling, not
the cluster start-up. Prints the median wall time per worker count and the
speed-up. The points are 128 px resolution charts on 7x7 … 13x13 grids
(49-169 captures each), a few seconds each on one core.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from cca_cli.config.load import parse_config
from cca_cli.config.model import SweepSection
from cca_cli.stages.sweep import expand_points, open_client, run_sweep


def base_config(iterations: int):
    return parse_config({
        "scene": {"kind": "resolution_chart", "size_px": 128, "field_width_m": 128 * 125e-6,
                  "widths_px": [6, 4, 3, 2, 1]},
        "array": {"grid": 7, "overlap": 0.61},
        "noise": {"model": "gaussian", "snr_db": 30},
        "simulate": {"store": "band"},
        "reconstruct": {"iterations": iterations, "tol": 0},
        "report": {"figures": False},
    }, source="benchmark")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=60)
    args = parser.parse_args()
    spec = SweepSection(parameters={"array.grid": [7, 9, 11, 13], "noise.snr_db": [20, 30]})
    medians = {}
    with tempfile.TemporaryDirectory() as tmp:
        points = expand_points(base_config(args.iterations), spec, Path(tmp))
        assert len(points) == 8
        for workers in (1, 2):
            with open_client(workers=workers) as client:
                run_sweep(points[:1], client, force=True)  # warm the workers (imports, FFT plans)
                times = []
                for _ in range(args.repeats):
                    start = time.perf_counter()
                    rows = run_sweep(points, client, force=True)
                    times.append(time.perf_counter() - start)
                    assert all(r["status"] == "ok" for r in rows), [r["error"] for r in rows]
            medians[workers] = statistics.median(times)
            print(f"{workers} worker(s): median {medians[workers]:.2f} s over {args.repeats} runs "
                  f"({', '.join(f'{t:.2f}' for t in times)})")
    print(f"speed-up 1 → 2 workers: {medians[1] / medians[2]:.2f}x")


if __name__ == "__main__":
    main()
