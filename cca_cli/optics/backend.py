"""Where the batched engines' arrays live: numpy on the CPU, CuPy on a CUDA GPU.

The batched engines (:mod:`cca_cli.engines.batched`) are written against an
array module ``xp`` and take it from here; nothing else in cca needs CuPy, and
CuPy is imported only when a device other than ``cpu`` is asked for. As in
SigPy's backend, :func:`get_array_module` tells from an array which module owns
it, :func:`to_device` and :func:`to_host` move arrays, and the few calls whose
spelling differs between numpy and CuPy (batched FFTs, scatter-add) are
written once here.

Devices
-------
``cpu``: the CPU engines, exactly as without this module. ``cuda``: the
batched engines on the current CUDA GPU (the first, unless :func:`using_gpu`
names another: a local Dask worker of a tiled run takes one of several,
:func:`gpu_for_worker`); an error naming the fix when CuPy or a GPU is missing.
``auto``: ``cuda`` when CuPy and a GPU are there, else ``cpu``.
"""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from cca_cli.optics.fft import _scipy_fft

__all__ = ["DEVICES", "GPU_INSTALL", "DeviceStatus", "DeviceUnavailable", "cupy_module", "device_status",
           "resolve_device", "gpu_count", "gpu_for_worker", "using_gpu", "array_module", "get_array_module", "to_device", "to_host", "fft2", "ifft2",
           "PlannedFFT2", "GraphedWork", "scatter_add", "synchronize"]

#: What ``reconstruct.device`` (``--device``, ``device=``) takes.
DEVICES = ("auto", "cpu", "cuda")
#: How to get CuPy for cca.
GPU_INSTALL = "pip install 'cca[gpu]'"


class DeviceUnavailable(ValueError):
    """``device: cuda`` was asked for where CuPy or a CUDA GPU is missing (the message says which and the fix)."""


@dataclass(frozen=True)
class DeviceStatus:
    """What this process can compute on.

    Attributes
    ----------
    cuda : bool
        Whether CuPy imports and sees at least one CUDA GPU.
    summary : str
        One line: ``CuPy 13.3.0, GPU 0: NVIDIA H100 80GB HBM3 (79.1 GiB)``, or why there is none
        (``cpu only: CuPy not installed``).
    """

    cuda: bool
    summary: str


@functools.lru_cache(maxsize=1)
def cupy_module() -> ModuleType | None:
    """CuPy, imported on first use, or None when it is not installed (or fails to import)."""
    try:
        import cupy
    except Exception:  # noqa: BLE001 - a broken CUDA install raises all sorts; the status says why
        return None
    return cupy


@functools.lru_cache(maxsize=1)
def device_status() -> DeviceStatus:
    """Whether a CUDA GPU can be used, with CuPy's version and the GPU's name (asked once per process)."""
    cupy = cupy_module()
    if cupy is None:
        return DeviceStatus(False, "cpu only: CuPy not installed")
    try:
        count = cupy.cuda.runtime.getDeviceCount()
    except Exception as exc:  # noqa: BLE001 - no driver, no device: CuPy raises its own CUDA errors
        return DeviceStatus(False, f"cpu only: CuPy {cupy.__version__} is installed but finds no CUDA GPU "
                                   f"({_first_line(exc)})")
    if count < 1:
        return DeviceStatus(False, f"cpu only: CuPy {cupy.__version__} is installed but finds no CUDA GPU")
    try:
        properties = cupy.cuda.runtime.getDeviceProperties(0)
        name = properties["name"].decode() if isinstance(properties["name"], bytes) else str(properties["name"])
        memory = properties["totalGlobalMem"] / 2 ** 30
    except Exception as exc:  # noqa: BLE001
        return DeviceStatus(False, f"cpu only: CuPy {cupy.__version__} cannot use GPU 0 ({_first_line(exc)})")
    more = f" (+{count - 1} more)" if count > 1 else ""
    return DeviceStatus(True, f"CuPy {cupy.__version__}, GPU 0: {name} ({memory:.1f} GiB){more}")


def _first_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def resolve_device(device: str, *, usable: bool = True) -> str:
    """The device a run uses: ``cpu`` or ``cuda``.

    Parameters
    ----------
    device : {"auto", "cpu", "cuda"}
    usable : bool
        Whether the run's engine and options can run on the GPU at all; ``auto`` then stays on
        the CPU (``cuda`` is refused by the engine itself, naming the option).

    Returns
    -------
    str
        ``cpu`` for ``cpu``; ``cuda`` for ``cuda``; for ``auto``, ``cuda`` when CuPy and a GPU are
        there (and ``usable``), else ``cpu``.

    Raises
    ------
    DeviceUnavailable
        ``cuda`` without CuPy or without a GPU (one line, with the fix).
    ValueError
        An unknown device name.
    """
    if device not in DEVICES:
        raise ValueError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device == "cpu":
        return "cpu"
    status = device_status()
    if device == "auto":
        return "cuda" if status.cuda and usable else "cpu"
    if not status.cuda:
        reason = status.summary.removeprefix("cpu only: ")
        raise DeviceUnavailable(f"device cuda needs CuPy and a CUDA GPU, but {reason}: install CuPy with "
                                f"{GPU_INSTALL} on a machine with an NVIDIA GPU, or use device cpu")
    return "cuda"


def gpu_count() -> int:
    """CUDA GPUs CuPy sees (0 without CuPy, a driver or a GPU)."""
    cupy = cupy_module()
    if cupy is None:
        return 0
    try:
        return max(0, int(cupy.cuda.runtime.getDeviceCount()))
    except Exception:  # noqa: BLE001 - no driver, no device: CuPy raises its own CUDA errors
        return 0


def gpu_memory_bytes() -> int:
    """Memory of the smallest CUDA GPU CuPy sees, in bytes (0 without CuPy, a driver or a GPU)."""
    cupy = cupy_module()
    if cupy is None:
        return 0
    try:
        count = int(cupy.cuda.runtime.getDeviceCount())
        return min((int(cupy.cuda.runtime.getDeviceProperties(i)["totalGlobalMem"]) for i in range(count)),
                   default=0)
    except Exception:  # noqa: BLE001 - no driver, no device: CuPy raises its own CUDA errors
        return 0


def gpu_for_worker(number: int, count: int) -> int:
    """The GPU (0 … count − 1) the local worker numbered ``number`` takes: workers spread over the GPUs."""
    if count < 1:
        raise ValueError(f"count must be ≥ 1, got {count}")
    return int(number) % count


@contextlib.contextmanager
def using_gpu(index: int):
    """Make GPU ``index`` the current device of this thread while the block runs (nothing without CuPy)."""
    cupy = cupy_module()
    if cupy is None:
        yield
        return
    with cupy.cuda.Device(int(index)):
        yield


def array_module(device: str) -> ModuleType:
    """numpy for ``cpu``, CuPy for ``cuda`` (a resolved device, see :func:`resolve_device`)."""
    if device == "cpu":
        return np
    if device == "cuda":
        cupy = cupy_module()
        if cupy is None:
            raise DeviceUnavailable(f"device cuda needs CuPy, which is not installed: {GPU_INSTALL}, or use device cpu")
        return cupy
    raise ValueError(f"device must be cpu or cuda here, got {device!r}")


def get_array_module(array) -> ModuleType:
    """The module that owns ``array``: CuPy for a CuPy array, numpy for anything else."""
    cupy = cupy_module() if type(array).__module__.startswith("cupy") else None
    return cupy if cupy is not None else np


def to_device(array, xp: ModuleType, dtype=None):
    """``array`` as an array of ``xp`` (copied to the GPU for CuPy; not copied when it is one already)."""
    return xp.asarray(array, dtype=dtype)


def to_host(array) -> np.ndarray:
    """``array`` as a numpy array (copied from the GPU for a CuPy array)."""
    if get_array_module(array) is np:
        return np.asarray(array)
    return array.get()


def fft2(xp: ModuleType, array):
    """Unnormalised forward 2-D FFT over the last two axes, batched over the leading ones; keeps complex64.

    numpy arrays go through ``scipy.fft`` (single precision, all cores), CuPy arrays through cuFFT; either
    may overwrite ``array``.
    """
    if xp is np:
        return _scipy_fft().fft2(array, norm="backward", overwrite_x=True, workers=_workers())
    return _cupy_fft().fft2(array, norm="backward", overwrite_x=True)


def ifft2(xp: ModuleType, array):
    """Unnormalised inverse 2-D FFT over the last two axes (``Σ X exp(+2πi k n / m)``), batched; keeps complex64.

    May overwrite ``array``.
    """
    if xp is np:
        return _scipy_fft().ifft2(array, norm="forward", overwrite_x=True, workers=_workers())
    return _cupy_fft().ifft2(array, norm="forward", overwrite_x=True)


class PlannedFFT2:
    """Unnormalised in-place 2-D FFTs of batches (as :func:`fft2` and :func:`ifft2`) with plans kept per shape.

    On a GPU a call of :func:`fft2` spends tens of microseconds in CuPy's plan lookup and checks,
    about as long as the transform of a small batch itself. This keeps one cuFFT plan per array shape
    and runs it on the array directly (the plan CuPy's own call would make, so the same results).
    Arrays it cannot run in place (not C-contiguous complex64), and numpy arrays, go through
    :func:`fft2` / :func:`ifft2`.

    Parameters
    ----------
    xp : module
        numpy or CuPy.
    """

    def __init__(self, xp: ModuleType):
        self.xp = xp
        self._plans: dict[tuple[int, ...], object] = {}

    def forward(self, array):
        """``fft2(array)``, in place where it can be."""
        return self._run(array, True)

    def inverse(self, array):
        """``ifft2(array)``, in place where it can be."""
        return self._run(array, False)

    def _run(self, array, forward: bool):
        xp = self.xp
        if xp is np or array.dtype != np.complex64 or not array.flags.c_contiguous or array.ndim < 2 or not array.size:
            return fft2(xp, array) if forward else ifft2(xp, array)
        plan = self._plans.get(array.shape)
        if plan is None:
            from cupyx.scipy.fftpack import get_fft_plan

            plan = self._plans[array.shape] = get_fft_plan(array, axes=(-2, -1), value_type="C2C")
        cufft = xp.cuda.cufft
        plan.fft(array, array, cufft.CUFFT_FORWARD if forward else cufft.CUFFT_INVERSE)
        return array


#: Array modules on which a CUDA graph recording failed in this process (later work is not recorded).
_RECORDING_FAILED: set = set()


class GraphedWork:
    """A function that only queues GPU work, replayed as one CUDA graph after its first two calls.

    A batched pass is hundreds of small launches, each costing more Python and driver time than
    arithmetic. The first call runs ``work`` as it is (kernels compile, FFT plans are made). The
    second records its launches into a CUDA graph (CuPy's stream capture) and launches the graph;
    later calls launch the graph only: no Python, one launch.

    A graph replays its launches on the memory they were recorded with, so ``work`` must read and
    write arrays that stay where they are while this object lives (update them with
    ``a[...] = b``), and must not wait for the GPU (no ``float(array)``, no copy to the host).
    What ``work`` allocates while it is recorded comes from a memory pool of this object's own,
    kept as long as the graph, so nothing else is ever given that memory. The value ``work``
    returned when it was recorded is returned by every launch: device arrays that each launch
    refills (read them before the next call, and not after this object is dropped: their memory
    goes with its pool).

    On numpy, with ``enabled`` False, or once a recording on the same array module has failed in
    this process (one warning naming why), every call runs ``work`` directly.

    Parameters
    ----------
    xp : module
        numpy or CuPy.
    work : callable
        Takes no arguments; queues GPU work on the current stream.
    enabled : bool
        Whether to record a graph at all.
    """

    def __init__(self, xp: ModuleType, work, *, enabled: bool = True):
        self.xp, self._work = xp, work
        self._enabled = enabled and xp is not np and xp not in _RECORDING_FAILED
        self._calls = 0
        self._graph = self._pool = self._result = None

    @property
    def recorded(self) -> bool:
        """Whether calls now launch a recorded graph."""
        return self._graph is not None

    def __call__(self):
        self._calls += 1
        if self._graph is not None:
            self._graph.launch()
            return self._result
        if not self._enabled or self._calls < 2:
            return self._work()
        try:
            self._record()
        except Exception as exc:  # noqa: BLE001 - any capture failure leaves the plain launches, which work
            import warnings

            self._enabled, self._graph, self._pool, self._result = False, None, None, None
            _RECORDING_FAILED.add(self.xp)
            warnings.warn(f"CUDA graph not recorded ({type(exc).__name__}: {_first_line(exc)[:160]}); "
                          "launching each step as it comes", RuntimeWarning, stacklevel=2)
            return self._work()
        self._graph.launch()
        return self._result

    def _record(self) -> None:
        cuda = self.xp.cuda
        pool = cuda.MemoryPool()
        stream = cuda.Stream(non_blocking=True)
        with cuda.using_allocator(pool.malloc), stream:
            stream.begin_capture()
            try:
                result = self._work()
            except BaseException:
                try:
                    stream.end_capture()
                except Exception:  # noqa: BLE001 - the first error is the one to report
                    pass
                raise
            graph = stream.end_capture()
        self._graph, self._pool, self._result = graph, pool, result


def _cupy_fft() -> ModuleType:
    """CuPy's ``scipy.fft``, whose transforms may run in place (``overwrite_x``); ``cupy.fft`` always copies."""
    import cupyx.scipy.fft

    return cupyx.scipy.fft


def _workers() -> int:
    from cca_cli.optics.fft import default_threads

    return default_threads()


def scatter_add(xp: ModuleType, target, flat_index, values) -> None:
    """``target.flat[flat_index] += values``, adding repeated indices up (an unbuffered scatter-add).

    Parameters
    ----------
    xp : module
    target : array, complex64 or float32, C-contiguous
        Receives the sums, in place.
    flat_index : array, int, any shape
        Indices into ``target.ravel()``.
    values : array, shaped as ``flat_index``
    """
    flat = target.reshape(-1)
    index = flat_index.reshape(-1)
    values = values.reshape(-1)
    if xp is np:
        if np.iscomplexobj(flat):
            flat.real += np.bincount(index, weights=values.real, minlength=flat.size).astype(flat.real.dtype)
            flat.imag += np.bincount(index, weights=values.imag, minlength=flat.size).astype(flat.real.dtype)
        else:
            flat += np.bincount(index, weights=values, minlength=flat.size).astype(flat.dtype)
        return
    import cupyx

    if xp.iscomplexobj(flat):  # atomics on the real and imaginary parts
        pairs = flat.view(flat.real.dtype).reshape(-1, 2)
        cupyx.scatter_add(pairs, (index, 0), values.real)
        cupyx.scatter_add(pairs, (index, 1), values.imag)
    else:
        cupyx.scatter_add(flat, index, values)


def synchronize(xp: ModuleType) -> None:
    """Wait for the GPU to finish its queued work (timings); nothing on the CPU."""
    if xp is not np:
        xp.cuda.get_current_stream().synchronize()
