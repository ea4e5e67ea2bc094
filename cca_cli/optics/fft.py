"""The one module that allocates arrays and runs FFTs for the numeric core.

Everything numeric goes through here so that another array backend (for
example CuPy) can replace this module without touching the engines.

Two kinds of transform are offered:

* :func:`fft2c` / :func:`ifft2c`: centred, orthonormal 2-D FFTs over the last
  two axes, batched over any leading axes (``numpy.fft``, in the input's
  precision). Convenient, not for hot loops.
* :class:`InPlaceFFT2` and :class:`BandedFFT2`: raw (unnormalised) 2-D FFTs
  planned once for one buffer and executed in place. FFTW (pyfftw) when
  installed, ``scipy.fft`` otherwise (imported only then: it costs a
  command about 0.15 s of start-up). Callers fold the normalisation into
  arrays they multiply anyway. How FFTW plans them (``$CCA_FFTW_PLANNING``,
  bounded and chosen by how long they run), who owns the plans and the one
  planner lock are the business of :mod:`cca_cli.optics.fftw_plans`.

``CCA_FFT_BACKEND=scipy`` runs without pyfftw (it is not even imported) and
``CCA_RAW_FFTW=off`` as where FFTW's library cannot be found (not Linux):
see :mod:`cca_cli.optics.switches`.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import time

import numpy as np

from cca_cli.optics import fftw_plans, switches
from cca_cli.optics.fftw_plans import HAVE_PYFFTW, PLANNER_LOCK, RawFFTPlans, Spec, pyfftw, raw_fftw_available
from cca_cli.optics.switches import planning_effort

__all__ = [
    "xp",
    "one_blas_thread",
    "BLAS_THREAD_SETTINGS",
    "HAVE_PYFFTW",
    "PLANNER_LOCK",
    "backend_name",
    "use_backend",
    "cpu_count",
    "default_threads",
    "limit_threads",
    "planning_effort",
    "planning_seconds",
    "check_settings",
    "raw_fftw_available",
    "empty",
    "zeros",
    "fft2",
    "ifft2",
    "fft2c",
    "ifft2c",
    "fourier_resample",
    "fourier_interpolate",
    "resize_spectrum",
    "InPlaceFFT2",
    "BandedFFT2",
    "RawFFTPlans",
]

#: Array module used by the numeric core.
xp = np

_backend = "pyfftw" if HAVE_PYFFTW else "scipy"


def check_settings() -> None:
    """Raise :class:`~cca_cli.errors.ConfigError` (one line) if an FFT environment switch has an unknown value."""
    switches.check()


def planning_seconds() -> float:
    """Seconds this process has spent in timed FFTW planning so far."""
    return fftw_plans.planning_seconds()


def cpu_count() -> int:
    """Cores available to this process."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


_thread_limit: int | None = None


def default_threads() -> int:
    """Threads the numeric core uses when a caller names none: the cores, or the :func:`limit_threads` limit."""
    cores = cpu_count()
    return cores if _thread_limit is None else max(1, min(cores, _thread_limit))


@contextlib.contextmanager
def limit_threads(count: int):
    """Use at most ``count`` threads in FFTs and engines inside the block (a Dask worker running one task per core)."""
    global _thread_limit
    previous, _thread_limit = _thread_limit, max(1, int(count))
    try:
        yield
    finally:
        _thread_limit = previous


#: Environment variables that set the BLAS libraries' threads: where the user set one, their choice stands.
BLAS_THREAD_SETTINGS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "OMP_NUM_THREADS")


@contextlib.contextmanager
def one_blas_thread():
    """Run numpy's and scipy's matrix products (BLAS, LAPACK) on one thread inside the block.

    cca's matrix products are small (a local DFT, a few Zernike modes, a lattice fit): BLAS threads of
    their own only wait for the cores the engines' threads hold, and OpenBLAS waits actively (the blood
    smear's aberration estimate took 70 ms on 2 cores, against 1 ms on one thread), and one thread sums
    in the same order on every machine. The ``cca`` command sets this for the whole process before numpy
    loads (:mod:`cca_cli.commands.entry`); a notebook's calls get it here. Where the environment sets the
    BLAS threads (:data:`BLAS_THREAD_SETTINGS`), nothing is changed.
    """
    if any(name in os.environ for name in BLAS_THREAD_SETTINGS):
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def backend_name() -> str:
    """Name of the FFT backend in use: ``"pyfftw"`` or ``"scipy"``."""
    check_settings()
    return _backend


@contextlib.contextmanager
def use_backend(name: str):
    """Temporarily select the FFT backend (``"pyfftw"`` or ``"scipy"``).

    Raises
    ------
    ValueError
        If the name is unknown or pyfftw is requested but not available.
    """
    global _backend
    if name not in ("pyfftw", "scipy"):
        raise ValueError(f"unknown FFT backend {name!r}; choose 'pyfftw' or 'scipy'")
    if name == "pyfftw" and not HAVE_PYFFTW:
        raise ValueError("FFT backend 'pyfftw' requested but pyfftw is not installed (or CCA_FFT_BACKEND=scipy)")
    previous, _backend = _backend, name
    try:
        yield
    finally:
        _backend = previous


def empty(shape, dtype=np.complex64) -> np.ndarray:
    """Uninitialised array, aligned to 64 bytes when FFTW is in use (every SIMD width; one FFTW plan per shape)."""
    if _backend == "pyfftw":
        return pyfftw.empty_aligned(shape, dtype=dtype, n=64)
    return np.empty(shape, dtype=dtype)


def zeros(shape, dtype=np.complex64) -> np.ndarray:
    """Zero-filled array, SIMD-aligned when FFTW is in use."""
    out = empty(shape, dtype)
    out.fill(0)
    return out


def _scipy_fft():
    """``scipy.fft``, imported on first use (the raw transforms' fallback where FFTW is not used)."""
    return importlib.import_module("scipy.fft")


def _single(result: np.ndarray, array) -> np.ndarray:
    """``result`` in single precision when ``array`` was (numpy before 2.0 transforms in double)."""
    if np.asarray(array).dtype in (np.float32, np.complex64) and result.dtype == np.complex128:
        return result.astype(np.complex64)
    return result


def fft2(array) -> np.ndarray:
    """Plain (uncentred, unnormalised) 2-D FFT over the last two axes; single precision stays single."""
    return _single(np.fft.fft2(array), array)


def ifft2(array) -> np.ndarray:
    """Plain (uncentred) inverse 2-D FFT over the last two axes, normalised by 1/n; single precision stays single."""
    return _single(np.fft.ifft2(array), array)


def fft2c(array) -> np.ndarray:
    """Centred orthonormal 2-D FFT over the last two axes (DC at ``n // 2``)."""
    shifted = np.fft.ifftshift(array, axes=(-2, -1))
    return _single(np.fft.fftshift(np.fft.fft2(shifted, norm="ortho"), axes=(-2, -1)), array)


def ifft2c(array) -> np.ndarray:
    """Centred orthonormal inverse 2-D FFT over the last two axes."""
    shifted = np.fft.ifftshift(array, axes=(-2, -1))
    return _single(np.fft.fftshift(np.fft.ifft2(shifted, norm="ortho"), axes=(-2, -1)), array)


def resize_spectrum(spectrum, shape) -> np.ndarray:
    """A centred spectrum cropped or zero-padded about DC (pixel ``n // 2``) to ``shape`` (last two axes), complex64."""
    spectrum = np.asarray(spectrum)
    shape = tuple(int(v) for v in shape)
    out = np.zeros(spectrum.shape[:-2] + shape, np.complex64)
    keep = [min(a, b) for a, b in zip(spectrum.shape[-2:], shape)]
    src = [n // 2 - k // 2 for n, k in zip(spectrum.shape[-2:], keep)]
    dst = [n // 2 - k // 2 for n, k in zip(shape, keep)]
    out[..., dst[0]:dst[0] + keep[0], dst[1]:dst[1] + keep[1]] = \
        spectrum[..., src[0]:src[0] + keep[0], src[1]:src[1] + keep[1]]
    return out


def fourier_interpolate(image, shape) -> np.ndarray:
    """Band-limited interpolation of an image (real or complex, any aspect) onto ``shape``, values kept, complex64.

    The spectrum is cropped or zero-padded about DC, so the centre pixel ``n // 2`` stays the centre and
    a constant image keeps its value. Exact for images band-limited to the smaller grid.
    """
    image = np.asarray(image)
    shape = tuple(int(v) for v in shape)
    spectrum = resize_spectrum(fft2c(image.astype(np.complex64, copy=False)), shape)
    scale = np.float32(np.sqrt(shape[0] * shape[1] / (image.shape[-2] * image.shape[-1])))
    return (ifft2c(spectrum) * scale).astype(np.complex64, copy=False)


def fourier_resample(images, size: int) -> np.ndarray:
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
    spectrum = resize_spectrum(fft2c(images.astype(np.complex64, copy=False)), (size, size))
    out = ifft2c(spectrum).real * (size / n)
    return out.astype(np.float32)


def _checked_buffer(buffer: np.ndarray, name: str) -> None:
    if not isinstance(buffer, np.ndarray) or buffer.dtype != np.complex64:
        raise ValueError(f"{name} needs a complex64 buffer, got {getattr(buffer, 'dtype', type(buffer))}")
    if not buffer.flags.c_contiguous or not buffer.flags.writeable:
        raise ValueError(f"{name} needs a C-contiguous, writeable buffer")


class InPlaceFFT2:
    """Raw 2-D FFTs over the last two axes of one complex64 buffer, planned once.

    Parameters
    ----------
    buffer : ndarray, complex64, (..., m, m), C-contiguous
        The array transformed in place. Keep using the same object.
    threads : int, optional
        Threads for one transform (default: all cores).
    effort : str, optional
        FFTW planning effort (default :func:`planning_effort`).

    Notes
    -----
    ``forward`` computes ``Σ x exp(-2πi k n / m)`` and ``inverse`` computes
    ``Σ X exp(+2πi k n / m)``, both without any scaling: one round trip
    multiplies by ``m * m``. Planning leaves the buffer untouched.
    """

    def __init__(self, buffer: np.ndarray, *, threads: int | None = None, effort: str | None = None):
        check_settings()
        _checked_buffer(buffer, "InPlaceFFT2")
        self.buffer = buffer
        self.threads = threads or default_threads()
        self.backend = _backend
        self._plans = None
        if self.backend == "pyfftw":
            specs = [Spec(None, None, (-2, -1), -1), Spec(None, None, (-2, -1), +1)]
            self._plans = fftw_plans.owned_plans(self, buffer, specs, self.threads, effort)

    def _execute(self, i: int) -> None:
        plans = self._plans
        with plans.lock:
            plans.check_alive()
            start = time.perf_counter()
            plans.fftw[i].execute()
            plans.note_use(time.perf_counter() - start, (i,))

    def forward(self) -> np.ndarray:
        """Unnormalised forward FFT of the buffer, in place; returns the buffer."""
        if self.backend == "pyfftw":
            self._execute(0)
        else:
            self.buffer[...] = _scipy_fft().fft2(self.buffer, norm="backward", overwrite_x=True, workers=self.threads)
        return self.buffer

    def inverse(self) -> np.ndarray:
        """Unnormalised inverse FFT of the buffer, in place; returns the buffer."""
        if self.backend == "pyfftw":
            self._execute(1)
        else:
            self.buffer[...] = _scipy_fft().ifft2(self.buffer, norm="forward", overwrite_x=True, workers=self.threads)
        return self.buffer

    def close(self) -> None:
        """Destroy the plans now; using the transform afterwards raises RuntimeError."""
        if self._plans is not None:
            fftw_plans.release(self._plans)


def _planned_counts(capacity: int) -> list[int]:
    """Field counts planned for a buffer of ``capacity`` fields: powers of two below it, and itself."""
    counts = [1 << bit for bit in range(capacity.bit_length()) if (1 << bit) < capacity]
    return counts + [capacity]


#: The four transforms of each planned count, in the order they run: inverse rows, inverse columns
#: (the inverse 2-D FFT), forward columns, forward rows (the forward one).
_INVERSE_ROWS, _INVERSE_COLUMNS, _FORWARD_COLUMNS, _FORWARD_ROWS = range(4)


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
    buffer : ndarray, complex64, (n, m, m), C-contiguous
    row_start, row_stop : int
        The band of rows that holds data.
    threads : int, optional
        Threads for one transform (default: all cores).
    effort : str, optional
        FFTW planning effort (default :func:`planning_effort`).

    Notes
    -----
    The plans live as long as this object (or a :class:`RawFFTPlans` made from
    it), or until :meth:`close`. Planning leaves the buffer untouched.
    """

    def __init__(self, buffer: np.ndarray, row_start: int, row_stop: int, *, threads: int | None = None,
                 effort: str | None = None):
        check_settings()
        _checked_buffer(buffer, "BandedFFT2")
        if buffer.ndim != 3 or buffer.shape[0] < 1 or buffer.shape[1] != buffer.shape[2]:
            raise ValueError(f"BandedFFT2 needs an (n, m, m) buffer with n >= 1, got {buffer.shape}")
        if not 0 <= row_start < row_stop <= buffer.shape[1]:
            raise ValueError(f"band rows [{row_start}, {row_stop}) must lie within [0, {buffer.shape[1]})")
        self.buffer = buffer
        self.band = buffer[:, row_start:row_stop, :]
        self.rows = (int(row_start), int(row_stop))
        self.threads = threads or default_threads()
        self.backend = _backend
        self._counts = _planned_counts(buffer.shape[0])
        self._group = {count: g for g, count in enumerate(self._counts)}
        self._plans = None
        self._raw_handle = None
        if self.backend == "pyfftw":
            specs = []
            for count in self._counts:
                specs += [Spec(count, self.rows, (-1,), +1), Spec(count, None, (-2,), +1),
                          Spec(count, None, (-2,), -1), Spec(count, self.rows, (-1,), -1)]
            self._plans = fftw_plans.owned_plans(self, buffer, specs, self.threads, effort)

    def raw_plans(self) -> RawFFTPlans | None:
        """Plans compiled code can execute (see :class:`RawFFTPlans`), or None.

        Available with pyfftw on Linux, for single-threaded buffers. The plans
        live as long as the returned object.
        """
        if self.backend != "pyfftw" or self.threads != 1 or not raw_fftw_available():
            return None
        handle = self._raw_handle
        plans = self._plans
        with plans.lock:
            plans.check_alive()
            if handle is None or handle.generation != plans.raw_generation or plans.raw is None:
                plans.make_raw()
                handle = self._raw_handle = RawFFTPlans(self, plans, self._counts)
        return handle

    def _planned(self, count: int | None) -> int:
        """The smallest planned count that holds ``count`` fields (0 for none)."""
        n = self.buffer.shape[0]
        if count is None:
            return n
        if not 0 <= count <= n:
            raise ValueError(f"count must be in [0, {n}], got {count}")
        return next((c for c in self._counts if c >= count), n) if count else 0

    def _execute(self, count: int, first: int, second: int) -> None:
        plans = self._plans
        base = 4 * self._group[count]
        with plans.lock:
            plans.check_alive()
            start = time.perf_counter()
            plans.fftw[base + first].execute()
            plans.fftw[base + second].execute()
            plans.note_use(time.perf_counter() - start, (base + first, base + second))

    def inverse(self, count: int | None = None) -> np.ndarray:
        """Unnormalised inverse 2-D FFT of the first ``count`` fields (default all), zero outside the band; in place."""
        count = self._planned(count)
        if not count:
            return self.buffer
        if self.backend == "pyfftw":
            self._execute(count, _INVERSE_ROWS, _INVERSE_COLUMNS)
        else:
            band, whole = self.band[:count], self.buffer[:count]
            band[...] = _scipy_fft().ifft(band, axis=-1, norm="forward", workers=self.threads)
            whole[...] = _scipy_fft().ifft(whole, axis=-2, norm="forward", overwrite_x=True, workers=self.threads)
        return self.buffer

    def forward(self, count: int | None = None) -> np.ndarray:
        """Unnormalised forward 2-D FFT of the first ``count`` fields (default all), exact inside the band; in place."""
        count = self._planned(count)
        if not count:
            return self.buffer
        if self.backend == "pyfftw":
            self._execute(count, _FORWARD_COLUMNS, _FORWARD_ROWS)
        else:
            band, whole = self.band[:count], self.buffer[:count]
            whole[...] = _scipy_fft().fft(whole, axis=-2, norm="backward", overwrite_x=True, workers=self.threads)
            band[...] = _scipy_fft().fft(band, axis=-1, norm="backward", workers=self.threads)
        return self.buffer

    def close(self) -> None:
        """Destroy the plans now (raw ones included); using them afterwards raises RuntimeError."""
        if self._plans is not None:
            fftw_plans.release(self._plans)


