"""The fused CuPy kernels: their reference formulas here, the kernels themselves on a GPU (skipped without one)."""

import numpy as np
import pytest

from cca_cli.engines import fused
from cca_cli.engines.batched import project
from cca_cli.optics import backend


def _random(shape, seed=0):
    rng = np.random.default_rng(seed)
    fields = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    return fields, rng.uniform(0, 2, shape).astype(np.float32), rng.uniform(0.5, 1, shape).astype(np.float32)


@pytest.fixture
def cupy():
    """CuPy on a CUDA GPU (the test is skipped where either is missing)."""
    if not backend.device_status().cuda:
        pytest.skip(f"needs CuPy and a CUDA GPU ({backend.device_status().summary})")
    return backend.cupy_module()


def test_numpy_never_takes_the_fused_path():
    assert fused.available(np) is False


def test_the_self_check_reference_is_the_engine_data_step():
    fields, targets, weights = _random((4, 16, 16))
    expected = fields.copy()
    expected_misfit = float(project(np, expected, targets, weights, 1e-3, keep=False))
    found = fields.copy()
    found_misfit = float(fused._reference_data_step(np, found, targets, weights, 1e-3))
    np.testing.assert_allclose(found, expected, rtol=1e-5, atol=1e-6)
    assert found_misfit == pytest.approx(expected_misfit, rel=1e-5)


@pytest.mark.gpu
@pytest.mark.parametrize("weighted", [False, True])
def test_gpu_fused_kernels_are_the_operations_they_replace(cupy, weighted):
    assert fused.available(cupy)
    fields, targets, weights = _random((24, 144, 144), seed=1)
    weights = weights if weighted else None
    expected = fields.copy()
    expected_misfit = float(project(np, expected, targets, weights, 1e-3, keep=False))
    found = cupy.array(fields)
    misfit = float(fused.data_step(cupy, found, cupy.asarray(targets), None if weights is None else cupy.asarray(weights),
                                   1e-3))
    np.testing.assert_allclose(cupy.asnumpy(found), expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())
    assert misfit == pytest.approx(expected_misfit, rel=1e-5)

    rng = np.random.default_rng(2)
    discs = rng.uniform(0, 1, (24, 104, 104)).astype(np.float32)
    spectrum = (rng.standard_normal((420, 420)) + 1j * rng.standard_normal((420, 420))).astype(np.complex64)
    origins = rng.integers(0, 420 - 104, (24, 2))
    index = ((origins[:, 0, None, None] + np.arange(104)[None, :, None]) * 420
             + origins[:, 1, None, None] + np.arange(104)[None, None, :]).astype(np.int64)
    seen = spectrum.reshape(-1)[index]
    residuals = expected[:, 20:124, 20:124]
    first, power = cupy.zeros((104, 104), cupy.complex128), cupy.zeros((104, 104), cupy.float64)
    fused.add_pupil_sums(cupy, first, power, cupy.asarray(discs), cupy.asarray(spectrum), cupy.asarray(index),
                         cupy.asarray(expected)[:, 20:124, 20:124], 1 / 144)
    lit = (discs * seen).astype(np.complex128)
    want = (np.conj(lit) * residuals).sum(axis=0) / 144
    np.testing.assert_allclose(cupy.asnumpy(first), want, atol=1e-5 * np.abs(want).max())
    np.testing.assert_allclose(cupy.asnumpy(power), np.square(np.abs(lit)).sum(axis=0), rtol=1e-5)

    pupils = (seen * np.exp(1j * discs)).astype(np.complex64)
    placed = fused.box_fields(cupy, cupy.asarray(spectrum), cupy.asarray(index), cupy.asarray(pupils), 144)
    want_fields = np.zeros((24, 144, 144), np.complex64)
    want_fields[:, 20:124, 20:124] = seen * pupils
    np.testing.assert_allclose(cupy.asnumpy(placed), want_fields, rtol=1e-6, atol=1e-6 * np.abs(want_fields).max())

    plan = fused.gather_plan(cupy, cupy.asarray(index))
    sums = []
    for _ in range(2):   # the same terms in the same order: the same bits
        target = cupy.zeros((420, 420), cupy.complex64)
        fused.gather_add(cupy, target, plan, cupy.asarray(expected)[:, 20:124, 20:124], cupy.asarray(pupils))
        sums.append(cupy.asnumpy(target))
    np.testing.assert_array_equal(sums[0], sums[1])
    added = np.zeros(420 * 420, np.complex128)
    np.add.at(added, index.reshape(-1), (residuals.astype(np.complex128) * pupils).reshape(-1))
    np.testing.assert_allclose(sums[0].reshape(-1), added, atol=1e-5 * np.abs(added).max())
    np.testing.assert_allclose(sums[0].reshape(-1), _ordered_sum(index, residuals * pupils, np.zeros(420 * 420)),
                               atol=1e-6 * np.abs(added).max())


@pytest.mark.gpu
def test_gpu_data_step_into_a_buffer_sums_to_the_returned_misfit(cupy):
    fields, targets, weights = _random((10, 32, 32), seed=3)
    summed = cupy.array(fields)
    misfit = float(fused.data_step(cupy, summed, cupy.asarray(targets), cupy.asarray(weights), 1e-3))
    buffer = cupy.zeros((16, 32, 32), cupy.float32)
    kept = cupy.array(fields)
    assert fused.data_step(cupy, kept, cupy.asarray(targets), cupy.asarray(weights), 1e-3, squared=buffer[3:13]) is None
    assert cupy.array_equal(kept, summed)
    assert float(buffer[3:13].sum(dtype=cupy.float64)) == pytest.approx(misfit, rel=1e-6)
    assert not cupy.any(buffer[:3]) and not cupy.any(buffer[13:])
    with pytest.raises(ValueError, match="squared"):
        fused.data_step(cupy, kept, cupy.asarray(targets), None, 1e-3, squared=buffer[:5])


@pytest.mark.gpu
def test_gpu_planned_ffts_are_cupys_ffts(cupy):
    fields, _, _ = _random((7, 48, 48), seed=4)
    planned = backend.PlannedFFT2(cupy)
    for _ in range(2):   # the second time from the kept plan
        for forward, plain in ((True, backend.fft2), (False, backend.ifft2)):
            a = cupy.array(fields)
            out = planned.forward(a) if forward else planned.inverse(a)
            assert out is a   # in place
            assert cupy.array_equal(out, plain(cupy, cupy.array(fields)))
    strided = cupy.array(fields)[:, ::2, ::2]   # not contiguous: the plain call
    assert cupy.array_equal(planned.forward(strided), backend.fft2(cupy, cupy.ascontiguousarray(strided)))


def test_planned_ffts_on_numpy_are_the_plain_ones():
    fields, _, _ = _random((3, 16, 16), seed=5)
    planned = backend.PlannedFFT2(np)
    np.testing.assert_array_equal(planned.forward(fields.copy()), backend.fft2(np, fields.copy()))
    np.testing.assert_array_equal(planned.inverse(fields.copy()), backend.ifft2(np, fields.copy()))


def test_a_cupy_that_cannot_compile_them_runs_the_plain_operations_after_one_warning():
    """available() on a module whose kernels fail to build: False, with one warning naming the reason."""

    class NoCompiler:
        __name__ = "no_compiler"
        float32, float64, complex64, complex128 = np.float32, np.float64, np.complex64, np.complex128
        asarray, array, zeros, empty = staticmethod(np.asarray), staticmethod(np.array), staticmethod(np.zeros), \
            staticmethod(np.empty)

        @staticmethod
        def ElementwiseKernel(*args, **kwargs):
            raise RuntimeError("nvrtc: compilation failed\nsecond line")

    module = NoCompiler()
    with pytest.warns(RuntimeWarning, match=r"fused GPU kernels unavailable \(RuntimeError: nvrtc: compilation "
                                            r"failed\); running each step's operations one by one"):
        assert fused.available(module) is False


# ----------------------------------------------------------------------------- recorded passes (CUDA graphs)
class _FakeCapture:
    """A stand-in for CuPy's stream capture: counts recordings and launches; ``fail`` makes recording raise."""

    def __init__(self, fail: bool = False):
        self.recordings = self.launches = 0
        self.fail = fail
        self.capturing = False
        fake = self

        class Graph:
            def __init__(self, work):
                self.work = work

            def launch(self):
                fake.launches += 1

        class Stream:
            def __init__(self, non_blocking=False):
                pass

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                return False

            def begin_capture(self):
                fake.capturing = True

            def end_capture(self):
                fake.capturing = False
                fake.recordings += 1
                return Graph(None)

        class Pool:
            def malloc(self, size):
                raise AssertionError("not called by the fake")

        class Cuda:
            MemoryPool = Pool

            @staticmethod
            def using_allocator(allocator):
                import contextlib
                return contextlib.nullcontext()

        Cuda.Stream = Stream
        self.cuda = Cuda


def test_graphed_work_runs_twice_then_records_once_and_launches():
    fake = _FakeCapture()
    seen = []

    def work():
        seen.append(fake.capturing)
        return "result"

    graphed = backend.GraphedWork(fake, work)
    assert [graphed() for _ in range(5)] == ["result"] * 5
    # first call plain, second recorded (the work runs once, capturing) and launched, then launches only
    assert seen == [False, True]
    assert fake.recordings == 1 and fake.launches == 4 and graphed.recorded


def test_graphed_work_on_numpy_or_disabled_always_runs_the_work():
    calls = []
    for graphed in (backend.GraphedWork(np, lambda: calls.append(1)),
                    backend.GraphedWork(_FakeCapture(), lambda: calls.append(1), enabled=False)):
        for _ in range(4):
            graphed()
        assert not graphed.recorded
    assert len(calls) == 8


def test_a_failed_recording_warns_once_and_runs_the_work_from_then_on():
    fake = _FakeCapture()
    calls = []

    def work():
        calls.append(fake.capturing)
        if fake.capturing:
            raise RuntimeError("operation not permitted when stream is capturing\nmore")
        return len(calls)

    graphed = backend.GraphedWork(fake, work)
    assert graphed() == 1
    with pytest.warns(RuntimeWarning, match=r"CUDA graph not recorded \(RuntimeError: operation not permitted when "
                                            r"stream is capturing\); launching each step as it comes"):
        assert graphed() == 3   # the failed recording, then the work itself
    assert not fake.capturing   # the capture was ended
    assert graphed() == 4 and not graphed.recorded and fake.launches == 0
    # later work on the same module is not recorded (no second warning); another module still is
    ended = fake.recordings   # the failed capture was ended
    again = backend.GraphedWork(fake, lambda: "plain")
    assert [again() for _ in range(3)] == ["plain"] * 3 and not again.recorded and fake.recordings == ended
    other = _FakeCapture()
    fresh = backend.GraphedWork(other, lambda: "work")
    assert [fresh() for _ in range(3)] == ["work"] * 3 and fresh.recorded


# ----------------------------------------------------------------------------- ordered scatter-add
def _ordered_sum(index, terms, start):
    """``start.flat[index] += terms`` one capture after another in float32 (what the gather kernel does)."""
    out = np.array(start, np.complex64 if np.iscomplexobj(terms) else np.float32).reshape(-1)
    for capture in range(index.shape[0]):   # a capture's own pixels never repeat
        out[index[capture].reshape(-1)] += terms[capture].reshape(-1).astype(out.dtype)
    return out


def test_a_gather_plan_groups_each_target_pixel_s_terms_in_capture_order():
    rng = np.random.default_rng(7)
    origins = rng.integers(0, 9, (6, 2))
    index = ((origins[:, 0, None, None] + np.arange(8)[None, :, None]) * 16
             + origins[:, 1, None, None] + np.arange(8)[None, None, :]).astype(np.int64)
    plan = fused.gather_plan(np, index)
    flat = index.reshape(-1)
    assert np.array_equal(np.sort(plan.order), np.arange(flat.size))     # every box pixel once
    assert np.array_equal(plan.pixels, np.unique(flat))
    assert plan.starts[0] == 0 and plan.starts[-1] == flat.size
    for group, pixel in enumerate(plan.pixels):
        members = plan.order[plan.starts[group]:plan.starts[group + 1]]
        assert np.all(flat[members] == pixel) and np.all(np.diff(members) > 0)   # capture order
    # the kernel's loop, run here: start from the target, add each group's terms in order
    terms = (rng.standard_normal(index.shape) + 1j * rng.standard_normal(index.shape)).astype(np.complex64)
    start = (rng.standard_normal(256) + 1j * rng.standard_normal(256)).astype(np.complex64)
    out = start.copy()
    for group, pixel in enumerate(plan.pixels):
        total = out[pixel]
        for q in plan.order[plan.starts[group]:plan.starts[group + 1]]:
            total = np.complex64(total + terms.reshape(-1)[q])
        out[pixel] = total
    np.testing.assert_array_equal(out, _ordered_sum(index, terms, start))


def test_boxes_of_no_captures_give_an_empty_gather_plan():
    plan = fused.gather_plan(np, np.zeros((0, 4, 4), np.int64))
    assert plan.pixels.size == 0 and list(plan.starts) == [0]
