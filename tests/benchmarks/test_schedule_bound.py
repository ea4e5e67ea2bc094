"""The schedule-bound count: one thread walks every capture, groups shorten the path where lanes are few."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import schedule_bound  # noqa: E402  (a broken import must fail these tests, not skip them)

from cca_cli.engines.schedule import build_schedule  # noqa: E402
from cca_cli.sampling.grid import band_layout, square_scan  # noqa: E402
from cca_cli.sampling.overlap import step_m  # noqa: E402


def test_groups_shorten_the_longest_path_only_where_threads_outnumber_lanes():
    radius = 20.9
    layout = band_layout(square_scan(15, step_m(2 * radius, 0.61)).centres_yx_m, radius, hires_size=512)
    distances = np.hypot(*layout.centres_px.T)
    schedule = build_schedule(layout.box_origins, layout.box_size, distances, layout.n_images, lanes=2)
    n = layout.n_images
    assert schedule_bound.path_length(schedule, 1, 0.14, groups=True) == n
    two = [schedule_bound.path_length(schedule, 2, 0.14, groups=g) for g in (False, True)]
    assert two[0] == two[1] and n / two[0] > 1.5                     # two threads: two lanes, nothing to group
    dealt, grouped = (schedule_bound.path_length(schedule, 4, 0.14, groups=g) for g in (False, True))
    assert dealt > 0.95 * two[0]                       # dealt lanes leave two of four threads idle (but the core's)
    assert grouped < 0.75 * dealt
