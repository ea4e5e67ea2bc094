"""Time one iteration of each engine on the headline case against the FFT floor.

The floor is the FFT work one iteration cannot avoid: an inverse and a forward
2-D FFT of every capture at the engine's grid size, complex64, on the same
backend (the faster of one batched plan and cache-sized chunks on threads).
Each round times the floor and then every engine, each back to back, so slow
drifts of the machine affect a round's floor and engines alike; the script
prints the median ms/iteration and the median (and quartiles) of the per-round
ratios.

Usage: python benchmarks/bench_altmin.py [--rounds 8] [--repeats 7] [--engines altmin momentum] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import fft_floor_seconds, headline_problem, median_seconds  # noqa: E402

from cca_cli.engines.registry import get_engine  # noqa: E402
from cca_cli.optics import fft  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=7, help="iterations (and floor passes) timed back to back per round")
    parser.add_argument("--engines", nargs="*", default=["altmin", "momentum"], help="registered engines to time")
    parser.add_argument("--store", choices=["band", "sensor"], default="band",
                        help="captures as stored: band grid or full 512² sensor images")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    problem, _ = headline_problem(store=args.store)
    model = problem.model
    k, m = model.n_images, model.layout.lowres_size
    engines = {}
    for name in args.engines:
        entry = get_engine(name)
        engines[name] = entry.engine_class()(problem, entry.options(max_iterations=10**6, tol=0))
        engines[name].update()
    # Rounds of back-to-back blocks (floor, then each engine) keep the machine's slow drifts
    # out of each round's ratio without disturbing either side's caches mid-block.
    floors, times = [], {name: [] for name in engines}
    round_ratios = {name: [] for name in engines}
    for _ in range(args.rounds):
        floors.append(fft_floor_seconds(k, m, repeats=args.repeats)[0])
        for name, engine in engines.items():
            seconds = median_seconds(engine.update, repeats=args.repeats, warmup=1)
            times[name].append(seconds)
            round_ratios[name].append(seconds / floors[-1])
    for engine in engines.values():
        engine.close()

    floor = float(np.median(floors))
    results = {"backend": fft.backend_name(), "threads": fft.cpu_count(), "n_images": k, "lowres_size": m,
               "hires_size": model.layout.hires_size, "store": args.store, "rounds": args.rounds,
               "floor_s": floor, "floor_s_rounds": floors, "engines": {}}
    print(f"headline ({args.store} captures): {k} captures, per-capture grid {m}², output {model.layout.hires_size}², "
          f"FFT backend {results['backend']}, {results['threads']} threads, {args.rounds} interleaved rounds")
    print(f"FFT floor (2 FFTs x {k} at {m}²): median {1e3 * floor:.1f} ms "
          f"(rounds {', '.join(f'{1e3 * f:.1f}' for f in floors)})")
    for name, samples in times.items():
        ratios = round_ratios[name]
        row = {"s_per_iteration": float(np.median(samples)), "ratio_to_floor": float(np.median(ratios)),
               "ratio_quartiles": [float(np.percentile(ratios, 25)), float(np.percentile(ratios, 75))],
               "ratio_rounds": ratios}
        results["engines"][name] = row
        q1, q3 = row["ratio_quartiles"]
        print(f"{name:10s} {1e3 * row['s_per_iteration']:7.1f} ms/iteration   ratio to floor {row['ratio_to_floor']:.2f} "
              f"(quartiles {q1:.2f}–{q3:.2f} over {len(ratios)} rounds)")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
