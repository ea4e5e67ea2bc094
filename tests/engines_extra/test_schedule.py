"""Visiting schedule of the sequential engine: centre-out shells of lanes that never touch."""

import numpy as np
import pytest

from cca_cli.engines import passes
from cca_cli.engines.momentum import MAX_LANES, MAX_THREADS, MomentumOptions, SequentialMomentum, lanes_for
from cca_cli.engines.passes import thread_groups
from cca_cli.engines.schedule import build_schedule, shell_sizes, split_disjoint
from cca_cli.sampling.grid import band_layout, square_scan
from cca_cli.sampling.overlap import step_m

from .test_momentum import make_case


def _layout(grid=21, radius=20.9):
    centres = square_scan(grid, step_m(2 * radius, 0.61)).centres_yx_m
    return band_layout(centres, radius, hires_size=512)


def _coverage(layout, captures):
    b = layout.box_size
    mask = np.zeros((layout.hires_size + b, layout.hires_size + b), np.int32)
    for y0, x0 in layout.box_origins[captures]:
        mask[y0:y0 + b, x0:x0 + b] = 1
    return mask


def test_split_keeps_boxes_on_their_side_of_the_line():
    starts = np.array([0, 10, 20, 30, 40, 50])
    before, after, seam = split_disjoint(starts, 12, np.arange(6))
    assert sorted(np.concatenate([before, after, seam]).tolist()) == list(range(6))
    line_before = (starts[before] + 12).max()
    assert np.all(starts[after] >= line_before)
    assert sorted([len(before), len(after)]) == [2, 3] and seam.tolist() in ([2], [3])


def test_shells_grow_away_from_dc_and_cover_every_capture():
    sizes = shell_sizes(441, 12)
    assert sizes[:6] == [24, 24, 48, 48, 96, 96] and sum(sizes) >= 441


@pytest.mark.parametrize("batch", [1, 5, 12])
def test_schedule_visits_every_capture_once_in_non_overlapping_lanes(batch):
    layout = _layout()
    distances = np.hypot(*layout.centres_px.T)
    schedule = build_schedule(layout.box_origins, layout.box_size, distances, batch)
    assert sorted(schedule.order.tolist()) == list(range(layout.n_images))
    covered = sorted(i for sl in schedule.batches for i in range(sl.start, sl.stop))
    assert covered == list(range(layout.n_images))
    assert all(0 < sl.stop - sl.start <= batch for sl in schedule.batches)
    first_shell = shell_sizes(layout.n_images, batch)[0]
    nearest = np.argsort(distances, kind="stable")[:first_shell]
    assert sorted(schedule.order[:first_shell].tolist()) == sorted(nearest.tolist())
    two_lanes = [phase for phase in schedule.phases if len(phase.lanes) == 2]
    assert len(two_lanes) >= 2
    for phase in two_lanes:
        masks = [_coverage(layout, schedule.order[[i for sl in lane for i in range(sl.start, sl.stop)]])
                 for lane in phase.lanes]
        assert not np.any(masks[0] & masks[1])
    # Side-by-side lanes carry nearly all the work: the phases' critical path is close to half of it.
    critical = sum(max(sum(sl.stop - sl.start for sl in lane) for lane in phase.lanes) if len(phase.lanes) == 2
                   else sum(sl.stop - sl.start for sl in phase.lanes[0]) / 2 for phase in schedule.phases)
    assert critical <= 0.56 * layout.n_images


def test_two_threads_give_the_one_thread_result():
    problem, *_ = make_case()
    spectra = []
    for threads in (1, 2):
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=4, tol=0, threads=threads))
        assert any(len(phase.lanes) == 2 for phase in engine._schedule.phases)
        for _ in range(4):
            engine.update()
        engine.close()
        spectra.append(engine.spectrum().copy())
    np.testing.assert_allclose(spectra[1], spectra[0], atol=1e-5 * np.abs(spectra[0]).max())


@pytest.mark.parametrize("lanes", [4, 8])
def test_deeper_splits_give_more_lanes_that_never_touch(lanes):
    layout = _layout()
    distances = np.hypot(*layout.centres_px.T)
    schedule = build_schedule(layout.box_origins, layout.box_size, distances, 6, lanes=lanes)
    assert sorted(schedule.order.tolist()) == list(range(layout.n_images))
    assert max(len(phase.lanes) for phase in schedule.phases) == lanes
    for phase in schedule.phases:
        masks = [_coverage(layout, schedule.order[[i for sl in lane for i in range(sl.start, sl.stop)]])
                 for lane in phase.lanes]
        assert not np.any(np.sum(masks, axis=0) > 1)
    # With lanes side by side, the critical path of a pass shrinks with their number.
    critical = sum(max(sum(sl.stop - sl.start for sl in lane) for lane in phase.lanes) for phase in schedule.phases)
    assert critical <= (0.42 if lanes == 4 else 0.32) * layout.n_images   # 0.38 and 0.29 here; two lanes: 0.52


def test_four_threads_agree_with_two_and_repeat_bit_for_bit():
    problem, *_ = make_case()
    spectra = {}
    for threads in (2, 4, 4):
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=6, tol=0, threads=threads))
        for _ in range(6):
            engine.update()
        engine.close()
        spectra.setdefault(threads, []).append(engine.spectrum().copy())
    np.testing.assert_array_equal(spectra[4][0], spectra[4][1])
    np.testing.assert_allclose(spectra[4][0], spectra[2][0], atol=2e-2 * np.abs(spectra[2][0]).max())


def test_thread_groups_share_threads_by_lane_size():
    assert thread_groups([25, 30], 3) == [[0], [1, 2]]
    assert thread_groups([78, 75], 4) == [[0, 1], [2, 3]]
    assert thread_groups([17, 6, 11], 8) == [[0, 1, 2, 3], [4, 5], [6, 7]]
    assert thread_groups([2, 1], 8) == [[0], [1]]               # each thread keeps PART_CAPTURES (2) or more
    assert thread_groups([2, 1], 8, least=1) == [[0, 1], [2]]
    assert thread_groups([5], 1) == [[0]]
    with pytest.raises(ValueError, match="1 to 2 lanes"):
        thread_groups([1, 2, 3], 2)


@pytest.mark.parametrize("pupil", [{}, {"pupil_recovery": "shared", "pupil_model": "full"}])
def test_three_threads_split_the_lanes_batches_and_give_the_two_thread_result(pupil, monkeypatch):
    problem, *_ = make_case()
    grouped = []
    original = passes._PassRun.grouped_lanes
    monkeypatch.setattr(passes._PassRun, "grouped_lanes",
                        lambda self, lanes: grouped.append(len(lanes)) or original(self, lanes))
    spectra = {}
    for threads in (2, 3, 3):
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=4, tol=0, threads=threads, **pupil))
        for _ in range(4):
            engine.update()
        engine.close()
        spectra.setdefault(threads, []).append(engine.spectrum().copy())
    assert grouped and set(grouped) == {2}   # three threads, two lanes: one lane split in two
    np.testing.assert_array_equal(spectra[3][0], spectra[3][1])
    # the same visiting order as two threads; only the pupil sums' partial sums are grouped otherwise
    np.testing.assert_allclose(spectra[3][0], spectra[2][0], rtol=0, atol=1e-5 * np.abs(spectra[2][0]).max())


def test_threads_beyond_the_cap_run_as_the_cap():
    """More threads than MAX_THREADS (those the passes gain from) give MAX_THREADS's result, bit for bit."""
    problem, *_ = make_case()
    assert lanes_for(1) == lanes_for(2) == 2 and lanes_for(4) == 4 and lanes_for(8) == lanes_for(16) == MAX_LANES
    spectra = {}
    for threads in (MAX_THREADS, 16, 16):
        engine = SequentialMomentum(problem, MomentumOptions(max_iterations=3, tol=0, threads=threads))
        assert engine.passes.threads == min(MAX_THREADS, problem.model.n_images)
        for _ in range(3):
            engine.update()
        engine.close()
        spectra.setdefault(threads, []).append(engine.spectrum().copy())
    np.testing.assert_array_equal(spectra[16][0], spectra[16][1])
    np.testing.assert_array_equal(spectra[16][0], spectra[MAX_THREADS][0])


def test_unnamed_threads_run_as_two_on_a_many_core_machine(monkeypatch):
    """Options naming no threads take DEFAULT_THREADS on 16 cores: the result of ``threads: 2``, bit for bit."""
    from cca_cli.engines.momentum import DEFAULT_THREADS
    from cca_cli.optics import fft

    problem, *_ = make_case()
    spectra = {}
    for threads in (None, DEFAULT_THREADS):
        with monkeypatch.context() as patch:
            patch.setattr(fft, "default_threads", lambda: 16)
            engine = SequentialMomentum(problem, MomentumOptions(max_iterations=3, tol=0, threads=threads))
        assert engine.passes.threads == DEFAULT_THREADS == 2
        for _ in range(3):
            engine.update()
        engine.close()
        spectra[threads] = engine.spectrum().copy()
    np.testing.assert_array_equal(spectra[None], spectra[DEFAULT_THREADS])
