"""CuPy kernels that do a batched engine step in one launch instead of eight or ten.

On a GPU the batched momentum engine is bound by launches, not arithmetic: a call of 24
blood-smear captures spends about 0.2 ms on each of its data step and pupil sums, most of it in
the small elementwise operations (abs, subtract, square, maximum, divide, conj, casts) each of
which is one launch. The kernels here fuse them:

* :func:`box_fields`: gather each capture's spectrum box, multiply by its pupil and place it in the
  middle of a zeroed field (four launches and a temporary before);
* :func:`data_step`: the amplitude data step ``ψ ← w (A/max(|ψ|, ε) − 1) ψ`` of
  :func:`~cca_cli.engines.batched.project` (``keep=False``) and its misfit ``Σ w (|ψ| − A)²``;
* :func:`add_pupil_sums`: a shared map pupil's sums ``Σ_k conj(D_k S_k) r_k / m`` and
  ``Σ_k |D_k S_k|²``, one thread per pupil pixel looping over the call's captures, added in
  float64 into the sums in place;
* :func:`gather_add`: multiply by the rPIE factors (or the adjoint pupils) and add the boxes into the
  spectrum, one thread per spectrum pixel adding the boxes that cover it in capture order (a
  :class:`GatherPlan` made once per arrangement says which). Atomic adds would be as fast, but
  their order, and so the rounding, changes from run to run; this way a GPU run repeats bit for bit.

The kernels are compiled on first use; :func:`available` compiles them and checks them against
the numpy-style operations once per process, and the engine uses them only where that check
passed (a CuPy build that cannot compile them runs the operations one by one, as before, after
one warning).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from types import ModuleType

import numpy as np

__all__ = ["available", "box_fields", "data_step", "add_pupil_sums", "GatherPlan", "gather_plan", "gather_add"]

_DATA_STEP = ("float32 target, float32 weight, float32 eps", "complex64 field, float32 squared", """
    const float magnitude = abs(field);
    const float misfit = magnitude - target;
    squared = weight * misfit * misfit;
    field = field * (weight * (target / max(magnitude, eps) - 1.0f));
""")

_FIELDS = ("raw complex64 spectrum, raw int64 index, raw complex64 pupils, int32 m, int32 b, int32 start",
           "complex64 field", """
    const ptrdiff_t capture = i / ((ptrdiff_t)m * m);
    const int y = (int)((i / m) % m) - start, x = (int)(i % m) - start;
    if (y >= 0 && y < b && x >= 0 && x < b) {
        const ptrdiff_t n = (capture * b + y) * b + x;
        field = spectrum[index[n]] * pupils[n];
    } else {
        field = complex<float>(0.0f, 0.0f);
    }
""")

_GATHER_PRODUCTS = ("raw complex64 values, raw complex64 factors, raw int64 order, raw int64 starts, "
                    "raw int64 pixels", "raw complex64 target", """
    const ptrdiff_t pixel = pixels[i];
    complex<float> sum = target[pixel];
    for (ptrdiff_t e = starts[i]; e < starts[i + 1]; ++e) {
        const ptrdiff_t q = order[e];
        sum += values[q] * factors[q];
    }
    target[pixel] = sum;
""")

_GATHER_VALUES = ("raw float32 values, raw int64 order, raw int64 starts, raw int64 pixels", "raw float32 target", """
    const ptrdiff_t pixel = pixels[i];
    float sum = target[pixel];
    for (ptrdiff_t e = starts[i]; e < starts[i + 1]; ++e) {
        sum += values[order[e]];
    }
    target[pixel] = sum;
""")

_PUPIL_SUMS = ("raw float32 discs, raw complex64 spectrum, raw int64 index, raw complex64 residuals, int32 count, "
               "int32 area, float32 scale", "complex128 first, float64 power", """
    double re = 0.0, im = 0.0, pw = 0.0;
    for (int j = 0; j < count; ++j) {
        const ptrdiff_t n = (ptrdiff_t)j * area + i;
        const complex<float> lit = spectrum[index[n]] * discs[n];
        const complex<float> r = residuals[n];
        re += (double)(lit.real() * r.real() + lit.imag() * r.imag());
        im += (double)(lit.real() * r.imag() - lit.imag() * r.real());
        pw += (double)(lit.real() * lit.real() + lit.imag() * lit.imag());
    }
    first += complex<double>(re * scale, im * scale);
    power += pw;
""")


@functools.lru_cache(maxsize=None)
def _kernels(xp: ModuleType) -> tuple:
    return (xp.ElementwiseKernel(*_DATA_STEP, "cca_data_step"),
            xp.ElementwiseKernel(*_PUPIL_SUMS, "cca_pupil_sums"),
            xp.ElementwiseKernel(*_FIELDS, "cca_fields"),
            xp.ElementwiseKernel(*_GATHER_PRODUCTS, "cca_gather_products"),
            xp.ElementwiseKernel(*_GATHER_VALUES, "cca_gather_values"))


def box_fields(xp: ModuleType, spectrum, index, pupils, m: int):
    """Fields ``F⁻¹``-ready: each capture's box ``spectrum.flat[index] · pupil`` in the middle of an m x m grid.

    Parameters
    ----------
    xp : module
        CuPy.
    spectrum : complex64 (M, M), C-contiguous
    index : int64 (k, b, b), C-contiguous
        Flat spectrum index of every box pixel.
    pupils : complex64 (k, b, b), C-contiguous
    m : int
        Field side; the box starts at ``m // 2 − b // 2``.

    Returns
    -------
    complex64 (k, m, m)
        Zero outside the boxes (what :meth:`~cca_cli.engines.batched.BoxOperator.fields` transforms).
    """
    b = index.shape[1]
    out = xp.empty((index.shape[0], m, m), xp.complex64)
    _kernels(xp)[2](spectrum, index, pupils, np.int32(m), np.int32(b), np.int32(m // 2 - b // 2), out)
    return out


@dataclass(frozen=True)
class GatherPlan:
    """Which box pixels add into which target pixel, in capture order (:func:`gather_plan`).

    Attributes
    ----------
    order : int64 (n,)
        Flat positions into the boxes (``(k, b, b)``), grouped by target pixel; within a group in
        increasing position, so in capture order.
    starts : int64 (p + 1,)
        Where each target pixel's group begins in ``order`` (and the end).
    pixels : int64 (p,)
        The flat target index of each group.
    """

    order: object
    starts: object
    pixels: object


def gather_plan(xp: ModuleType, index) -> GatherPlan:
    """The :class:`GatherPlan` of boxes whose pixels add into ``target.flat[index]``.

    Parameters
    ----------
    xp : module
        numpy or CuPy (the plan's arrays live there).
    index : int64 (k, b, b)
        Flat target index of every box pixel.
    """
    flat = index.reshape(-1)
    order = xp.argsort(flat, kind="stable")
    ordered = flat[order]
    first = xp.ones(ordered.shape, bool)
    first[1:] = ordered[1:] != ordered[:-1]
    starts = xp.nonzero(first)[0].astype(xp.int64)
    pixels = ordered[starts]
    return GatherPlan(order.astype(xp.int64), xp.concatenate([starts, xp.asarray([flat.size], xp.int64)]),
                      xp.ascontiguousarray(pixels))


def gather_add(xp: ModuleType, target, plan: GatherPlan, values, factors=None) -> None:
    """``target.flat[index] += values · factors``, each target pixel's terms added in capture order.

    Parameters
    ----------
    xp : module
        CuPy.
    target : complex64 (with ``factors``) or float32 (without), C-contiguous
    plan : GatherPlan
        From :func:`gather_plan` of the boxes' target index.
    values : complex64 or float32 (k, b, b), any strides
    factors : complex64 (k, b, b), any strides, or None
    """
    if not target.flags.c_contiguous:   # a copy would take the sums and drop them
        raise ValueError("fused.gather_add: target must be C-contiguous")
    size, flat = int(plan.pixels.size), target.reshape(-1)
    if not size:
        return
    if factors is None:
        _kernels(xp)[4](values, plan.order, plan.starts, plan.pixels, flat, size=size)
    else:
        _kernels(xp)[3](values, factors, plan.order, plan.starts, plan.pixels, flat, size=size)


def data_step(xp: ModuleType, fields, targets, weights, eps: float, squared=None):
    """``fields ← w (A/max(|ψ|, ε) − 1) ψ`` in place; returns ``Σ w (|ψ| − A)²`` (a float64 device scalar).

    Parameters
    ----------
    xp : module
        CuPy.
    fields : complex64 (k, m, m), C-contiguous
    targets : float32 (k, m, m)
        Measured amplitudes ``A``.
    weights : float32 (k, m, m) or None
    eps : float
        Floor on ``|ψ|``.
    squared : float32 (k, m, m), C-contiguous, optional
        Receives each pixel's ``w (|ψ| − A)²`` instead of their sum (None is returned): a caller that
        sums many calls' misfits sums once (a reduction costs a launch and its set-up on every call).
    """
    given = squared is not None
    if given and (squared.shape != fields.shape or squared.dtype != np.float32 or not squared.flags.c_contiguous):
        raise ValueError("fused.data_step: squared must be a C-contiguous float32 array shaped as the fields")
    if not given:
        squared = xp.empty(fields.shape, xp.float32)
    weight = xp.float32(1.0) if weights is None else weights
    _kernels(xp)[0](targets, weight, xp.float32(eps), fields, squared)
    return None if given else squared.sum(dtype=xp.float64)


def add_pupil_sums(xp: ModuleType, first, power, discs, spectrum, index, residuals, scale: float) -> None:
    """Add ``Σ_k conj(D_k S_k) r_k · scale`` to ``first`` and ``Σ_k |D_k S_k|²`` to ``power`` (one shared pupil).

    Parameters
    ----------
    xp : module
        CuPy.
    first : complex128 (b, b), C-contiguous
    power : float64 (b, b), C-contiguous
    discs : float32 (k, b, b)
        Each capture's NA disc ``D_k``.
    spectrum : complex64 (M, M), C-contiguous
        The spectrum the call read (its boxes ``S_k``), not yet updated.
    index : int64 (k, b, b), C-contiguous
        Flat spectrum index of every box pixel.
    residuals : complex64 (k, b, b), any strides
        The call's data-step spectra ``r_k``.
    scale : float
    """
    count, b = index.shape[0], index.shape[1]
    _kernels(xp)[1](discs, spectrum, index, residuals, np.int32(count), np.int32(b * b), xp.float32(scale), first,
                    power)


def _reference_data_step(xp, fields, targets, weights, eps):
    magnitude = xp.abs(fields)
    squared = xp.sum(weights * xp.square(magnitude - targets), dtype=xp.float64)
    fields *= weights * (targets / xp.maximum(magnitude, xp.float32(eps)) - 1)
    return squared


@functools.lru_cache(maxsize=None)
def available(xp: ModuleType) -> bool:
    """Whether the fused kernels compile on ``xp`` (CuPy) and agree with the operations they replace.

    False for numpy, and (after one warning naming the reason) where compiling or the check fails.
    """
    if xp is np:
        return False
    try:
        rng = np.random.default_rng(0)
        shape = (3, 8, 8)
        psi = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
        targets = rng.uniform(0, 2, shape).astype(np.float32)
        weights = rng.uniform(0.5, 1, shape).astype(np.float32)
        got = xp.array(psi)   # a copy on either module
        misfit = float(data_step(xp, got, xp.asarray(targets), xp.asarray(weights), 1e-3))
        expected = psi.copy()
        expected_misfit = float(_reference_data_step(np, expected, targets, weights, 1e-3))
        ok = (np.allclose(xp.asnumpy(got), expected, rtol=1e-5, atol=1e-6)
              and np.isclose(misfit, expected_misfit, rtol=1e-5))
        got = xp.array(psi)   # without weights: the kernel then takes a scalar weight (another compiled form)
        misfit = float(data_step(xp, got, xp.asarray(targets), None, 1e-3))
        expected = psi.copy()
        expected_misfit = float(_reference_data_step(np, expected, targets, np.float32(1.0), 1e-3))
        ok = ok and (np.allclose(xp.asnumpy(got), expected, rtol=1e-5, atol=1e-6)
                     and np.isclose(misfit, expected_misfit, rtol=1e-5))
        # three overlapping 8 x 8 boxes of a 16 x 16 spectrum, placed on a 12 x 12 field grid
        spectrum = (rng.standard_normal((16, 16)) + 1j * rng.standard_normal((16, 16))).astype(np.complex64)
        origins = np.array([[0, 0], [3, 5], [8, 8]])
        index = ((origins[:, 0, None, None] + np.arange(8)[None, :, None]) * 16
                 + origins[:, 1, None, None] + np.arange(8)[None, None, :]).astype(np.int64)
        seen = spectrum.reshape(-1)[index]
        pupils = (seen * 0.5j).astype(np.complex64)
        got = box_fields(xp, xp.asarray(spectrum), xp.asarray(index), xp.asarray(pupils), 12)
        expected = np.zeros((3, 12, 12), np.complex64)
        expected[:, 2:10, 2:10] = seen * pupils
        ok = ok and np.allclose(xp.asnumpy(got), expected, rtol=1e-6, atol=1e-6)
        discs = rng.uniform(0, 1, shape).astype(np.float32)
        wide = (rng.standard_normal((3, 12, 12)) + 1j * rng.standard_normal((3, 12, 12))).astype(np.complex64)
        residuals = wide[:, 2:10, 2:10]                      # strided, as the engine's spectra are
        first, power = xp.zeros((8, 8), xp.complex128), xp.zeros((8, 8), xp.float64)
        add_pupil_sums(xp, first, power, xp.asarray(discs), xp.asarray(spectrum), xp.asarray(index),
                       xp.asarray(wide)[:, 2:10, 2:10], 0.5)
        lit = discs * seen
        ok = ok and np.allclose(xp.asnumpy(first), (np.conj(lit) * residuals).sum(axis=0) * 0.5, rtol=1e-5, atol=1e-5)
        ok = ok and np.allclose(xp.asnumpy(power), np.square(np.abs(lit)).sum(axis=0), rtol=1e-5, atol=1e-5)
        start = (rng.standard_normal((16, 16)) + 1j * rng.standard_normal((16, 16))).astype(np.complex64)
        target = xp.asarray(start)
        plan = gather_plan(xp, xp.asarray(index))
        gather_add(xp, target, plan, xp.asarray(wide)[:, 2:10, 2:10], xp.asarray(pupils))
        added = start.reshape(-1).copy()
        np.add.at(added, index.reshape(-1), (residuals * pupils).reshape(-1))
        ok = ok and np.allclose(xp.asnumpy(target).reshape(-1), added, rtol=1e-5, atol=1e-5)
        coverage = xp.zeros(256, xp.float32)
        gather_add(xp, coverage, plan, xp.asarray(discs))
        summed = np.zeros(256, np.float32)
        np.add.at(summed, index.reshape(-1), discs.reshape(-1))
        ok = ok and np.allclose(xp.asnumpy(coverage), summed, rtol=1e-5, atol=1e-6)
        if not ok:
            raise ValueError("the fused kernels disagree with the operations they replace")
        return True
    except Exception as exc:   # a CuPy that cannot compile them still runs the engine, one operation at a time
        warnings.warn(f"fused GPU kernels unavailable ({type(exc).__name__}: {str(exc).splitlines()[0][:160]}); "
                      "running each step's operations one by one", RuntimeWarning, stacklevel=2)
        return False
