"""How reconstruction time scales with threads, on recorded captures.

Runs ``cca.reconstruct`` on one capture set with 1, 2, 4, ... threads (up to
the cores this process may use), several times each, and prints the median
whole-call time, the passes run and the median time per pass, with the speed-up
over one thread. Per-pass time is the fair comparison: with more than two
threads the spectrum is split further, so a run may stop a few passes earlier
or later. The passes alone (the engine's loop, ``Reconstruction.seconds``) are
shown beside the whole call: what lies outside them (problem and engine set-up,
the final fit report) runs mostly on one thread. Memory is reused as the ``cca``
command lets it be (:func:`cca_cli.commands.entry.keep_freed_memory`).

Usage::

    cca ingest configs/bloodsmear_green_manifest.yaml -o blood_raw.h5
    python benchmarks/bench_threads.py blood_raw.h5 --repeats 3
    python benchmarks/bench_threads.py blood_raw.h5 --threads 1,2 --json threads.json
    python benchmarks/bench_threads.py blood_raw.h5 --threads 2 --iterations 33 --repeats 5   # capped runs
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import cca_cli as cca
from cca_cli.commands.entry import keep_freed_memory
from cca_cli.optics.fft import cpu_count


def thread_counts(cores: int) -> list[int]:
    """1, 2, 4, ... up to ``cores``, and ``cores`` itself."""
    counts, n = [], 1
    while n < cores:
        counts.append(n)
        n *= 2
    return counts + [cores]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("captures", type=Path, help="captures.h5 (from cca ingest or cca simulate)")
    parser.add_argument("--threads", default=None, help="comma-separated thread counts (default 1, 2, 4, ... cores)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--engine", default="auto")
    parser.add_argument("--iterations", type=int, default=None,
                        help="cap every run at this many passes (the time to a quality reached there)")
    parser.add_argument("--json", type=Path, default=None, help="also write the table here")
    args = parser.parse_args()

    counts = [int(t) for t in args.threads.split(",")] if args.threads else thread_counts(cpu_count())
    keep_freed_memory()   # as the cca command does
    captures = cca.load(args.captures)
    cca.reconstruct(captures, engine=args.engine, iterations=2)  # compile and warm the caches once
    capped_at = {} if args.iterations is None else {"iterations": args.iterations}
    runs: dict[int, list[tuple[float, int, float]]] = {n: [] for n in counts}
    for _ in range(args.repeats):
        for n in counts:  # interleaved, so a slow spell of the machine hits every count
            start = time.perf_counter()
            result = cca.reconstruct(captures, engine=args.engine, threads=n, **capped_at)
            runs[n].append((time.perf_counter() - start, result.iterations, result.seconds))

    rows = []
    for n in counts:
        seconds = statistics.median(s for s, _, _ in runs[n])
        per_pass = statistics.median(s / max(i, 1) for s, i, _ in runs[n])
        loop_per_pass = statistics.median(p / max(i, 1) for _, i, p in runs[n])
        rows.append({"threads": n, "median_s": seconds, "passes": [i for _, i, _ in runs[n]], "s_per_pass": per_pass,
                     "passes_median_s": statistics.median(p for _, _, p in runs[n]),
                     "passes_s_per_pass": loop_per_pass})
    base, base_loop = rows[0]["s_per_pass"], rows[0]["passes_s_per_pass"]
    capped = "" if args.iterations is None else f", at most {args.iterations} passes"
    print(f"{args.captures} on {cpu_count()} cores, engine {args.engine}{capped}, {args.repeats} runs each")
    print(f"{'threads':>7} {'median s':>9} {'s/pass':>8} {'speed-up/pass':>14} {'passes s':>9} {'speed-up':>9}  passes")
    for row in rows:
        row["speedup_per_pass"] = base / row["s_per_pass"]
        row["passes_speedup_per_pass"] = base_loop / row["passes_s_per_pass"]
        print(f"{row['threads']:>7} {row['median_s']:>9.2f} {row['s_per_pass']:>8.4f} {row['speedup_per_pass']:>13.2f}× "
              f"{row['passes_median_s']:>9.2f} {row['passes_speedup_per_pass']:>8.2f}×  {row['passes']}")
    if args.json:
        args.json.write_text(json.dumps({"captures": str(args.captures), "cores": cpu_count(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
