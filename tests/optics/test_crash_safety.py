"""Bad calls into compiled code and raw FFTW plans raise instead of crashing the interpreter.

Each case once ended in a segfault or a glibc abort. They run in one child process, so a
crash fails the cases from the one that crashed on instead of killing pytest; the numpy
kernels' answers to the same calls are checked here directly.
"""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from cca_cli.optics import fft, kernels

#: Runs every case in order and prints "result NAME ERROR-TYPE: message" after each.
CHILD = textwrap.dedent('''
    import gc, sys, threading
    import numpy as np
    from cca_cli.optics import fft, kernels
    from cca_cli.optics.forward import Workspace

    M, K, b, m = 32, 6, 8, 16
    spectrum = np.zeros((M, M), np.complex64)
    origins = np.full((K, 2), 4, np.int64)
    pupils = np.ones((K, b, b), np.complex64)
    fields = np.zeros((3, m, m), np.complex64)
    amplitudes = np.ones((3, m, m), np.float32)
    cases = {}

    def case(function):
        cases[function.__name__] = function
        return function

    def shifted(row, value):
        bad = origins.copy()
        bad[row] = value
        return bad

    @case
    def place_box_far_outside_the_spectrum():
        kernels.place_boxes(spectrum, shifted(1, 10**9), pupils, fields, 0)

    @case
    def place_box_at_a_negative_origin():
        kernels.place_boxes(spectrum, shifted(2, -3), pupils, fields, 0)

    @case
    def scatter_box_one_pixel_past_the_edge():
        kernels.scatter_boxes(fields, shifted(0, M - b + 1), pupils, spectrum, 0)

    @case
    def place_pupils_larger_than_the_fields():
        kernels.place_boxes(spectrum, origins, np.ones((K, m + 2, m + 2), np.complex64), fields, 0)

    @case
    def scatter_captures_beyond_the_last():
        kernels.scatter_boxes(fields, origins, pupils, spectrum, K - 1)

    @case
    def scatter_complex128_fields():
        kernels.scatter_boxes(fields.astype(np.complex128), origins, pupils, spectrum, 0)

    @case
    def project_onto_fewer_amplitudes():
        kernels.project_magnitudes(fields, amplitudes[:1], np.zeros((2, 3, m, m), np.float32))

    @case
    def magnitude_step_with_weights_of_another_shape():
        kernels.magnitude_step(fields, amplitudes, np.zeros((3, m, m), np.float32),
                               weights=np.ones((3, m, m - 1), np.float32))

    @case
    def magnitude_step_of_complex128_fields():
        kernels.magnitude_step(fields.astype(np.complex128), amplitudes, np.zeros((3, m, m), np.float32))

    @case
    def tikhonov_with_a_smaller_normal():
        kernels.tikhonov_update(spectrum.copy(), np.ones((M // 2, M), np.float32), spectrum)

    @case
    def momentum_with_a_complex128_velocity():
        kernels.momentum_step(spectrum.copy(), spectrum.copy(), spectrum.astype(np.complex128), 0.5)

    discs = np.ones((K, b, b), np.float32)

    def map_pupil_factors(maps_index, batches, factors=None):
        kernels.map_pupil_factors(discs, pupils[:1].copy(), maps_index, origins, np.array(batches, np.int64),
                                  alpha=0.1, tau=1e-3, scale=1.0, forward_scale=1.0,
                                  coverage=np.zeros((M, M), np.float32), pupils=pupils.copy(), boxes=pupils.copy(),
                                  factors=pupils.copy() if factors is None else factors)

    @case
    def map_pupil_factors_naming_a_map_that_does_not_exist():
        map_pupil_factors(np.full(K, 1, np.int64), [[0, K]])

    @case
    def map_pupil_factors_beyond_the_last_capture():
        map_pupil_factors(np.zeros(K, np.int64), [[0, K + 1]])

    @case
    def map_pupil_factors_into_strided_factors():
        map_pupil_factors(np.zeros(K, np.int64), [[0, K]], np.empty((K, b, 2 * b), np.complex64)[:, :, ::2])

    @case
    def rpie_factors_into_a_strided_out():
        out = np.empty((K, b, 2 * b), np.complex64)[:, :, ::2]
        kernels.rpie_factors(pupils, origins, np.array([[0, K]], np.int64), alpha=0.1, tau=1e-3, scale=1.0,
                             coverage=np.zeros((M, M), np.float32), out=out)

    workspace = Workspace(4, m, threads=1, band=(m // 2 - b // 2, m // 2 + b // 2), effort="estimate")
    raw = workspace.box_fft.raw_plans()
    lane_amplitudes = np.ones((K, m, m), np.float32)

    def lane(batches, lane_origins=origins, lane_fields=None, plans=None, boxes=None, **options):
        return kernels.sequential_lane(raw if plans is None else plans, np.array(batches, np.int64), spectrum,
                                       lane_origins, pupils, pupils, workspace.fields if lane_fields is None
                                       else lane_fields, lane_amplitudes, None, 1e-6, boxes=boxes, **options)

    if kernels.can_fuse_lanes(raw):
        @case
        def lane_batch_larger_than_its_boxes():
            lane([[0, 6]], boxes=np.empty((4, b, b), np.complex64))

        @case
        def lane_boxes_of_another_size():
            lane([[0, 2]], boxes=np.empty((4, b + 1, b), np.complex64))

        @case
        def lane_chunk_of_zero():
            lane([[0, 2]], chunk=0)

        @case
        def lane_leaving_two_batches_unscattered():
            lane([[0, 2], [2, 4]], scatter=False, boxes=np.empty((4, b, b), np.complex64))

        @case
        def lane_left_unscattered_without_boxes():
            lane([[0, 2]], scatter=False)

        @case
        def lane_of_a_huge_batch_allocates_nothing_first():
            lane([[0, 10 ** 12]])

        @case
        def lane_batch_beyond_the_last_capture():
            lane([[4, 7]])

        @case
        def lane_box_outside_the_spectrum_runs_nothing():
            before = spectrum.copy()
            try:
                lane([[0, 2], [2, 4]], lane_origins=shifted(3, M))
            finally:
                assert np.array_equal(spectrum, before), "the lane ran batches before refusing"

        @case
        def lane_on_another_buffer_than_the_planned_one():
            lane([[0, 2]], lane_fields=fft.zeros((4, m, m)))

        def lane_with_sums(sums):
            return kernels.sequential_lane(raw, np.array([[0, 2]], np.int64), spectrum, origins, pupils, pupils,
                                           workspace.fields, lane_amplitudes, None, 1e-6, pupil_sums=sums)

        @case
        def lane_pupil_sums_of_too_few_discs():
            lane_with_sums((discs[:2], np.zeros(K, np.int64), np.zeros((1, b, b), np.complex128),
                            np.zeros((1, b, b))))

        def map_parts(map_index=None):
            return kernels.MapPupils(discs, pupils[:1].copy(), np.zeros(K, np.int64) if map_index is None
                                     else map_index, forward_scale=1.0, alpha=0.1, tau=1e-3, scale=1.0)

        def map_lane(parts, coverage=None, lane_pupils=None, lane_origins=origins, batches=((0, 2),)):
            return kernels.sequential_lane(raw, np.array(batches, np.int64), spectrum, lane_origins, lane_pupils,
                                           lane_pupils, workspace.fields, lane_amplitudes, None, 1e-6,
                                           map_pupils=parts,
                                           coverage=np.zeros((M, M), np.float32) if coverage is None else coverage)

        def map_scatter(parts, boxes, scatter_origins=origins, batch=(0, 2), start=0):
            kernels.scatter_map_boxes(boxes, scatter_origins, parts, np.zeros((M, M), np.float32), spectrum, batch,
                                      start)

        @case
        def map_pupils_naming_a_map_that_does_not_exist():
            map_lane(map_parts(np.full(K, 1, np.int64)))

        @case
        def map_lane_with_a_coverage_of_another_shape():
            map_lane(map_parts(), coverage=np.zeros((M, M - 1), np.float32))

        @case
        def map_lane_given_pupils_too():
            map_lane(map_parts(), lane_pupils=pupils)

        @case
        def map_lane_box_outside_the_spectrum_runs_nothing():
            before = spectrum.copy()
            try:
                map_lane(map_parts(), lane_origins=shifted(3, M), batches=((0, 2), (2, 4)))
            finally:
                assert np.array_equal(spectrum, before), "the lane ran batches before refusing"

        @case
        def map_pupils_whose_index_changed_after_they_were_made():
            map_index = np.zeros(K, np.int64)
            parts = map_parts(map_index)
            map_index[:] = 10**9
            map_scatter(parts, np.zeros((2, b, b), np.complex64))

        @case
        def map_scatter_of_whole_fields():
            map_scatter(map_parts(), np.zeros((2, m, m), np.complex64))

        @case
        def map_scatter_without_origins():
            map_scatter(map_parts(), np.zeros((2, b, b), np.complex64), scatter_origins=None)

        @case
        def map_scatter_boxes_outside_their_batch():
            map_scatter(map_parts(), np.zeros((3, b, b), np.complex64), batch=(0, 4), start=2)

        @case
        def lane_pupil_sums_naming_a_pupil_that_does_not_exist():
            lane_with_sums((discs, np.full(K, 3, np.int64), np.zeros((1, b, b), np.complex128), np.zeros((1, b, b))))

        @case
        def lane_pupil_sums_in_single_precision():
            lane_with_sums((discs, np.zeros(K, np.int64), np.zeros((1, b, b), np.complex64), np.zeros((1, b, b))))

        @case
        def raw_plans_of_a_collected_transform_still_run():
            plans = fft.BandedFFT2(fft.zeros((2, m, m)), 4, 12, threads=1).raw_plans()
            gc.collect()
            data = np.zeros((2, m, m), np.complex64)
            data[:, 4:12, 2:9] = 1 + 2j
            plans.buffer[...] = data
            plans.execute(2, 0)
            plans.execute(2, 1)
            assert np.allclose(plans.buffer, np.fft.ifft2(data) * m * m, atol=1e-3)

        @case
        def raw_plans_released_refuse_to_run():
            plans = fft.BandedFFT2(fft.zeros((2, m, m)), 4, 12, threads=1).raw_plans()
            plans.release()
            plans.execute(2, 0)

        @case
        def lane_after_the_workspace_was_closed():
            lane([[0, 2]])  # runs
            workspace.close()
            lane([[0, 2]])

    @case
    def threads_planning_at_once_all_get_working_plans():
        # Two sweep points in one threaded worker plan at once; FFTW's planner is not thread-safe.
        errors = []

        def plan_and_check(seed):
            rng = np.random.default_rng(seed)
            for size in range(8, 36, 4):
                transform = fft.BandedFFT2(fft.zeros((8, size, size)), 2, size - 2, threads=1, effort="estimate")
                raw_plans = transform.raw_plans()
                data = np.zeros((8, size, size), np.complex64)
                data[:, 2:size - 2] = rng.standard_normal((8, size - 4, size))
                transform.buffer[...] = data
                transform.inverse(8)
                if not np.allclose(transform.buffer, np.fft.ifft2(data) * size * size, atol=1e-2):
                    errors.append(size)
                del transform, raw_plans

        threads = [threading.Thread(target=plan_and_check, args=(seed,)) for seed in range(6)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert not errors, errors

    for name, function in cases.items():
        print("start", name, flush=True)
        try:
            function()
            print("result", name, "none", flush=True)
        except (ValueError, RuntimeError) as error:
            print("result", name, f"{type(error).__name__}: {error}", flush=True)
''')

RAISES = {
    "place_box_far_outside_the_spectrum": ("ValueError", "capture 1 at origin (1000000000, 1000000000)"),
    "place_box_at_a_negative_origin": ("ValueError", "capture 2 at origin (-3, -3) does not lie inside"),
    "scatter_box_one_pixel_past_the_edge": ("ValueError", "capture 0 at origin (25, 25)"),
    "place_pupils_larger_than_the_fields": ("ValueError", "b <= m"),
    "scatter_captures_beyond_the_last": ("ValueError", "captures 5 to 7 are not among the 6"),
    "scatter_complex128_fields": ("ValueError", "fields complex64"),
    "project_onto_fewer_amplitudes": ("ValueError", "amplitudes float32 (1, 16, 16)"),
    "magnitude_step_with_weights_of_another_shape": ("ValueError", "weights float32 (3, 16, 15)"),
    "magnitude_step_of_complex128_fields": ("ValueError", "fields complex128"),
    "tikhonov_with_a_smaller_normal": ("ValueError", "inverse_normal float32 (16, 32)"),
    "momentum_with_a_complex128_velocity": ("ValueError", "velocity complex128"),
    "map_pupil_factors_naming_a_map_that_does_not_exist": ("ValueError", "index must name maps 0 … 0"),
    "map_pupil_factors_beyond_the_last_capture": ("ValueError", "batches must be [start, stop) rows within the 6"),
    "map_pupil_factors_into_strided_factors": ("ValueError", "factors must be C-contiguous"),
    "rpie_factors_into_a_strided_out": ("ValueError", "coverage and out must be C-contiguous"),
    "lane_batch_larger_than_its_boxes": ("ValueError", "batch 0 [0, 6) must lie within the 6 captures and "
                                                       "hold at most 4 (the boxes' capacity)"),
    "lane_boxes_of_another_size": ("ValueError", "boxes must be a C-contiguous complex64 (n, 8, 8) array"),
    "lane_chunk_of_zero": ("ValueError", "chunk must be at least 1"),
    "lane_leaving_two_batches_unscattered": ("ValueError", "scatter=False runs exactly one batch, got 2"),
    "lane_left_unscattered_without_boxes": ("ValueError", "scatter=False leaves the update in boxes: pass boxes"),
    "lane_of_a_huge_batch_allocates_nothing_first": ("ValueError", "batch 0 [0, 1000000000000) must lie within the "
                                                                   "6 captures"),
    "lane_batch_beyond_the_last_capture": ("ValueError", "batch 0 [4, 7) must lie within the 6 captures"),
    "lane_box_outside_the_spectrum_runs_nothing": ("ValueError", "capture 3 at origin (32, 32)"),
    "lane_on_another_buffer_than_the_planned_one": ("ValueError", "buffer these FFTW plans were made for"),
    "lane_pupil_sums_of_too_few_discs": ("ValueError", "discs must be a C-contiguous float32 array (6, 8, 8)"),
    "lane_pupil_sums_naming_a_pupil_that_does_not_exist": ("ValueError", "index must name pupils 0 … 0"),
    "lane_pupil_sums_in_single_precision": ("ValueError", "numerator must be a C-contiguous complex128 array"),
    "map_pupils_naming_a_map_that_does_not_exist": ("ValueError", "MapPupils: index must name maps 0 … 0"),
    "map_lane_with_a_coverage_of_another_shape": ("ValueError", "coverage must be a C-contiguous float32 (32, 32)"),
    "map_lane_given_pupils_too": ("ValueError", "pass None for both"),
    "map_lane_box_outside_the_spectrum_runs_nothing": ("ValueError", "capture 3 at origin (32, 32)"),
    "map_pupils_whose_index_changed_after_they_were_made": ("ValueError", "scatter_map_boxes: index must name "
                                                                           "maps 0 … 0"),
    "map_scatter_of_whole_fields": ("ValueError", "boxes must be (k, 8, 8) update boxes, got (2, 16, 16)"),
    "map_scatter_without_origins": ("ValueError", "origins must be a 2-d int64 array"),
    "map_scatter_boxes_outside_their_batch": ("ValueError", "captures 2 to 4 must lie in the batch [0, 4)"),
    "raw_plans_of_a_collected_transform_still_run": ("none", ""),
    "raw_plans_released_refuse_to_run": ("RuntimeError", "released"),
    "lane_after_the_workspace_was_closed": ("RuntimeError", "released"),
    "threads_planning_at_once_all_get_working_plans": ("none", ""),
}
NEEDS_RAW = [name for name in RAISES if name.startswith(("lane_", "raw_", "map_"))]


@pytest.fixture(scope="module")
def child(tmp_path_factory):
    """The child's outcome per case, and its exit status and stderr for crash reports."""
    env = dict(os.environ, CCA_CACHE_DIR=str(tmp_path_factory.mktemp("fftw-cache")))  # plan afresh
    run = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=300, env=env)
    outcomes = {}
    for line in run.stdout.splitlines():
        if line.startswith("result "):
            _, name, outcome = line.split(" ", 2)
            outcomes[name] = outcome
    started = [line.split()[1] for line in run.stdout.splitlines() if line.startswith("start ")]
    return outcomes, run.returncode, run.stderr[-2000:], started


@pytest.mark.parametrize("name", list(RAISES))
def test_bad_call_raises_instead_of_crashing(child, name):
    outcomes, returncode, stderr, started = child
    if name in NEEDS_RAW and not (kernels.HAVE_NUMBA and fft.raw_fftw_available()):
        pytest.skip("needs numba and raw FFTW plans")
    if name not in outcomes:
        crashed = started[-1] if started else "before the first case"
        pytest.fail(f"the child process ended with status {returncode} during {crashed}: {stderr}")
    kind, message = RAISES[name]
    assert outcomes[name].startswith(kind), outcomes[name]
    assert message in outcomes[name]
    assert returncode == 0, stderr


def test_numpy_kernels_refuse_the_same_calls():
    spectrum = np.zeros((32, 32), np.complex64)
    origins = np.full((6, 2), 4, np.int64)
    pupils = np.ones((6, 8, 8), np.complex64)
    fields = np.zeros((3, 16, 16), np.complex64)
    with kernels.use_kernels("numpy"):
        bad = origins.copy()
        bad[1] = (-1, 4)
        with pytest.raises(ValueError, match=r"capture 1 at origin \(-1, 4\)"):
            kernels.place_boxes(spectrum, bad, pupils, fields, 0)
        bad[1] = (4, 25)
        with pytest.raises(ValueError, match=r"capture 1 at origin \(4, 25\)"):
            kernels.scatter_boxes(fields, bad, pupils, spectrum, 0)
        with pytest.raises(ValueError, match="captures 4 to 6"):
            kernels.place_boxes(spectrum, origins, pupils, fields, 4)
        with pytest.raises(ValueError, match="arrays of one shape"):
            kernels.project_magnitudes(fields, np.ones((3, 16, 15), np.float32), np.zeros((2, 3, 16, 16)))
        with pytest.raises(ValueError, match="arrays of one shape"):
            kernels.tikhonov_update(spectrum.copy(), np.ones((32, 32), np.float64), spectrum)
