"""Fused per-pixel kernels of the numeric core, compiled with numba when it is installed.

Each kernel does in one pass what would otherwise take several numpy passes
(and several trips through the interpreter): placing pupil boxes into the
field buffer, the magnitude projection with its misfit, and the pupil-weighted
scatter back into the spectrum. The compiled kernels release the GIL, so the
engines' worker threads run them in parallel on different chunks. They sit beside :mod:`cca_cli.optics.fft` as
part of the array backend: another backend (e.g. CuPy) supplies its own
versions of these few functions. Without numba, equivalent numpy code runs;
``CCA_KERNELS=numpy`` selects it (numba is then not imported).

Compiled code does not check its indices, so every public function checks
shapes, dtypes, layouts and box origins first: a bad call raises ValueError
and never reaches compiled code.
"""

from __future__ import annotations

import numpy as np

from cca_cli.optics import fft, jit, switches
from cca_cli.optics.jit import cache_enabled

numba = None
if switches.read_at_import("CCA_KERNELS", "numba", ("numba", "numpy")) == "numba":
    try:  # pragma: no cover - exercised when numba is installed
        import numba
    except ImportError:  # pragma: no cover
        numba = None
_HAVE_NUMBA = numba is not None

__all__ = ["HAVE_NUMBA", "kernels_name", "use_kernels", "check_settings", "warm_up", "place_boxes",
           "project_magnitudes", "magnitude_step", "can_fuse_lanes", "lane_chunk", "sequential_lane", "scatter_boxes",
           "momentum_step", "tikhonov_update", "rpie_factors", "map_pupil_factors", "accumulate_pupil", "MapPupils",
           "scatter_map_boxes"]

#: Whether numba is installed and enabled (``CCA_KERNELS`` is not ``numpy``).
HAVE_NUMBA = _HAVE_NUMBA
_use_numba = _HAVE_NUMBA


def check_settings() -> None:
    """Raise :class:`~cca_cli.errors.ConfigError` (one line) if a backend switch, ``CCA_KERNELS`` included,
    has an unknown value (see :mod:`cca_cli.optics.switches`)."""
    switches.check()


def kernels_name() -> str:
    """``"numba"`` or ``"numpy"``: which implementation the kernels use."""
    return "numba" if _use_numba else "numpy"


class use_kernels:
    """Context manager selecting ``"numba"`` or ``"numpy"`` kernels (tests compare the two)."""

    def __init__(self, name: str):
        if name not in ("numba", "numpy"):
            raise ValueError(f"unknown kernels {name!r}; choose 'numba' or 'numpy'")
        if name == "numba" and not _HAVE_NUMBA:
            raise ValueError("numba kernels requested but numba is not installed (or CCA_KERNELS=numpy)")
        self.name = name

    def __enter__(self):
        global _use_numba
        self._previous, _use_numba = _use_numba, self.name == "numba"
        return self

    def __exit__(self, *exc):
        global _use_numba
        _use_numba = self._previous


# ----------------------------------------------------------------------------- numpy versions
def _place_boxes_numpy(spectrum, origins, pupils, fields, start):
    k, m, b = fields.shape[0], fields.shape[1], pupils.shape[1]
    s = m // 2 - b // 2
    fields[:k, :s] = 0
    fields[:k, s + b:] = 0
    fields[:k, s:s + b, :s] = 0
    fields[:k, s:s + b, s + b:] = 0
    for j in range(k):
        y0, x0 = origins[start + j]
        np.multiply(spectrum[y0:y0 + b, x0:x0 + b], pupils[start + j], out=fields[j, s:s + b, s:s + b])


def _magnitude_numpy(fields, amplitudes, weights, eps, keep, magnitude, misfit):
    """:func:`_magnitude_numba` in numpy: ``magnitude`` is a work array, ``misfit`` one too or None."""
    np.abs(fields, out=magnitude)
    misfit = np.subtract(magnitude, amplitudes, out=misfit)
    if weights is not None:
        misfit *= np.sqrt(weights)
    flat = misfit.reshape(-1)
    squared = float(np.dot(flat, flat))
    np.maximum(magnitude, np.float32(eps), out=magnitude)
    factor = np.divide(amplitudes, magnitude, out=magnitude)
    if keep:  # w · A/|ψ| + (1 − w)
        if weights is not None:
            factor *= weights
            factor += 1.0 - weights
    else:  # w · (A/|ψ| − 1)
        factor -= 1.0
        if weights is not None:
            factor *= weights
    fields *= factor
    return squared


def _scatter_numpy(fields, origins, pupils, accumulator, start):
    k, m, b = fields.shape[0], fields.shape[1], pupils.shape[1]
    s = m // 2 - b // 2
    boxes = fields[:k, s:s + b, s:s + b]
    boxes *= pupils[start:start + k]
    for j in range(k):
        y0, x0 = origins[start + j]
        accumulator[y0:y0 + b, x0:x0 + b] += boxes[j]


# ----------------------------------------------------------------------------- numba versions
if _HAVE_NUMBA:  # pragma: no branch
    # error_model="numpy": float division by zero gives inf instead of raising, which lets
    # LLVM vectorise loops that divide (about 5x faster magnitude steps).
    _cache = cache_enabled()  # False (with a note) where numba can write no cache folder: a read-only install
    _jit = numba.njit(nogil=True, cache=_cache, error_model="numpy")
    _jit_fast = numba.njit(nogil=True, cache=_cache, error_model="numpy", fastmath=True)

    @_jit
    def _first_bad_box(origins, start, count, last_y, last_x):  # pragma: no cover - compiled
        """Index of the first capture in ``start … start + count - 1`` whose box leaves the spectrum, or -1."""
        for j in range(start, start + count):
            y0 = origins[j, 0]
            x0 = origins[j, 1]
            if y0 < 0 or x0 < 0 or y0 > last_y or x0 > last_x:
                return j
        return -1

    @_jit
    def _place_boxes_numba(spectrum, origins, pupils, fields, start):  # pragma: no cover - compiled
        """Returns -1, or the first capture whose box leaves the spectrum (then nothing is written)."""
        k, m, b = fields.shape[0], fields.shape[1], pupils.shape[1]
        bad = _first_bad_box(origins, start, k, spectrum.shape[0] - b, spectrum.shape[1] - b)
        if bad >= 0:
            return bad
        s = m // 2 - b // 2
        for j in range(k):
            y0 = origins[start + j, 0]
            x0 = origins[start + j, 1]
            for r in range(m):
                if r < s or r >= s + b:
                    for c in range(m):
                        fields[j, r, c] = 0
                else:
                    for c in range(s):
                        fields[j, r, c] = 0
                    for c in range(b):
                        fields[j, r, s + c] = spectrum[y0 + r - s, x0 + c] * pupils[start + j, r - s, c]
                    for c in range(s + b, m):
                        fields[j, r, c] = 0
        return -1

    #: Elements per float32 partial sum of the misfit (the partial sums are added in float64).
    _MISFIT_BLOCK = 2048

    @_jit_fast
    def _magnitude_block(values, measured, eps, keep):  # pragma: no cover - compiled
        one = np.float32(1.0)
        total = np.float32(0.0)
        for i in range(measured.size):
            re = values[2 * i]
            im = values[2 * i + 1]
            magnitude = np.sqrt(re * re + im * im)
            a = measured[i]
            d = magnitude - a
            total += d * d
            q = a / max(magnitude, eps) - one + keep
            values[2 * i] = re * q
            values[2 * i + 1] = im * q
        return total

    @_jit_fast
    def _magnitude_block_weighted(values, measured, confidence, eps, keep):  # pragma: no cover - compiled
        one = np.float32(1.0)
        total = np.float32(0.0)
        for i in range(measured.size):
            re = values[2 * i]
            im = values[2 * i + 1]
            magnitude = np.sqrt(re * re + im * im)
            a = measured[i]
            w = confidence[i]
            d = magnitude - a
            total += w * d * d
            q = w * (a / max(magnitude, eps) - one) + keep
            values[2 * i] = re * q
            values[2 * i + 1] = im * q
        return total

    @_jit
    def _magnitude_numba(fields, amplitudes, weights, eps, keep, weighted):  # pragma: no cover - compiled
        """``ψ ← (w (A/max(|ψ|, ε) − 1) + keep) ψ``; returns ``Σ w (|ψ| − A)²``."""
        values = fields.reshape(fields.size).view(np.float32)
        measured = amplitudes.reshape(amplitudes.size)
        confidence = weights.reshape(weights.size)
        n = measured.size
        total = 0.0
        # Separate loops per case (rather than a branch inside one) are what LLVM vectorises.
        for s in range(0, n, _MISFIT_BLOCK):
            e = min(n, s + _MISFIT_BLOCK)
            if weighted:
                total += _magnitude_block_weighted(values[2 * s:2 * e], measured[s:e], confidence[s:e], eps, keep)
            else:
                total += _magnitude_block(values[2 * s:2 * e], measured[s:e], eps, keep)
        return total

    @_jit_fast
    def _tikhonov_numba(numerator, inverse_normal, spectrum):  # pragma: no cover - compiled
        new = numerator.reshape(numerator.size).view(np.float32)
        old = spectrum.reshape(spectrum.size).view(np.float32)
        scale = inverse_normal.reshape(inverse_normal.size)
        change = 0.0
        norm = 0.0
        for i in range(scale.size):
            q = scale[i]
            re = new[2 * i] * q
            im = new[2 * i + 1] * q
            new[2 * i] = re
            new[2 * i + 1] = im
            dr = re - old[2 * i]
            di = im - old[2 * i + 1]
            change += dr * dr + di * di
            norm += old[2 * i] * old[2 * i] + old[2 * i + 1] * old[2 * i + 1]
        return change, norm

    @_jit
    def _scatter_numba(fields, origins, pupils, accumulator, start):  # pragma: no cover - compiled
        """Returns -1, or the first capture whose box leaves the spectrum (then nothing is written)."""
        k, m, b = fields.shape[0], fields.shape[1], pupils.shape[1]
        bad = _first_bad_box(origins, start, k, accumulator.shape[0] - b, accumulator.shape[1] - b)
        if bad >= 0:
            return bad
        s = m // 2 - b // 2
        for j in range(k):
            y0 = origins[start + j, 0]
            x0 = origins[start + j, 1]
            for r in range(b):
                # Rows as interleaved floats: the loop vectorises (the same products as complex64 ones).
                f = fields[j, s + r, s:s + b].view(np.float32)
                p = pupils[start + j, r].view(np.float32)
                a = accumulator[y0 + r, x0:x0 + b].view(np.float32)
                for c in range(b):
                    fr, fi, pr, pi = f[2 * c], f[2 * c + 1], p[2 * c], p[2 * c + 1]
                    a[2 * c] += fr * pr - fi * pi
                    a[2 * c + 1] += fr * pi + fi * pr
        return -1

    # Strict IEEE arithmetic: with fastmath, LLVM fused and reordered this loop differently depending on
    # what the process had compiled before it, so the same inputs gave different bits from one cache to another.
    @_jit
    def _momentum_numba(spectrum, anchor, velocity, eta):  # pragma: no cover - compiled
        s = spectrum.reshape(spectrum.size)
        a = anchor.reshape(anchor.size)
        v = velocity.reshape(velocity.size)
        change = 0.0
        norm = 0.0
        for i in range(s.size):
            start = a[i]
            step = eta * v[i] + (s[i] - start)
            v[i] = step
            new = s[i] + eta * step
            s[i] = new
            a[i] = new
            d = new - start
            change += d.real * d.real + d.imag * d.imag
            norm += start.real * start.real + start.imag * start.imag
        return change, norm


# ----------------------------------------------------------------------------- argument checks
# These run before every compiled call, so they stay cheap: attribute reads and comparisons only.
_C64, _F32, _I64 = np.dtype(np.complex64), np.dtype(np.float32), np.dtype(np.int64)
_ndarray = np.ndarray


def _describe(array) -> str:
    if isinstance(array, _ndarray):
        return f"{array.dtype} {array.shape}"
    return type(array).__name__


def _check_boxes(function: str, spectrum, origins, pupils, fields, start: int) -> None:
    """Dtypes and shapes of a box placement or scatter of captures ``start …`` (origins are checked apart)."""
    if not (isinstance(spectrum, _ndarray) and isinstance(origins, _ndarray) and isinstance(pupils, _ndarray)
            and isinstance(fields, _ndarray) and spectrum.dtype == _C64 and origins.dtype == _I64 and pupils.dtype == _C64 and fields.dtype == _C64
            and spectrum.ndim == 2 and origins.ndim == 2 and pupils.ndim == 3 and fields.ndim == 3):
        raise ValueError(f"{function} needs spectrum complex64 (M, M), origins int64 (K, 2), pupils complex64 "
                         f"(K, b, b) and fields complex64 (k, m, m); got {_describe(spectrum)}, "
                         f"{_describe(origins)}, {_describe(pupils)}, {_describe(fields)}")
    n, b, b2 = pupils.shape
    k, m, m2 = fields.shape
    if (origins.shape[0] != n or origins.shape[1] != 2 or b2 != b or m2 != m or b > m or b > spectrum.shape[0]
            or b > spectrum.shape[1]):
        raise ValueError(f"{function}: shapes do not fit together: spectrum {spectrum.shape}, origins "
                         f"{origins.shape}, pupils {pupils.shape}, fields {fields.shape} (need origins (K, 2), "
                         "pupils (K, b, b), fields (k, m, m) with b <= m and b <= M)")
    if start < 0 or start + k > n:
        raise ValueError(f"{function}: captures {start} to {start + k - 1} are not among the {n} captures")


def _bad_box(function: str, origins, index: int, spectrum_shape, box: int) -> ValueError:
    y0, x0 = (int(v) for v in origins[index])
    return ValueError(f"{function}: the {box}x{box} box of capture {index} at origin ({y0}, {x0}) does not lie "
                      f"inside the {spectrum_shape[0]}x{spectrum_shape[1]} spectrum")


def _check_origins_numpy(function: str, origins, start: int, count: int, spectrum_shape, box: int) -> None:
    used = origins[start:start + count]
    if not count:
        return
    outside = ((used < 0).any(axis=1) | (used[:, 0] > spectrum_shape[0] - box)
               | (used[:, 1] > spectrum_shape[1] - box))
    if outside.any():
        raise _bad_box(function, origins, start + int(np.argmax(outside)), spectrum_shape, box)


def _check_arrays(function: str, arrays: tuple) -> None:
    """Each ``(name, array, dtype, ndim)`` is an ndarray of that dtype and number of dimensions."""
    for name, array, dtype, ndim in arrays:
        if not (isinstance(array, _ndarray) and array.dtype == dtype and array.ndim == ndim):
            raise ValueError(f"{function}: {name} must be a {ndim}-d {dtype} array, got {_describe(array)}")


def _contiguous(*arrays) -> bool:
    """Whether every array is C-contiguous (the compiled kernels read rows as interleaved floats)."""
    return all(array.flags.c_contiguous for array in arrays)


def _check_alike(function: str, names: tuple[str, ...], arrays: tuple, dtypes: tuple) -> bool:
    """Every array has its dtype and the first one's shape; returns whether all are C-contiguous."""
    first = arrays[0]
    shape = first.shape if isinstance(first, _ndarray) else None
    contiguous = True
    for array, dtype in zip(arrays, dtypes):
        if not (isinstance(array, _ndarray) and array.dtype == dtype and array.shape == shape):
            expected = ", ".join(f"{name} {dtype}" for name, dtype in zip(names, dtypes))
            got = ", ".join(f"{name} {_describe(value)}" for name, value in zip(names, arrays))
            raise ValueError(f"{function} needs arrays of one shape ({expected}); got {got}")
        contiguous = contiguous and array.flags.c_contiguous
    return contiguous


# ----------------------------------------------------------------------------- public entry points
_warm = False


def warm_up() -> None:
    """Load (or compile) every kernel once, so no iteration pays for it; cheap after the first call.

    Raises
    ------
    ConfigError
        If a backend switch (``CCA_KERNELS`` …) has an unknown value.
    """
    global _warm
    check_settings()
    if _warm or not _use_numba:
        return
    _warm = True
    with jit.first_load():
        _load_every_kernel()


def _load_every_kernel() -> None:
    spectrum = np.zeros((8, 8), np.complex64)
    origins = np.zeros((1, 2), np.int64)
    pupils = np.zeros((1, 4, 4), np.complex64)
    fields = np.zeros((1, 8, 8), np.complex64)
    real = np.ones((1, 8, 8), np.float32)
    _place_boxes_numba(spectrum, origins, pupils, fields, 0)
    _scatter_numba(fields, origins, pupils, spectrum, 0)
    _momentum_numba(spectrum, spectrum.copy(), spectrum.copy(), np.float32(0.5))
    _magnitude_numba(fields, real, real, np.float32(1e-6), np.float32(1.0), False)
    _magnitude_numba(fields, real, real, np.float32(1e-6), np.float32(0.0), True)
    _tikhonov_numba(spectrum, np.ones((8, 8), np.float32), spectrum.copy())
    one = np.float32(1.0)
    _map_pupil_factors_numba(np.ones((1, 4, 4), np.float32), pupils, np.zeros(1, np.int64), origins,
                             np.array([[0, 1]], np.int64), one, one, one, one, np.zeros((8, 8), np.float32),
                             pupils.copy(), pupils.copy(), pupils.copy())
    _scatter_map_numba(pupils, origins, real[:, :4, :4].copy(), pupils, origins[:, 0].copy(), one, one, one,
                       np.zeros((8, 8), np.float32), spectrum, 0, 1, 0)
    no_batches = np.zeros((0, 2), np.int64)  # compiles (or loads) the fused lane without running an FFT
    _lane_numba(0, np.ones(1, np.int64), np.zeros((1, 4), np.int64), no_batches, spectrum, origins, pupils, pupils,
                fields, pupils.copy(), 1, True, real, real, False, np.float32(1e-6), False, *_checked_pupil_sums("warm_up", None, 1, 4),
                np.float32(1.0), *_map_arguments("warm_up", None, None, None, 1, 4))


def place_boxes(spectrum: np.ndarray, origins: np.ndarray, pupils: np.ndarray, fields: np.ndarray,
                start: int) -> None:
    """Write ``spectrum`` box × pupil of captures ``start …`` into the centre of each field, zeros elsewhere.

    Parameters
    ----------
    spectrum : ndarray, complex64, (M, M)
    origins : ndarray, int64, (K, 2)
        Top-left corner of every capture's box in ``spectrum``.
    pupils : ndarray, complex64, (K, b, b)
        Pupil boxes (with any scaling folded in).
    fields : ndarray, complex64, (k, m, m)
        Receives captures ``start … start + k - 1``; the box is centred on ``m // 2``.
    start : int
        Index of the first capture.

    Raises
    ------
    ValueError
        If dtypes or shapes do not fit, the captures are out of range or a box leaves the spectrum.
    """
    _check_boxes("place_boxes", spectrum, origins, pupils, fields, start)
    if _use_numba:
        bad = _place_boxes_numba(spectrum, origins, pupils, fields, start)
        if bad >= 0:
            raise _bad_box("place_boxes", origins, bad, spectrum.shape, pupils.shape[1])
    else:
        _check_origins_numpy("place_boxes", origins, start, fields.shape[0], spectrum.shape, pupils.shape[1])
        _place_boxes_numpy(spectrum, origins, pupils, fields, start)


def _magnitude(fields, amplitudes, weights, eps, keep, magnitude, misfit):
    """``ψ ← (w (A/max(|ψ|, ε) − 1) + keep) ψ`` in place; returns ``Σ w (|ψ| − A)²``.

    ``magnitude`` and ``misfit`` (or None) are work arrays for the numpy implementation.
    """
    if weights is None:
        contiguous = _check_alike("the magnitude projection", ("fields", "amplitudes"), (fields, amplitudes),
                                  (_C64, _F32))
    else:
        contiguous = _check_alike("the magnitude projection", ("fields", "amplitudes", "weights"),
                                  (fields, amplitudes, weights), (_C64, _F32, _F32))
    if _use_numba and contiguous:
        confidence = amplitudes if weights is None else weights
        return float(_magnitude_numba(fields, amplitudes, confidence, np.float32(eps), np.float32(keep),
                                      weights is not None))
    return _magnitude_numpy(fields, amplitudes, weights, eps, keep, magnitude, misfit)


def project_magnitudes(fields: np.ndarray, amplitudes: np.ndarray, scratch: np.ndarray, *,
                       weights: np.ndarray | None = None, eps: float = 1e-12) -> float:
    """Replace ``|ψ|`` by the measured amplitude, keeping the phase; return the squared misfit.

    ``ψ ← w · A ψ/max(|ψ|, ε) + (1 − w) · ψ`` with ``w = 1`` when no weights are given,
    in place; returns ``Σ w (|ψ| − A)²`` before the update.

    Parameters
    ----------
    fields : ndarray, complex64, (k, m, m)
    amplitudes : ndarray, float32, (k, m, m)
    scratch : ndarray, float32, (2, k, m, m)
        Work arrays for the numpy implementation.
    weights : ndarray, float32, (k, m, m), optional
    eps : float

    Raises
    ------
    ValueError
        If the arrays' dtypes or shapes differ from those above.
    """
    return _magnitude(fields, amplitudes, weights, eps, 1.0, scratch[0], scratch[1])


def scatter_boxes(fields: np.ndarray, origins: np.ndarray, pupils: np.ndarray, accumulator: np.ndarray,
                  start: int) -> None:
    """Add each field's centre box × pupil into ``accumulator`` at its capture's origin.

    Parameters
    ----------
    fields : ndarray, complex64, (k, m, m)
        Spectra of captures ``start …`` (box centred on ``m // 2``); the numpy
        implementation overwrites the boxes.
    origins : ndarray, int64, (K, 2)
    pupils : ndarray, complex64, (K, b, b)
        Adjoint pupil boxes (conjugate, with scaling folded in).
    accumulator : ndarray, complex64, (M, M)
    start : int

    Raises
    ------
    ValueError
        If dtypes or shapes do not fit, the captures are out of range or a box leaves the spectrum.
    """
    _check_boxes("scatter_boxes", accumulator, origins, pupils, fields, start)
    if _use_numba and _contiguous(fields, pupils, accumulator):
        bad = _scatter_numba(fields, origins, pupils, accumulator, start)
        if bad >= 0:
            raise _bad_box("scatter_boxes", origins, bad, accumulator.shape, pupils.shape[1])
    else:
        _check_origins_numpy("scatter_boxes", origins, start, fields.shape[0], accumulator.shape, pupils.shape[1])
        _scatter_numpy(fields, origins, pupils, accumulator, start)


def momentum_step(spectrum: np.ndarray, anchor: np.ndarray, velocity: np.ndarray, eta: float) -> tuple[float, float]:
    """mPIE momentum, in place: ``v ← η v + (S − S₀)``, ``S ← S + η v``, ``S₀ ← S``.

    Parameters
    ----------
    spectrum, anchor, velocity : ndarray, complex64, (M, M)
        Current spectrum S, the spectrum at the previous momentum step S₀, and the velocity v.
    eta : float
        Momentum η (0: the spectrum is left as it is, the anchor still follows it).

    Returns
    -------
    change, norm : float
        ``‖S_new − S₀‖²`` and ``‖S₀‖²``: the squared change since the previous step and its reference.

    Raises
    ------
    ValueError
        If the three arrays are not complex64 of one shape.
    """
    contiguous = _check_alike("momentum_step", ("spectrum", "anchor", "velocity"), (spectrum, anchor, velocity),
                              (_C64, _C64, _C64))
    if _use_numba and contiguous:
        change, norm = _momentum_numba(spectrum, anchor, velocity, np.float32(eta))
        return float(change), float(norm)
    norm = float(np.vdot(anchor.ravel(), anchor.ravel()).real)
    velocity *= np.float32(eta)
    velocity += spectrum - anchor
    spectrum += np.float32(eta) * velocity
    delta = spectrum - anchor
    np.copyto(anchor, spectrum)
    return float(np.vdot(delta.ravel(), delta.ravel()).real), norm


def tikhonov_update(numerator: np.ndarray, inverse_normal: np.ndarray, spectrum: np.ndarray) -> tuple[float, float]:
    """``numerator ← numerator · inverse_normal`` in place; return ``(‖numerator − spectrum‖², ‖spectrum‖²)``.

    Parameters
    ----------
    numerator : ndarray, complex64, (M, M)
        ``Σ A_iᴴ ψ_i``; becomes the new spectrum.
    inverse_normal : ndarray, float32, (M, M)
        ``1 / (Σ |P_i|² + τ)``.
    spectrum : ndarray, complex64, (M, M)
        The previous spectrum (read only).

    Raises
    ------
    ValueError
        If the arrays' dtypes or shapes differ from those above.
    """
    contiguous = _check_alike("tikhonov_update", ("numerator", "inverse_normal", "spectrum"),
                              (numerator, inverse_normal, spectrum), (_C64, _F32, _C64))
    if _use_numba and contiguous:
        change, norm = _tikhonov_numba(numerator, inverse_normal, spectrum)
        return float(change), float(norm)
    numerator *= inverse_normal
    delta = numerator - spectrum
    return (float(np.vdot(delta.ravel(), delta.ravel()).real),
            float(np.vdot(spectrum.ravel(), spectrum.ravel()).real))


def magnitude_step(fields: np.ndarray, amplitudes: np.ndarray, scratch: np.ndarray, *,
                   weights: np.ndarray | None = None, eps: float = 1e-12) -> float:
    """Replace ``ψ`` by the magnitude-projection step ``ψ' − ψ = w (A/|ψ| − 1) ψ``; return the misfit.

    The sequential engines add this difference, back-propagated, to the
    spectrum. ``|ψ|`` is floored at ``eps``. Returns ``Σ w (|ψ| − A)²``.

    The parameters are those of :func:`project_magnitudes`, except ``scratch``:
    one float32 (k, m, m) work array for the numpy implementation.
    """
    return _magnitude(fields, amplitudes, weights, eps, 0.0, scratch, None)


# ----------------------------------------------------------------------------- fused sequential lane
if _HAVE_NUMBA:  # pragma: no branch
    from llvmlite import ir
    from numba.extending import intrinsic

    @intrinsic
    def _call_address(typingctx, function, argument):  # pragma: no cover - compiled
        """Call the C function ``void f(void *)`` at address ``function`` with pointer ``argument``.

        The address arrives at run time, so the kernels that use this stay cacheable.
        """
        signature = numba.types.void(numba.types.int64, numba.types.int64)

        def codegen(context, builder, sig, args):
            pointer = ir.IntType(8).as_pointer()
            callee = builder.inttoptr(args[0], ir.FunctionType(ir.VoidType(), [pointer]).as_pointer())
            builder.call(callee, [builder.inttoptr(args[1], pointer)])
            return context.get_dummy_value()

        return signature, codegen

    @_jit
    def _lane_numba(execute, counts, plans, batches, spectrum, origins, pupils, factors, fields, boxes, chunk,
                    scatter, amplitudes, weights, weighted, eps, summed, discs, index, numerator, denominator,
                    sum_scale, mapped, map_discs, maps, map_index, forward_scale, alpha, tau, step,
                    coverage):  # pragma: no cover
        """Returns the lane's misfit, a status and the largest planned count it transformed.

        The status is -1, or the first capture whose box leaves the spectrum, or ``-2 - i`` for
        batch ``i`` outside the captures or larger than ``boxes``; nothing runs unless it is -1.
        A batch goes through the transforms ``chunk`` captures at a time (fields that stay in
        cache), keeping only each capture's update box; the boxes are scattered at the batch's end.
        ``mapped``: the pupils and factors are formed from a map model's parts instead of read.
        """
        b, m = boxes.shape[1], fields.shape[1]
        s = m // 2 - b // 2
        for i in range(batches.shape[0]):  # every batch and box is checked before anything runs
            start, stop = batches[i, 0], batches[i, 1]
            if start < 0 or stop <= start or stop > origins.shape[0] or stop - start > boxes.shape[0]:
                return 0.0, -2 - i, 0
            bad = _first_bad_box(origins, start, stop - start, spectrum.shape[0] - b, spectrum.shape[1] - b)
            if bad >= 0:
                return 0.0, bad, 0
        total = 0.0
        zero = np.float32(0.0)
        largest = 0
        for i in range(batches.shape[0]):
            start, stop = batches[i, 0], batches[i, 1]
            for first in range(start, stop, chunk):
                last = min(stop, first + chunk)
                k = last - first
                j = 0
                while counts[j] < k:
                    j += 1
                largest = max(largest, counts[j])
                if mapped:
                    _place_map_boxes_numba(spectrum, origins, map_discs, maps, map_index, forward_scale, fields[:k],
                                           first)
                else:
                    _place_boxes_numba(spectrum, origins, pupils, fields[:k], first)
                _call_address(execute, plans[j, 0])
                _call_address(execute, plans[j, 1])
                total += _magnitude_numba(fields[:k], amplitudes[first:last], weights[first:last], eps, zero,
                                          weighted)
                _call_address(execute, plans[j, 2])
                _call_address(execute, plans[j, 3])
                if summed:  # the pupil fit's sums, from the spectrum the batch saw (before its update)
                    _accumulate_pupil_numba(spectrum, origins, discs, fields[:k], first, index, numerator,
                                            denominator, sum_scale)
                for q in range(k):
                    boxes[first - start + q] = fields[q, s:s + b, s:s + b]
            if scatter and mapped:
                _scatter_map_numba(boxes[:stop - start], origins, map_discs, maps, map_index, alpha, tau, step,
                                   coverage, spectrum, start, stop, start)
            elif scatter:
                _scatter_numba(boxes[:stop - start], origins, factors, spectrum, start)
        return total, -1, largest


#: Bytes of fields a fused lane transforms together: about half a core's L2 cache.
_LANE_CHUNK_BYTES = 1 << 19


def lane_chunk(m: int) -> int:
    """Captures of ``m`` × ``m`` complex64 fields a fused lane transforms together (a power of two, at least 1).

    It depends on the field size alone, so a run is reproducible from machine to machine (the
    misfit's partial sums, which restarts compare, follow the chunks).
    """
    fitting = max(1, _LANE_CHUNK_BYTES // (8 * m * m))
    return 1 << (fitting.bit_length() - 1)


def can_fuse_lanes(raw_plans) -> bool:
    """Whether :func:`sequential_lane` can run with ``raw_plans`` (numba kernels and live raw FFTW plans)."""
    return _use_numba and isinstance(raw_plans, fft.RawFFTPlans) and not raw_plans.released


class MapPupils:
    """A map model's pupils ``P_i = D_i · A_p(i)`` and rPIE factors as parts, for lanes that form them on the fly.

    Forming each pupil where a lane places or scatters its box costs a few products, where stored
    pupils, pupil boxes and factors cost three (K, b, b) arrays rebuilt after every pupil step and
    read again in every pass: memory traffic is what lanes running side by side share. The products
    are those of :func:`map_pupil_factors`, so the results are bit-identical.

    Parameters
    ----------
    discs : ndarray, float32, (K, b, b), C-contiguous
        Each capture's NA disc on its box.
    maps : ndarray, complex64, (P, b, b), C-contiguous
    index : ndarray, int64, (K,)
        Map each capture uses.
    forward_scale : float
        Raw-FFT scaling of the forward pupil boxes.
    alpha, tau, scale : float
        The rPIE factors' parameters (:func:`rpie_factors`).

    Raises
    ------
    ValueError
        If an array has the wrong dtype, shape or layout, or ``index`` names a map that does not exist.
    """

    def __init__(self, discs: np.ndarray, maps: np.ndarray, index: np.ndarray, *, forward_scale: float,
                 alpha: float, tau: float, scale: float):
        self.discs, self.maps, self.index = discs, maps, index
        self.values = tuple(np.float32(v) for v in (forward_scale, alpha, tau, scale))
        self.check("MapPupils")

    def check(self, where: str) -> None:
        """Raise ValueError unless the parts fit together (run again before every compiled call: the arrays
        are the caller's, and may have changed since).
        """
        discs, maps, index = self.discs, self.maps, self.index
        named = (("discs", discs, _F32, 3), ("maps", maps, _C64, 3), ("index", index, _I64, 1))
        _check_arrays(where, named)
        for name, array, _, _ in named:
            if not array.flags.c_contiguous:
                raise ValueError(f"{where}: {name} must be C-contiguous, got {_describe(array)}")
        k, b = discs.shape[0], discs.shape[1]
        if discs.shape[2] != b or maps.shape[1:] != (b, b) or index.shape != (k,):
            raise ValueError(f"{where}: shapes do not fit together: discs {discs.shape}, maps {maps.shape}, "
                             f"index {index.shape} (need (K, b, b), (P, b, b) and (K,))")
        if index.size and (int(index.min()) < 0 or int(index.max()) >= maps.shape[0]):
            raise ValueError(f"{where}: index must name maps 0 … {maps.shape[0] - 1}")

    @property
    def box(self) -> int:
        """Box size ``b``."""
        return self.discs.shape[1]

    @property
    def count(self) -> int:
        """Captures ``K``."""
        return self.discs.shape[0]

    def pupils(self) -> np.ndarray:
        """Every capture's pupil, complex64 (K, b, b) (as :func:`map_pupil_factors` writes them)."""
        pupils = self.maps[self.index]   # a new array, scaled in place (the same products, no temporaries)
        pupils.real *= self.discs
        pupils.imag *= self.discs
        return pupils


_NO_MAP = None


def _map_arguments(where: str, map_pupils: MapPupils | None, coverage, spectrum, n: int, b: int) -> tuple:
    """The lane's map-model arguments, checked (placeholders without a map model)."""
    global _NO_MAP
    if map_pupils is None:
        if _NO_MAP is None:
            _NO_MAP = (False, np.zeros((1, 1, 1), _F32), np.zeros((1, 1, 1), _C64), np.zeros(1, _I64),
                       *(np.float32(0),) * 4, np.zeros((1, 1), _F32))
        return _NO_MAP
    if not isinstance(map_pupils, MapPupils):
        raise ValueError(f"{where}: map_pupils must be a MapPupils, got {type(map_pupils).__name__}")
    map_pupils.check(where)
    if map_pupils.count != n or map_pupils.box != b:
        raise ValueError(f"{where}: map_pupils hold {map_pupils.count} captures of {map_pupils.box}² boxes; "
                         f"need {n} of {b}²")
    if not (isinstance(coverage, _ndarray) and coverage.dtype == _F32 and coverage.flags.c_contiguous
            and coverage.shape == spectrum.shape):
        raise ValueError(f"{where}: coverage must be a C-contiguous float32 {spectrum.shape} array, "
                         f"got {_describe(coverage)}")
    return (True, map_pupils.discs, map_pupils.maps, map_pupils.index, *map_pupils.values, coverage)


def scatter_map_boxes(boxes: np.ndarray, origins: np.ndarray, map_pupils: MapPupils, coverage: np.ndarray,
                      accumulator: np.ndarray, batch: tuple[int, int], start: int) -> None:
    """Add captures ``start …``'s update boxes × their rPIE factors, formed from ``map_pupils``, to ``accumulator``.

    The factors are those :func:`map_pupil_factors` gives for the batch ``[batch[0], batch[1])``
    the captures belong to (its coverage is summed here, in ``coverage``, and left zero).

    Parameters
    ----------
    boxes : ndarray, complex64, (k, b, b), C-contiguous
    origins : ndarray, int64, (K, 2)
    map_pupils : MapPupils
    coverage : ndarray, float32, (M, M), C-contiguous
        Zero work array, left zero.
    accumulator : ndarray, complex64, (M, M), C-contiguous
    batch : (int, int)
        ``[start, stop)`` of the whole batch; captures ``start … start + k - 1`` lie in it.
    start : int

    Raises
    ------
    ValueError
        If an argument has the wrong dtype, shape or layout, the captures leave the batch or the
        batch the captures, or a box leaves the spectrum; nothing has run then.
    """
    if not _use_numba:
        raise ValueError("scatter_map_boxes needs the numba kernels")
    _check_arrays("scatter_map_boxes", (("origins", origins, _I64, 2), ("boxes", boxes, _C64, 3)))
    b = map_pupils.box if isinstance(map_pupils, MapPupils) else 0
    _check_boxes("scatter_map_boxes", accumulator, origins, np.broadcast_to(np.complex64(0), (len(origins), b, b)),
                 boxes, 0)
    if boxes.shape[1:] != (b, b):
        raise ValueError(f"scatter_map_boxes: boxes must be (k, {b}, {b}) update boxes, got {boxes.shape}")
    try:
        first, stop = (int(v) for v in batch)
    except (TypeError, ValueError):
        raise ValueError(f"scatter_map_boxes: batch must be two integers [start, stop), got {batch!r}") from None
    k = boxes.shape[0]
    if not (0 <= first <= start and start + k <= stop <= len(origins)):
        raise ValueError(f"scatter_map_boxes: captures {start} to {start + k - 1} must lie in the batch "
                         f"[{first}, {stop}) of the {len(origins)} captures")
    args = _map_arguments("scatter_map_boxes", map_pupils, coverage, accumulator, len(origins), b)
    if not _contiguous(boxes, accumulator, origins):
        raise ValueError("scatter_map_boxes: boxes, accumulator and origins must be C-contiguous")
    _check_origins_numpy("scatter_map_boxes", origins, first, stop - first, accumulator.shape, b)
    _, discs, maps, index, _, alpha, tau, scale, coverage = args
    _scatter_map_numba(boxes, origins, discs, maps, index, alpha, tau, scale, coverage, accumulator, first, stop,
                       start)


def sequential_lane(raw_plans, batches: np.ndarray, spectrum: np.ndarray, origins: np.ndarray,
                    pupils: np.ndarray | None, factors: np.ndarray | None, fields: np.ndarray, amplitudes: np.ndarray,
                    weights: np.ndarray | None, eps: float, pupil_sums: tuple | None = None,
                    boxes: np.ndarray | None = None, chunk: int | None = None, scatter: bool = True,
                    map_pupils: MapPupils | None = None, coverage: np.ndarray | None = None) -> float:
    """Run batches one after the other in one GIL-free call: place, inverse FFT, magnitude step, FFT, scatter.

    Each batch does what :meth:`~cca_cli.optics.forward.ForwardModel.forward_into`,
    :func:`magnitude_step`, the forward transform and :func:`scatter_boxes` do in turn, without
    returning to the interpreter in between, so two threads running lanes do not wait for each
    other. Requires :func:`can_fuse_lanes`. Every argument is checked before compiled code runs.

    A batch goes through the transforms ``chunk`` captures at a time, so the fields stay in the
    core's cache from the inverse FFT to the forward one; only each capture's update box is kept
    (in ``boxes``) until the batch's update is scattered. Memory traffic, not arithmetic, is what
    two cores running lanes side by side share.

    Parameters
    ----------
    raw_plans : RawFFTPlans
        :meth:`~cca_cli.optics.fft.BandedFFT2.raw_plans` of the workspace holding ``fields``; kept
        unchanged (and alive) while the lane runs.
    batches : ndarray, int64, (n, 2)
        ``[start, stop)`` of each batch, in order.
    spectrum : ndarray, complex64, (M, M), C-contiguous
        Updated in place.
    origins : ndarray, int64, (K, 2)
    pupils : ndarray, complex64, (K, b, b), or None
        Forward pupil boxes (scaling folded in); None with ``map_pupils``.
    factors : ndarray, complex64, (K, b, b), or None
        Update factors multiplying each capture's back-transformed step; None with ``map_pupils``.
    fields : ndarray, complex64, (c, m, m)
        The workspace buffer the plans were made for.
    amplitudes : ndarray, float32, (K, m, m)
    weights : ndarray, float32, (K, m, m), optional
    eps : float
        Floor on ``|ψ|``.
    pupil_sums : tuple, optional
        ``(discs, index, numerator, denominator)``: also add each batch's terms of the pupil
        fit (:func:`accumulate_pupil`) before its update is scattered.
    boxes : ndarray, complex64, (n, b, b), optional
        Work array for a batch's update boxes, at least as many as the largest batch holds
        (default: allocated here).
    chunk : int, optional
        Captures transformed together (default :func:`lane_chunk`; at most the workspace's capacity).
    scatter : bool
        False: run one batch and leave its update boxes in ``boxes`` (for :func:`scatter_boxes`
        with ``factors``, or :func:`scatter_map_boxes`), so that threads sharing a batch scatter
        their parts after all have read the spectrum.
    map_pupils : MapPupils, optional
        Form the pupil boxes and the factors from a map model's parts (in place of ``pupils`` and
        ``factors``); each batch's factors are those of :func:`map_pupil_factors`.
    coverage : ndarray, float32, (M, M), C-contiguous, optional
        Zero work array for ``map_pupils`` (left zero).

    Returns
    -------
    float
        The summed squared misfit ``Σ w (|ψ| − A)²`` of the lane.

    Raises
    ------
    ValueError
        If an argument has the wrong dtype, shape or layout, a batch is out of range or larger
        than ``boxes``, a box leaves the spectrum, or ``fields`` is not the planned buffer;
        nothing has run then.
    RuntimeError
        If the plans were released.
    """
    if not (_use_numba and isinstance(raw_plans, fft.RawFFTPlans)):
        raise ValueError("sequential_lane needs numba kernels and raw FFTW plans (see can_fuse_lanes)")
    if raw_plans.released:
        raise RuntimeError("sequential_lane: these raw FFTW plans were released; ask the workspace for new ones")
    if not (isinstance(fields, _ndarray) and fields.dtype == _C64 and fields.ndim == 3):
        raise ValueError(f"sequential_lane: fields must be a complex64 (c, m, m) array, got {_describe(fields)}")
    if map_pupils is not None:
        if pupils is not None or factors is not None:
            raise ValueError("sequential_lane: with map_pupils the pupils and factors are formed: pass None for both")
        _check_arrays("sequential_lane", (("origins", origins, _I64, 2),))
        b = map_pupils.box if isinstance(map_pupils, MapPupils) else 0
        pupils = factors = np.broadcast_to(np.complex64(0), (len(origins), b, b))   # shapes for the checks
    _check_boxes("sequential_lane", spectrum, origins, pupils, fields[:0], 0)
    n, m = origins.shape[0], fields.shape[1]
    mapping = _map_arguments("sequential_lane", map_pupils, coverage, spectrum, n, pupils.shape[1])
    if map_pupils is not None:
        pupils = factors = mapping[2][:0]   # unused: the kernel forms them
    confidence = amplitudes if weights is None else weights
    for name, array, dtype, shape in (("spectrum", spectrum, _C64, spectrum.shape), ("origins", origins, _I64, None),
                                      ("pupils", pupils, _C64, None),
                                      ("factors", factors, _C64, pupils.shape),
                                      ("amplitudes", amplitudes, _F32, (n, m, m)),
                                      ("weights", confidence, _F32, (n, m, m)), ("batches", batches, _I64, None)):
        if not (isinstance(array, _ndarray) and array.dtype == dtype and array.flags.c_contiguous
                and (shape is None or array.shape == shape)):
            wanted = "" if shape is None else f" {shape}"
            raise ValueError(f"sequential_lane: {name} must be a C-contiguous {dtype}{wanted} array, "
                             f"got {_describe(array)}")
    if batches.ndim != 2 or batches.shape[1] != 2:
        raise ValueError(f"sequential_lane: batches must be (n, 2) [start, stop) rows, got {batches.shape}")
    sums = _checked_pupil_sums("sequential_lane", pupil_sums, n, pupils.shape[1])
    b = pupils.shape[1]
    if boxes is None:
        if not scatter:
            raise ValueError("sequential_lane: scatter=False leaves the update in boxes: pass boxes")
        largest = int((batches[:, 1] - batches[:, 0]).max()) if batches.size else 0
        boxes = np.empty((min(max(largest, 1), max(n, 1)), b, b), np.complex64)   # batches are checked in the kernel
    if not (isinstance(boxes, _ndarray) and boxes.dtype == _C64 and boxes.ndim == 3 and boxes.shape[1:] == (b, b)
            and boxes.flags.c_contiguous):
        raise ValueError(f"sequential_lane: boxes must be a C-contiguous complex64 (n, {b}, {b}) array, "
                         f"got {_describe(boxes)}")
    chunk = lane_chunk(m) if chunk is None else int(chunk)
    if chunk < 1:
        raise ValueError(f"sequential_lane: chunk must be at least 1, got {chunk}")
    chunk = min(chunk, int(raw_plans.counts[-1]))
    if not scatter and batches.shape[0] != 1:
        raise ValueError(f"sequential_lane: scatter=False runs exactly one batch, got {batches.shape[0]}")
    with raw_plans.executing(fields) as held:
        total, status, held.largest = _lane_numba(held.execute, held.counts, held.plans, batches, spectrum, origins,
                                                  pupils, factors, fields, boxes, chunk, bool(scatter), amplitudes,
                                                  confidence,
                                                  weights is not None, np.float32(eps), pupil_sums is not None,
                                                  *sums, np.float32(1.0 / m), *mapping)
    if status >= 0:
        raise _bad_box("sequential_lane", origins, status, spectrum.shape, pupils.shape[1])
    if status < -1:
        start, stop = (int(v) for v in batches[-2 - status])
        raise ValueError(f"sequential_lane: batch {-2 - status} [{start}, {stop}) must lie within the {n} captures "
                         f"and hold at most {boxes.shape[0]} (the boxes' capacity)")
    return float(total)


_NO_SUMS = None


def _checked_pupil_sums(where: str, pupil_sums, n: int, b: int) -> tuple:
    """The pupil-fit arrays a fused lane adds to, checked (placeholders when there are none)."""
    global _NO_SUMS
    if pupil_sums is None:
        if _NO_SUMS is None:
            _NO_SUMS = (np.zeros((1, 1, 1), _F32), np.zeros(1, _I64), np.zeros((1, 1, 1), np.complex128),
                        np.zeros((1, 1, 1), np.float64))
        return _NO_SUMS
    discs, index, numerator, denominator = pupil_sums
    for name, array, dtype, shape in (("discs", discs, _F32, (n, b, b)), ("index", index, _I64, (n,)),
                                      ("numerator", numerator, np.complex128, None),
                                      ("denominator", denominator, np.float64, None)):
        if not (isinstance(array, _ndarray) and array.dtype == dtype and array.flags.c_contiguous
                and (shape is None or array.shape == shape)):
            raise ValueError(f"{where}: {name} must be a C-contiguous {np.dtype(dtype)} array"
                             f"{'' if shape is None else f' {shape}'}, got {_describe(array)}")
    pupils = numerator.shape[0]
    if numerator.shape != (pupils, b, b) or denominator.shape != numerator.shape:
        raise ValueError(f"{where}: numerator and denominator must both be (P, {b}, {b}), got {numerator.shape} "
                         f"and {denominator.shape}")
    if index.size and (int(index.min()) < 0 or int(index.max()) >= pupils):
        raise ValueError(f"{where}: index must name pupils 0 … {pupils - 1}")
    return discs, index, numerator, denominator


# ----------------------------------------------------------------------------- calibration support
def _rpie_factors_numpy(pupils, origins, batches, alpha, tau, scale, coverage, out):
    b = pupils.shape[1]
    for start, stop in batches:   # only the batches' pupils are read (others may not be filled yet)
        if stop <= start:
            continue
        for i in range(start, stop):
            y0, x0 = origins[i]
            coverage[y0:y0 + b, x0:x0 + b] += np.abs(pupils[i]) ** 2
        boxes = np.stack([coverage[y0:y0 + b, x0:x0 + b] for y0, x0 in origins[start:stop]])
        peak = float(np.max(boxes))
        out[start:stop] = scale * np.conj(pupils[start:stop]) / ((1.0 - alpha) * boxes + alpha * peak + tau + 1e-30)
        for i in range(start, stop):
            y0, x0 = origins[i]
            coverage[y0:y0 + b, x0:x0 + b] = 0


def _accumulate_pupil_numpy(spectrum, origins, discs, fields, start, index, numerator, denominator, scale):
    k, m, b = fields.shape[0], fields.shape[1], discs.shape[1]
    s = m // 2 - b // 2
    for j in range(k):
        i = start + j
        y0, x0 = origins[i]
        lit = discs[i] * spectrum[y0:y0 + b, x0:x0 + b]
        numerator[index[i]] += np.conj(lit) * (fields[j, s:s + b, s:s + b] * scale)
        denominator[index[i]] += np.abs(lit) ** 2


if _HAVE_NUMBA:  # pragma: no branch
    @_jit
    def _rpie_batch_numba(pupils, origins, start, stop, alpha, tau, scale, coverage, out):  # pragma: no cover
        """The factors of one batch ``[start, stop)`` (coverage left zero)."""
        b = pupils.shape[1]
        # Coverage only grows while it is summed, so the largest running value is the largest final one.
        peak = np.float32(0.0)
        for i in range(start, stop):
            y0, x0 = origins[i, 0], origins[i, 1]
            for r in range(b):
                p = pupils[i, r].view(np.float32)   # re, im interleaved: loops over floats vectorise
                row = coverage[y0 + r, x0:x0 + b]
                for c in range(b):
                    v = row[c] + (p[2 * c] * p[2 * c] + p[2 * c + 1] * p[2 * c + 1])
                    row[c] = v
                    peak = max(peak, v)
        floor = alpha * peak + tau + np.float32(1e-30)
        keep = np.float32(1.0) - alpha
        for i in range(start, stop):
            y0, x0 = origins[i, 0], origins[i, 1]
            for r in range(b):
                p = pupils[i, r].view(np.float32)
                o = out[i, r].view(np.float32)
                row = coverage[y0 + r, x0:x0 + b]
                for c in range(b):
                    q = scale / (keep * row[c] + floor)
                    o[2 * c] = p[2 * c] * q
                    o[2 * c + 1] = -p[2 * c + 1] * q
        for i in range(start, stop):
            y0, x0 = origins[i, 0], origins[i, 1]
            for r in range(b):
                coverage[y0 + r, x0:x0 + b] = 0

    @_jit
    def _rpie_factors_numba(pupils, origins, batches, alpha, tau, scale, coverage, out):  # pragma: no cover
        for n in range(batches.shape[0]):
            _rpie_batch_numba(pupils, origins, batches[n, 0], batches[n, 1], alpha, tau, scale, coverage, out)

    @_jit
    def _accumulate_pupil_numba(spectrum, origins, discs, fields, start, index, numerator, denominator,
                                scale):  # pragma: no cover - compiled
        k, m, b = fields.shape[0], fields.shape[1], discs.shape[1]
        s = m // 2 - b // 2
        for j in range(k):
            i = start + j
            y0, x0 = origins[i, 0], origins[i, 1]
            p = index[i]
            for r in range(b):
                # Rows as interleaved floats: the loop vectorises (the same float32 products, summed in float64).
                row = spectrum[y0 + r, x0:x0 + b].view(np.float32)
                field = fields[j, s + r, s:s + b].view(np.float32)
                disc = discs[i, r]
                first = numerator[p, r].view(np.float64)
                power = denominator[p, r]
                for c in range(b):
                    d = disc[c]
                    lr, li = d * row[2 * c], d * row[2 * c + 1]
                    gr, gi = field[2 * c] * scale, field[2 * c + 1] * scale
                    first[2 * c] += lr * gr + li * gi
                    first[2 * c + 1] += lr * gi - li * gr
                    power[c] += lr * lr + li * li


def rpie_factors(pupils: np.ndarray, origins: np.ndarray, batches: np.ndarray, *, alpha: float, tau: float,
                 scale: float, coverage: np.ndarray, out: np.ndarray) -> None:
    """Each capture's rPIE update factor ``scale · P_i* / ((1 − α) D_B + α max D_B + τ)``, batch by batch.

    ``D_B`` is the pupil power ``Σ_{i∈B} |P_i|²`` of the capture's batch B, on the spectrum grid.

    Parameters
    ----------
    pupils : ndarray, complex64, (K, b, b)
    origins : ndarray, int64, (K, 2)
        Box corners in the spectrum (the visiting order of ``pupils``).
    batches : ndarray, int64, (n, 2)
        ``[start, stop)`` of every batch.
    alpha, tau, scale : float
    coverage : ndarray, float32, (M, M), C-contiguous
        Zero work array, left zero.
    out : ndarray, complex64, (K, b, b), C-contiguous
        Receives the factors.

    Raises
    ------
    ValueError
        If an array has the wrong dtype, shape or layout, a batch leaves ``[0, K)`` or a box leaves
        the spectrum; nothing has run then.
    """
    _check_arrays("rpie_factors", (("pupils", pupils, _C64, 3), ("origins", origins, _I64, 2),
                                   ("batches", batches, _I64, 2), ("coverage", coverage, _F32, 2),
                                   ("out", out, _C64, 3)))
    n, b = pupils.shape[0], pupils.shape[1]
    if (pupils.shape[2] != b or origins.shape != (n, 2) or out.shape != pupils.shape or batches.shape[1:] != (2,)):
        raise ValueError(f"rpie_factors: shapes do not fit together: pupils {pupils.shape}, origins {origins.shape}, "
                         f"batches {batches.shape}, out {out.shape} (need (K, b, b), (K, 2), (n, 2), (K, b, b))")
    if batches.size and (batches.min() < 0 or batches.max() > n or (batches[:, 1] < batches[:, 0]).any()):
        raise ValueError(f"rpie_factors: batches must be [start, stop) rows within the {n} captures")
    _check_origins_numpy("rpie_factors", origins, 0, n, coverage.shape, b)
    if not (coverage.flags.c_contiguous and out.flags.c_contiguous):
        raise ValueError(f"rpie_factors: coverage and out must be C-contiguous, got {_describe(coverage)} and "
                         f"{_describe(out)}")
    if _use_numba:
        pupils = np.ascontiguousarray(pupils)   # the compiled loops read rows as interleaved floats
        _rpie_factors_numba(pupils, origins, batches, np.float32(alpha), np.float32(tau), np.float32(scale),
                            coverage, out)
    else:
        _rpie_factors_numpy(pupils, origins, batches, alpha, tau, scale, coverage, out)


def _map_pupil_factors_numpy(discs, maps, index, origins, batches, alpha, tau, scale, forward_scale, coverage,
                             pupils, boxes, factors):
    for start, stop in batches:
        pupils[start:stop] = discs[start:stop] * maps[index[start:stop]]
        boxes[start:stop] = pupils[start:stop] * np.float32(forward_scale)
    _rpie_factors_numpy(pupils, origins, batches, alpha, tau, scale, coverage, factors)


if _HAVE_NUMBA:  # pragma: no branch
    @_jit
    def _map_pupil_factors_numba(discs, maps, index, origins, batches, alpha, tau, scale, forward_scale, coverage,
                                 pupils, boxes, factors):  # pragma: no cover - compiled
        b = discs.shape[1]
        for n in range(batches.shape[0]):
            start, stop = batches[n, 0], batches[n, 1]
            for i in range(start, stop):   # the batch's pupils, then its factors while they are in cache
                for r in range(b):
                    a = maps[index[i], r].view(np.float32)
                    d = discs[i, r]
                    p, f = pupils[i, r].view(np.float32), boxes[i, r].view(np.float32)
                    for c in range(b):
                        re, im = d[c] * a[2 * c], d[c] * a[2 * c + 1]
                        p[2 * c], p[2 * c + 1] = re, im
                        f[2 * c], f[2 * c + 1] = re * forward_scale, im * forward_scale
            _rpie_batch_numba(pupils, origins, start, stop, alpha, tau, scale, coverage, factors)


if _HAVE_NUMBA:  # pragma: no branch
    # A map model's pupils P_i = D_i · A_p(i), formed where they are used (the same float32 products as
    # _map_pupil_factors_numba's, so results are bit-identical to placing and scattering stored arrays).
    @_jit
    def _map_coverage_numba(discs, maps, index, origins, start, stop, coverage):  # pragma: no cover - compiled
        """Add ``|P_i|²`` of captures ``start … stop - 1`` into ``coverage``; returns the largest sum."""
        b = discs.shape[1]
        peak = np.float32(0.0)
        for i in range(start, stop):
            y0, x0 = origins[i, 0], origins[i, 1]
            for r in range(b):
                a = maps[index[i], r].view(np.float32)
                d = discs[i, r]
                row = coverage[y0 + r, x0:x0 + b]
                for c in range(b):
                    re, im = d[c] * a[2 * c], d[c] * a[2 * c + 1]
                    v = row[c] + (re * re + im * im)
                    row[c] = v
                    peak = max(peak, v)
        return peak

    @_jit
    def _place_map_boxes_numba(spectrum, origins, discs, maps, index, forward_scale, fields,
                               start):  # pragma: no cover - compiled
        """:func:`_place_boxes_numba` with the pupil boxes ``forward_scale · P_i`` formed on the fly."""
        k, m, b = fields.shape[0], fields.shape[1], discs.shape[1]
        s = m // 2 - b // 2
        for j in range(k):
            i = start + j
            y0, x0 = origins[i, 0], origins[i, 1]
            for r in range(m):
                if r < s or r >= s + b:
                    fields[j, r, :] = 0
                    continue
                fields[j, r, :s] = 0
                fields[j, r, s + b:] = 0
                a = maps[index[i], r - s].view(np.float32)
                d = discs[i, r - s]
                x = spectrum[y0 + r - s, x0:x0 + b].view(np.float32)
                f = fields[j, r, s:s + b].view(np.float32)
                for c in range(b):
                    pr = (d[c] * a[2 * c]) * forward_scale
                    pi = (d[c] * a[2 * c + 1]) * forward_scale
                    xr, xi = x[2 * c], x[2 * c + 1]
                    f[2 * c] = xr * pr - xi * pi
                    f[2 * c + 1] = xr * pi + xi * pr

    @_jit
    def _scatter_map_numba(boxes, origins, discs, maps, index, alpha, tau, scale, coverage, accumulator,
                           batch_start, batch_stop, start):  # pragma: no cover - compiled
        """Scatter the update boxes of captures ``start …`` of batch ``[batch_start, batch_stop)`` with the
        rPIE factors of :func:`_rpie_batch_numba` formed on the fly from the batch's coverage (left zero)."""
        b = discs.shape[1]
        peak = _map_coverage_numba(discs, maps, index, origins, batch_start, batch_stop, coverage)
        floor = alpha * peak + tau + np.float32(1e-30)
        keep = np.float32(1.0) - alpha
        for j in range(boxes.shape[0]):
            i = start + j
            y0, x0 = origins[i, 0], origins[i, 1]
            for r in range(b):
                a = maps[index[i], r].view(np.float32)
                d = discs[i, r]
                f = boxes[j, r].view(np.float32)
                row = coverage[y0 + r, x0:x0 + b]
                out = accumulator[y0 + r, x0:x0 + b].view(np.float32)
                for c in range(b):
                    q = scale / (keep * row[c] + floor)
                    pr = (d[c] * a[2 * c]) * q
                    pi = -(d[c] * a[2 * c + 1]) * q
                    fr, fi = f[2 * c], f[2 * c + 1]
                    out[2 * c] += fr * pr - fi * pi
                    out[2 * c + 1] += fr * pi + fi * pr
        for i in range(batch_start, batch_stop):
            y0, x0 = origins[i, 0], origins[i, 1]
            for r in range(b):
                coverage[y0 + r, x0:x0 + b] = 0


def map_pupil_factors(discs: np.ndarray, maps: np.ndarray, index: np.ndarray, origins: np.ndarray,
                      batches: np.ndarray, *, alpha: float, tau: float, scale: float, forward_scale: float,
                      coverage: np.ndarray, pupils: np.ndarray, boxes: np.ndarray, factors: np.ndarray) -> None:
    """A map pupil model's pupils, forward pupil boxes and rPIE factors, for the captures of ``batches``.

    Each capture's pupil is ``P_i = D_i · A_{p(i)}`` (its NA disc times its pupil's map); this
    writes ``P_i``, ``forward_scale · P_i`` (the forward model's pupil boxes, raw-FFT scaling
    folded in) and the factors of :func:`rpie_factors`, batch by batch, so that a batch's pupils
    are still in cache when its factors are formed (a gather, a product, a copy and a scaling
    took a sweep of memory each). They are rebuilt after every pupil step.

    Parameters
    ----------
    discs : ndarray, float32, (K, b, b), C-contiguous
        Each capture's NA disc on its box.
    maps : ndarray, complex64, (P, b, b), C-contiguous
        The pupil maps.
    index : ndarray, int64, (K,)
        Map each capture uses.
    origins : ndarray, int64, (K, 2)
        Box corners in the spectrum.
    batches : ndarray, int64, (n, 2)
        ``[start, stop)`` of every batch to fill.
    alpha, tau, scale : float
        As in :func:`rpie_factors`.
    forward_scale : float
    coverage : ndarray, float32, (M, M), C-contiguous
        Zero work array, left zero.
    pupils, boxes, factors : ndarray, complex64, (K, b, b), C-contiguous
        Receive the pupils, the pupil boxes and the factors.

    Raises
    ------
    ValueError
        If an array has the wrong dtype, shape or layout, a batch leaves ``[0, K)``, ``index``
        names a map that does not exist or a box leaves the spectrum; nothing has run then.
    """
    named = (("discs", discs, _F32, 3), ("maps", maps, _C64, 3), ("index", index, _I64, 1),
             ("origins", origins, _I64, 2), ("batches", batches, _I64, 2), ("coverage", coverage, _F32, 2),
             ("pupils", pupils, _C64, 3), ("boxes", boxes, _C64, 3), ("factors", factors, _C64, 3))
    _check_arrays("map_pupil_factors", named)
    for name, array, _, _ in named:
        if not array.flags.c_contiguous:
            raise ValueError(f"map_pupil_factors: {name} must be C-contiguous, got {_describe(array)}")
    k, b = discs.shape[0], discs.shape[1]
    if (discs.shape[2] != b or maps.shape[1:] != (b, b) or index.shape != (k,) or origins.shape != (k, 2)
            or any(array.shape != discs.shape for array in (pupils, boxes, factors))):
        raise ValueError(f"map_pupil_factors: shapes do not fit together: discs {discs.shape}, maps {maps.shape}, "
                         f"index {index.shape}, origins {origins.shape}, pupils {pupils.shape}, boxes "
                         f"{boxes.shape}, factors {factors.shape} (need (K, b, b), (P, b, b), (K,), (K, 2) and "
                         "(K, b, b) for the three outputs)")
    if batches.shape[1:] != (2,) or (batches.size and (batches.min() < 0 or batches.max() > k
                                                       or (batches[:, 1] < batches[:, 0]).any())):
        raise ValueError(f"map_pupil_factors: batches must be [start, stop) rows within the {k} captures")
    if index.size and (int(index.min()) < 0 or int(index.max()) >= maps.shape[0]):
        raise ValueError(f"map_pupil_factors: index must name maps 0 … {maps.shape[0] - 1}")
    _check_origins_numpy("map_pupil_factors", origins, 0, k, coverage.shape, b)
    values = (np.float32(alpha), np.float32(tau), np.float32(scale), np.float32(forward_scale))
    if _use_numba:
        _map_pupil_factors_numba(discs, maps, index, origins, batches, *values, coverage, pupils, boxes, factors)
    else:
        _map_pupil_factors_numpy(discs, maps, index, origins, batches, alpha, tau, scale, forward_scale, coverage,
                                 pupils, boxes, factors)


def accumulate_pupil(spectrum: np.ndarray, origins: np.ndarray, discs: np.ndarray, fields: np.ndarray, start: int,
                     index: np.ndarray, numerator: np.ndarray, denominator: np.ndarray, scale: float) -> None:
    """Add a batch's terms of the closed-form pupil fit: ``Σ conj(D_i S_i) G_i`` and ``Σ |D_i S_i|²``.

    Parameters
    ----------
    spectrum : ndarray, complex64, (M, M)
        The spectrum the batch's fields were computed from (before its update).
    origins : ndarray, int64, (K, 2)
    discs : ndarray, float32, (K, b, b)
        Each capture's NA disc ``D_i``.
    fields : ndarray, complex64, (k, m, m)
        Raw forward transforms of the batch's data steps (pupil box centred on ``m // 2``).
    start : int
        Index of the batch's first capture.
    index : ndarray, int64, (K,)
        Pupil of each capture.
    numerator : ndarray, complex128, (P, b, b)
    denominator : ndarray, float64, (P, b, b)
    scale : float
        Converts the raw transform to the orthonormal one (``1/m``).

    Raises
    ------
    ValueError
        If an array has the wrong dtype or shape, a capture, pupil index or box is out of range;
        nothing has run then.
    """
    _check_arrays("accumulate_pupil", (("spectrum", spectrum, _C64, 2), ("origins", origins, _I64, 2),
                                       ("discs", discs, _F32, 3), ("fields", fields, _C64, 3),
                                       ("index", index, _I64, 1), ("numerator", numerator, np.dtype(np.complex128), 3),
                                       ("denominator", denominator, np.dtype(np.float64), 3)))
    n, b = discs.shape[0], discs.shape[1]
    k, m = fields.shape[0], fields.shape[1]
    if (discs.shape[2] != b or origins.shape != (n, 2) or index.shape != (n,) or fields.shape[2] != m or b > m
            or numerator.shape[1:] != (b, b) or denominator.shape != numerator.shape):
        raise ValueError(f"accumulate_pupil: shapes do not fit together: discs {discs.shape}, origins "
                         f"{origins.shape}, index {index.shape}, fields {fields.shape}, numerator {numerator.shape}, "
                         f"denominator {denominator.shape}")
    start = int(start)
    if start < 0 or start + k > n:
        raise ValueError(f"accumulate_pupil: captures {start} to {start + k - 1} are not among the {n} captures")
    used = index[start:start + k]
    if k and (used.min() < 0 or used.max() >= numerator.shape[0]):
        raise ValueError(f"accumulate_pupil: pupil indices must lie in [0, {numerator.shape[0]})")
    _check_origins_numpy("accumulate_pupil", origins, start, k, spectrum.shape, b)
    if _use_numba and _contiguous(spectrum, discs, fields, numerator, denominator):
        _accumulate_pupil_numba(spectrum, origins, discs, fields, start, index, numerator, denominator,
                                np.float32(scale))
    else:
        _accumulate_pupil_numpy(spectrum, origins, discs, fields, start, index, numerator, denominator, scale)
