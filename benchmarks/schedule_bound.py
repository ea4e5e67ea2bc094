"""How far the sequential engine's visiting order lets threads share a pass: a count of captures.

The ``momentum`` engine updates the spectrum batch by batch in the phases and lanes of
``cca_cli.engines.schedule.build_schedule``: lanes of a phase never touch, so they run side by
side, and the captures of one batch may be split among threads and added in order
(``cca_cli.engines.passes``). This script builds the schedule of a capture set for each thread
count and batch size the default run goes through, and counts the captures on the longest path
through each phase, with every capture costing 1 of which ``--scatter`` (the in-order addition of a
split batch) runs on one thread. The bound is the captures of a pass over that path: the speed-up
no machine can beat with this order, before memory bandwidth and hand-overs.

Two ways to give threads the lanes of a phase:

* ``dealt``: the lanes, largest first, dealt to the threads in turn (a phase of one lane split
  among all threads) — what cca did before thread groups;
* ``groups``: as above, but a phase with fewer lanes than threads gives each lane a group of
  threads that split each of its batches (``cca_cli.engines.passes.thread_groups``).

Usage::

    cca ingest configs/bloodsmear_green_manifest.yaml -o blood_raw.h5
    python benchmarks/schedule_bound.py blood_raw.h5 --batches 24,48,96,0 --passes 44,6,5,42

Thread counts above ``MAX_THREADS`` (4) count as ``MAX_THREADS``, as the engine runs them.

``--batches`` 0 stands for one batch of every capture (where the default's growing batches end);
``--passes`` weighs the batch sizes by the passes the default run spent at each (the blood smear's
are shown; ``history`` of a recon.h5 does not record them).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cca_cli.engines.momentum import MAX_THREADS, lanes_for
from cca_cli.engines.passes import part_threads, thread_groups
from cca_cli.engines.schedule import Schedule, build_schedule
from cca_cli.io.captures import read_captures
from cca_cli.sampling.grid import band_layout


def _size(lane) -> int:
    return sum(sl.stop - sl.start for sl in lane)


def _split(batch: int, threads: int, scatter: float) -> float:
    """One batch split among ``threads`` as the engine splits it: the largest part, then every part added in order."""
    threads = part_threads(batch, threads)
    return (1 - scatter) * -(-batch // threads) + scatter * batch if threads > 1 else float(batch)


def path_length(schedule: Schedule, threads: int, scatter: float, groups: bool) -> float:
    """Captures on the longest path through a pass's phases with ``threads`` threads."""
    total = 0.0
    for phase in schedule.phases:
        lanes = sorted(phase.lanes, key=_size, reverse=True)
        if threads == 1:
            total += sum(_size(lane) for lane in lanes)
        elif len(lanes) == 1:
            total += sum(_split(sl.stop - sl.start, threads, scatter) for sl in lanes[0])
        elif groups and len(lanes) < threads:
            members = thread_groups([_size(lane) for lane in lanes], threads)
            total += max(sum(_split(sl.stop - sl.start, len(group), scatter) for sl in lane)
                         for lane, group in zip(lanes, members))
        else:
            total += max(sum(_size(lane) for lane in lanes[t::threads]) for t in range(min(threads, len(lanes))))
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("captures", type=Path, help="captures.h5 (from cca ingest or cca simulate)")
    parser.add_argument("--threads", default="1,2,3,4,8", help="comma-separated thread counts")
    parser.add_argument("--batches", default="24,0", help="batch sizes (0: every capture in one batch)")
    parser.add_argument("--passes", default="", help="passes at each batch size (default: one each)")
    parser.add_argument("--scatter", type=float, default=0.14,
                        help="share of a capture's cost in adding its update (0.14: 7.3 of 52 ms a pass, blood "
                             "smear, one thread)")
    args = parser.parse_args()
    captures = read_captures(args.captures)
    geometry = captures.geometry
    layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px,
                         sensor_size=captures.intensity.shape[-1])
    distances = np.hypot(layout.centres_px[:, 0], layout.centres_px[:, 1])
    batches = [int(b) or layout.n_images for b in args.batches.split(",")]
    passes = [int(p) for p in args.passes.split(",")] if args.passes else [1] * len(batches)
    if len(passes) != len(batches):
        raise SystemExit("--passes: one count per --batches entry")
    print(f"{args.captures}: {layout.n_images} captures, box {layout.box_size} px, batches {batches} "
          f"(passes {passes}); captures a pass / longest path, scatter share {args.scatter}")
    print("threads  lanes  dealt  groups")
    for threads in (int(t) for t in args.threads.split(",")):
        used = min(threads, MAX_THREADS)
        lanes = lanes_for(used)
        work = dealt = grouped = 0.0
        for batch, count in zip(batches, passes):
            schedule = build_schedule(layout.box_origins, layout.box_size, distances, batch, lanes=lanes)
            work += count * layout.n_images
            dealt += count * path_length(schedule, used, args.scatter, groups=False)
            grouped += count * path_length(schedule, used, args.scatter, groups=True)
        print(f"{threads:7d}  {lanes:5d}  {work / dealt:4.2f}×  {work / grouped:5.2f}×")


if __name__ == "__main__":
    main()
