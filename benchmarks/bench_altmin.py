"""Time one alternating-minimization iteration on the headline case against the FFT floor.

The floor is the FFT work one iteration cannot avoid: an inverse and a forward
2-D FFT of every capture at the engine's grid size, complex64, on the same
backend. Prints ms/iteration, the floor and their ratio (medians).

Usage: python benchmarks/bench_altmin.py [--repeats 15] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import fft_floor_seconds, headline_problem, median_seconds  # noqa: E402

from cca_cli.engines.altmin import AlternatingMinimization, AltMinOptions  # noqa: E402
from cca_cli.optics import fft  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--chunks", type=int, nargs="*", default=[8, 16, 32])
    args = parser.parse_args()

    problem, _ = headline_problem()
    model = problem.model
    k, m = model.n_images, model.layout.lowres_size
    results = {"backend": fft.backend_name(), "threads": fft.cpu_count(), "n_images": k, "lowres_size": m,
               "hires_size": model.layout.hires_size, "engines": {}}
    floor, how = fft_floor_seconds(k, m, repeats=args.repeats)
    results["floor_s"], results["floor_method"] = floor, how
    for chunk in args.chunks:
        engine = AlternatingMinimization(problem, AltMinOptions(chunk=chunk, max_iterations=10**6, tol=0))
        seconds = median_seconds(engine.update, repeats=args.repeats, warmup=2)
        engine.close()
        results["engines"][f"altmin_chunk{chunk}"] = {"s_per_iteration": seconds, "ratio_to_floor": seconds / floor}
    floor_again, _ = fft_floor_seconds(k, m, repeats=args.repeats)
    results["floor_s"] = min(floor, floor_again)

    print(f"headline: {k} captures, per-capture grid {m}², output {model.layout.hires_size}², "
          f"FFT backend {results['backend']}, {results['threads']} threads")
    print(f"FFT floor (2 FFTs x {k} at {m}², {how}): {1e3 * results['floor_s']:.1f} ms")
    for name, row in results["engines"].items():
        row["ratio_to_floor"] = row["s_per_iteration"] / results["floor_s"]
        print(f"{name:20s} {1e3 * row['s_per_iteration']:7.1f} ms/iteration   ratio {row['ratio_to_floor']:.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
