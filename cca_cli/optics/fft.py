"""The one module that allocates arrays and runs FFTs for the numeric core.

Everything numeric goes through here so that another array backend (for
example CuPy) can replace this module without touching the engines.

Two kinds of transform are offered:

* :func:`fft2c` / :func:`ifft2c`: centred, orthonormal 2-D FFTs over the last
  two axes, batched over any leading axes. Convenient, not for hot loops.
* :class:`InPlaceFFT2`: raw (unnormalised) 2-D FFTs planned once for one
  buffer and executed in place. FFTW (pyfftw) when installed, ``scipy.fft``
  otherwise. Callers fold the normalisation into arrays they multiply anyway.
  FFTW plans are measured once per shape and machine: the wisdom is kept in
  ``$CCA_CACHE_DIR`` (default ``~/.cache/cca``). ``$CCA_FFTW_PLANNING`` sets how
  hard FFTW searches: ``patient`` (default; a second or two per new shape, once,
  and up to a third faster strided transforms), ``measure`` or ``estimate``.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import threading
import weakref

import numpy as np
import scipy.fft

try:  # pragma: no cover - exercised when pyfftw is installed
    import pyfftw

    _HAVE_PYFFTW = True
except ImportError:  # pragma: no cover
    pyfftw = None
    _HAVE_PYFFTW = False

__all__ = [
    "xp",
    "backend_name",
    "use_backend",
    "cpu_count",
    "planning_effort",
    "empty",
    "zeros",
    "fft2",
    "ifft2",
    "fft2c",
    "ifft2c",
    "fourier_resample",
    "InPlaceFFT2",
    "BandedFFT2",
    "fftw_execute",
]

#: Array module used by the numeric core.
xp = np

_backend = "pyfftw" if _HAVE_PYFFTW else "scipy"


def _wisdom_path():
    """Where FFTW plans measured on this machine are kept between runs."""
    from pathlib import Path

    root = os.environ.get("CCA_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "cca")
    return Path(root) / f"fftw-wisdom-{pyfftw.__version__}.pickle"


_wisdom_loaded = False


def _load_wisdom() -> None:
    """Import the saved FFTW wisdom once per process (planning then takes milliseconds)."""
    global _wisdom_loaded
    if _wisdom_loaded:
        return
    _wisdom_loaded = True
    try:
        import pickle

        with open(_wisdom_path(), "rb") as handle:
            pyfftw.import_wisdom(pickle.load(handle))
    except Exception:  # noqa: BLE001
        pass  # no or unreadable cache: plans are measured afresh


def _save_wisdom() -> None:
    """Write the process's FFTW wisdom (atomically, so concurrent workers never see half a file)."""
    try:
        import pickle
        import tempfile

        path = _wisdom_path()
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("wb", dir=path.parent, delete=False, suffix=".tmp") as handle:
            pickle.dump(pyfftw.export_wisdom(), handle)
        os.replace(handle.name, path)
    except OSError:
        pass  # a read-only home only costs planning time


_PLANNING = {"estimate": "FFTW_ESTIMATE", "measure": "FFTW_MEASURE", "patient": "FFTW_PATIENT"}


def planning_effort() -> str:
    """How hard FFTW searches for plans: ``$CCA_FFTW_PLANNING``, default ``"patient"``.

    Raises
    ------
    ValueError
        If the variable names an unknown effort.
    """
    effort = os.environ.get("CCA_FFTW_PLANNING", "patient").strip().lower()
    if effort not in _PLANNING:
        raise ValueError(f"CCA_FFTW_PLANNING={effort!r} is not one of {', '.join(_PLANNING)}; unset it or pick one")
    return effort


def _plan(array, axes, direction, threads, effort=None):
    """An FFTW plan searched for once per shape and machine (wisdom kept in the user cache)."""
    _load_wisdom()
    before = pyfftw.export_wisdom()
    plan = pyfftw.FFTW(array, array, axes=axes, direction=direction,
                       flags=(_PLANNING[effort or planning_effort()], "FFTW_DESTROY_INPUT"), threads=threads)
    if pyfftw.export_wisdom() != before:
        _save_wisdom()
    return plan


def cpu_count() -> int:
    """Cores available to this process."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def backend_name() -> str:
    """Name of the FFT backend in use: ``"pyfftw"`` or ``"scipy"``."""
    return _backend


@contextlib.contextmanager
def use_backend(name: str):
    """Temporarily select the FFT backend (``"pyfftw"`` or ``"scipy"``).

    Raises
    ------
    ValueError
        If the name is unknown or pyfftw is requested but not installed.
    """
    global _backend
    if name not in ("pyfftw", "scipy"):
        raise ValueError(f"unknown FFT backend {name!r}; choose 'pyfftw' or 'scipy'")
    if name == "pyfftw" and not _HAVE_PYFFTW:
        raise ValueError("FFT backend 'pyfftw' requested but pyfftw is not installed")
    previous, _backend = _backend, name
    try:
        yield
    finally:
        _backend = previous


def empty(shape, dtype=np.complex64) -> np.ndarray:
    """Uninitialised array, SIMD-aligned when FFTW is in use."""
    if _backend == "pyfftw":
        return pyfftw.empty_aligned(shape, dtype=dtype)
    return np.empty(shape, dtype=dtype)


def zeros(shape, dtype=np.complex64) -> np.ndarray:
    """Zero-filled array, SIMD-aligned when FFTW is in use."""
    out = empty(shape, dtype)
    out.fill(0)
    return out


def fft2(array, *, workers: int | None = None) -> np.ndarray:
    """Plain (uncentred, unnormalised) 2-D FFT over the last two axes."""
    return scipy.fft.fft2(array, workers=workers or cpu_count())


def ifft2(array, *, workers: int | None = None) -> np.ndarray:
    """Plain (uncentred) inverse 2-D FFT over the last two axes, normalised by 1/n."""
    return scipy.fft.ifft2(array, workers=workers or cpu_count())


def fft2c(array, *, workers: int | None = None) -> np.ndarray:
    """Centred orthonormal 2-D FFT over the last two axes (DC at ``n // 2``)."""
    workers = workers or cpu_count()
    shifted = scipy.fft.ifftshift(array, axes=(-2, -1))
    return scipy.fft.fftshift(scipy.fft.fft2(shifted, norm="ortho", workers=workers), axes=(-2, -1))


def ifft2c(array, *, workers: int | None = None) -> np.ndarray:
    """Centred orthonormal inverse 2-D FFT over the last two axes."""
    workers = workers or cpu_count()
    shifted = scipy.fft.ifftshift(array, axes=(-2, -1))
    return scipy.fft.fftshift(scipy.fft.ifft2(shifted, norm="ortho", workers=workers), axes=(-2, -1))


def fourier_resample(images, size: int, *, workers: int | None = None) -> np.ndarray:
    """Resample real images to ``size x size`` by cropping or zero-padding their spectra.

    Sample values are preserved: a constant image stays the same constant. The
    operation is exact for images band-limited to the smaller grid (as camera
    intensities of a circular pupil are, once the grid exceeds 4 pupil radii).

    Parameters
    ----------
    images : ndarray, (..., N, N)
        Real images.
    size : int
        Output side length.

    Returns
    -------
    ndarray, float32, (..., size, size)
    """
    images = np.asarray(images)
    n = images.shape[-1]
    if images.shape[-2] != n:
        raise ValueError(f"images must be square, got {images.shape[-2:]}")
    if size == n:
        return images.astype(np.float32, copy=True)
    spectrum = fft2c(images.astype(np.complex64, copy=False), workers=workers)
    out_spec = np.zeros(images.shape[:-2] + (size, size), dtype=np.complex64)
    keep = min(n, size)
    src = n // 2 - keep // 2
    dst = size // 2 - keep // 2
    out_spec[..., dst : dst + keep, dst : dst + keep] = spectrum[..., src : src + keep, src : src + keep]
    out = ifft2c(out_spec, workers=workers).real * (size / n)
    return out.astype(np.float32)


class InPlaceFFT2:
    """Raw 2-D FFTs over the last two axes of one complex64 buffer, planned once.

    Parameters
    ----------
    buffer : ndarray, complex64, (..., m, m)
        The array transformed in place. Keep using the same object.
    threads : int, optional
        Threads for one transform (default: all cores).
    effort : str, optional
        FFTW planning effort (default :func:`planning_effort`); ``"measure"`` suits buffers used a few times.

    Notes
    -----
    ``forward`` computes ``Σ x exp(-2πi k n / m)`` and ``inverse`` computes
    ``Σ X exp(+2πi k n / m)``, both without any scaling: one round trip
    multiplies by ``m * m``. With FFTW, planning overwrites the buffer: fill it
    after constructing the plan.
    """

    def __init__(self, buffer: np.ndarray, *, threads: int | None = None, effort: str | None = None):
        if buffer.dtype != np.complex64:
            raise ValueError(f"InPlaceFFT2 needs a complex64 buffer, got {buffer.dtype}")
        self.buffer = buffer
        self.threads = threads or cpu_count()
        self.backend = _backend
        if self.backend == "pyfftw":
            self._forward = _plan(buffer, (-2, -1), "FFTW_FORWARD", self.threads, effort)
            self._inverse = _plan(buffer, (-2, -1), "FFTW_BACKWARD", self.threads, effort)

    def forward(self) -> np.ndarray:
        """Unnormalised forward FFT of the buffer, in place; returns the buffer."""
        if self.backend == "pyfftw":
            self._forward.execute()
        else:
            self.buffer[...] = scipy.fft.fft2(self.buffer, norm="backward", overwrite_x=True, workers=self.threads)
        return self.buffer

    def inverse(self) -> np.ndarray:
        """Unnormalised inverse FFT of the buffer, in place; returns the buffer."""
        if self.backend == "pyfftw":
            self._inverse.execute()
        else:
            self.buffer[...] = scipy.fft.ifft2(self.buffer, norm="forward", overwrite_x=True, workers=self.threads)
        return self.buffer


# ----------------------------------------------------------------------------- raw FFTW plans
class _IODim(ctypes.Structure):
    _fields_ = [("n", ctypes.c_int), ("is_", ctypes.c_int), ("os", ctypes.c_int)]


_FFTW_FLAGS = {"estimate": 1 << 6, "measure": 0, "patient": 1 << 5}
_FFTW_DESTROY_INPUT = 1
_raw_library = None
_raw_lock = threading.Lock()


def _fftw_library():
    """The single-precision FFTW that pyfftw loaded, through ctypes; None where it cannot be found.

    Plans made through it share pyfftw's wisdom, and compiled kernels can execute them
    without the interpreter (see :data:`fftw_execute`). Found through ``/proc/self/maps``,
    so only on Linux.
    """
    global _raw_library
    if _raw_library is not None or not _HAVE_PYFFTW:
        return _raw_library or None
    _raw_library = False
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "/libfftw3f" in line}
    except OSError:
        return None
    threaded = [p for p in paths if "_omp" in p or "_threads" in p]
    paths = [p for p in paths if p not in threaded]
    if len(paths) != 1 or len(threaded) > 1:
        return None
    try:
        library = ctypes.CDLL(paths[0])
        # Planning reads a global thread count that pyfftw sets per plan: raw plans set it to 1.
        library.set_plan_threads = ctypes.CDLL(threaded[0]).fftwf_plan_with_nthreads if threaded else None
        library.fftwf_plan_guru_dft.restype = ctypes.c_void_p
        library.fftwf_plan_guru_dft.argtypes = [ctypes.c_int, ctypes.POINTER(_IODim), ctypes.c_int,
                                                ctypes.POINTER(_IODim), ctypes.c_void_p, ctypes.c_void_p,
                                                ctypes.c_int, ctypes.c_uint]
        library.fftwf_execute.argtypes = [ctypes.c_void_p]
        library.fftwf_execute.restype = None
        library.fftwf_destroy_plan.argtypes = [ctypes.c_void_p]
        library.fftwf_destroy_plan.restype = None
    except (OSError, AttributeError):
        return None
    _raw_library = library
    return library


def fftw_execute():
    """``fftwf_execute`` as a ctypes function (callable from numba-compiled code), or None."""
    library = _fftw_library()
    return None if library is None else library.fftwf_execute


def _raw_plan(array: np.ndarray, axis: int, row_start: int, row_stop: int, sign: int, effort: str | None) -> int:
    """A raw FFTW plan, in place, of 1-D transforms of ``array`` (n, m, m) along ``axis``.

    Along the last axis only rows ``[row_start, row_stop)`` are transformed. Returns the plan's address.
    """
    library = _fftw_library()
    count, m = array.shape[0], array.shape[-1]
    if axis == -1:
        dims = [_IODim(m, 1, 1)]
        loops = [_IODim(count, m * m, m * m), _IODim(row_stop - row_start, m, m)]
        start = array[:, row_start:row_stop].ctypes.data if count else array.ctypes.data
    else:
        dims = [_IODim(m, m, m)]
        loops = [_IODim(count, m * m, m * m), _IODim(m, 1, 1)]
        start = array.ctypes.data
    flags = _FFTW_FLAGS[effort or planning_effort()] | _FFTW_DESTROY_INPUT
    with _raw_lock:
        if library.set_plan_threads is not None:
            library.set_plan_threads(1)
        plan = library.fftwf_plan_guru_dft(1, (_IODim * 1)(*dims), 2, (_IODim * 2)(*loops), start, start, sign,
                                           flags)
    if not plan:
        raise RuntimeError("FFTW could not plan a transform")
    return int(plan)


def _destroy_raw_plans(plans: list[int]) -> None:
    library = _fftw_library()
    with _raw_lock:
        for plan in plans:
            library.fftwf_destroy_plan(plan)


def _planned_counts(capacity: int) -> list[int]:
    """Field counts planned for a buffer of ``capacity`` fields: powers of two below it, and itself."""
    counts = [1 << bit for bit in range(capacity.bit_length()) if (1 << bit) < capacity]
    return counts + [capacity]


class BandedFFT2:
    """Raw 2-D FFTs of a buffer whose data live in a band of rows, planned once.

    The inverse transform assumes the input is zero outside rows
    ``[row_start, row_stop)``; the forward transform is exact only inside
    those rows. Transforming along the last axis for the band's rows alone
    saves about ``(1 - band/m) / 2`` of the work of a full 2-D FFT — the
    forward model's pupil box occupies about half the rows.

    Both transforms take the number of leading fields to transform, so a
    partly filled buffer costs little more than what it holds: the transform
    covers the smallest planned count that holds them (a power of two, or the
    whole buffer). Fields beyond ``count`` may be changed.

    Parameters
    ----------
    buffer : ndarray, complex64, (n, m, m)
    row_start, row_stop : int
        The band of rows that holds data.
    threads : int, optional
        Threads for one transform (default: all cores).
    effort : str, optional
        FFTW planning effort (default :func:`planning_effort`).

    Notes
    -----
    With FFTW, planning overwrites the buffer: fill it after construction.
    """

    def __init__(self, buffer: np.ndarray, row_start: int, row_stop: int, *, threads: int | None = None,
                 effort: str | None = None):
        if buffer.dtype != np.complex64 or buffer.ndim != 3:
            raise ValueError(f"BandedFFT2 needs a complex64 (n, m, m) buffer, got {buffer.dtype} {buffer.shape}")
        self.buffer = buffer
        self.band = buffer[:, row_start:row_stop, :]
        self.threads = threads or cpu_count()
        self.backend = _backend
        self._plans = {}
        self._counts = _planned_counts(buffer.shape[0])
        if self.backend == "pyfftw":
            for count in self._counts:
                whole, band = buffer[:count], self.band[:count]
                self._plans[count] = (
                    _plan(band, (-1,), "FFTW_BACKWARD", self.threads, effort),
                    _plan(whole, (-2,), "FFTW_BACKWARD", self.threads, effort),
                    _plan(whole, (-2,), "FFTW_FORWARD", self.threads, effort),
                    _plan(band, (-1,), "FFTW_FORWARD", self.threads, effort),
                )
        #: Raw FFTW plans per planned count, for compiled loops (None where unavailable); see :meth:`raw_plans`.
        self._raw = None
        if self.backend == "pyfftw" and self.threads == 1 and _fftw_library() is not None:
            rows = (row_start, row_stop)
            self._raw = np.array([[_raw_plan(buffer[:count], -1, *rows, +1, effort),
                                   _raw_plan(buffer[:count], -2, *rows, +1, effort),
                                   _raw_plan(buffer[:count], -2, *rows, -1, effort),
                                   _raw_plan(buffer[:count], -1, *rows, -1, effort)] for count in self._counts],
                                 dtype=np.int64)
            weakref.finalize(self, _destroy_raw_plans, [int(p) for p in self._raw.ravel()])

    def raw_plans(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Plans compiled code can execute with :func:`fftw_execute`, or None.

        Returns
        -------
        counts : ndarray, int64, (n,)
            The planned field counts, ascending.
        plans : ndarray, int64, (n, 4)
            For each count, the addresses of the inverse row and column plans and the forward
            column and row plans, in the order they run. Available with pyfftw on Linux, for
            single-threaded buffers.
        """
        if self._raw is None:
            return None
        return np.array(self._counts, dtype=np.int64), self._raw

    def _planned(self, count: int | None) -> int:
        """The smallest planned count that holds ``count`` fields (0 for none)."""
        n = self.buffer.shape[0]
        if count is None:
            return n
        if not 0 <= count <= n:
            raise ValueError(f"count must be in [0, {n}], got {count}")
        return next((c for c in self._counts if c >= count), n) if count else 0

    def inverse(self, count: int | None = None) -> np.ndarray:
        """Unnormalised inverse 2-D FFT of the first ``count`` fields (default all), zero outside the band; in place."""
        count = self._planned(count)
        if not count:
            return self.buffer
        if self.backend == "pyfftw":
            rows, columns, _, _ = self._plans[count]
            rows.execute()
            columns.execute()
        else:
            band, whole = self.band[:count], self.buffer[:count]
            band[...] = scipy.fft.ifft(band, axis=-1, norm="forward", workers=self.threads)
            whole[...] = scipy.fft.ifft(whole, axis=-2, norm="forward", overwrite_x=True, workers=self.threads)
        return self.buffer

    def forward(self, count: int | None = None) -> np.ndarray:
        """Unnormalised forward 2-D FFT of the first ``count`` fields (default all), exact inside the band; in place."""
        count = self._planned(count)
        if not count:
            return self.buffer
        if self.backend == "pyfftw":
            _, _, columns, rows = self._plans[count]
            columns.execute()
            rows.execute()
        else:
            band, whole = self.band[:count], self.buffer[:count]
            whole[...] = scipy.fft.fft(whole, axis=-2, norm="backward", overwrite_x=True, workers=self.threads)
            band[...] = scipy.fft.fft(band, axis=-1, norm="backward", workers=self.threads)
        return self.buffer
