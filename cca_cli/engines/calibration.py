"""Calibration of the forward model from the data: aperture positions and pupil aberration.

Positions are refined against a fixed spectrum estimate and a change is
accepted only where it lowers that capture's data misfit, so a calibrated
model never fits the data worse than the nominal one. The pupil model below
carries a Zernike phase; :func:`estimate_quadratic_aberration` finds its
quadratic part directly from the captures, and
:class:`~cca_cli.engines.momentum.SequentialMomentum` refines it jointly with
the object.

Pupil model
-----------
The aperture transmission is known to be a binary disc; only its phase is
unknown. Capture ``i`` has the pupil

    P_i(k) = circ(|k − c_i − δ_i| ≤ R) · exp(i Σ_j a_j B_j(k − c_i − δ_i))

with ``c_i`` the nominal centre, ``δ_i`` a sub-pixel position offset and
``B_j`` Zernike polynomials of radial order 2 to ``order`` (piston and tilt
are left out: tilt only shifts the image, which the object absorbs). The
coefficients ``a`` are shared by all captures (one scanned camera) or held per
capture (a camera array).

Position step
-------------
Each capture's offset moves to the best of itself and its eight neighbours
``δ + h·(±1 | 0, ±1 | 0)``, for a few decreasing ``h``, judged by that capture's
misfit with the pupil disc drawn at the fractional centre.

Quadratic aberrations are image shifts
--------------------------------------
A quadratic pupil phase ``(k − c_i)ᵀ Q (k − c_i)`` (defocus and the two
astigmatisms) equals a global quadratic phase on the object spectrum, a
constant, and the ramp ``−2 c_iᵀ Q k``: capture ``i`` sees the same (defocused)
object shifted by ``d_i = (m/π) Q c_i`` pixels of its m x m grid. Neighbours
``i, j`` are therefore shifted against each other by ``(m/π) Q (c_j − c_i)``,
the same for every pair with the same separation, which the phase correlation
of their images (summed over all such pairs) measures directly. This gives
``Q`` without a search, far beyond the ±0.05-wave basin of a gradient method.

On the periodic m grid the shifts are known only modulo m, so ``Q`` and
``Q + (π/s) N`` (``s`` the lattice step, ``N`` integer) explain a lattice scan
equally well: with ``R = 9``, ``s = 7`` px this makes 1 wave RMS of defocus
plus 1 wave of astigmatism indistinguishable from (0.17, −0.18) waves, with
the object carrying the difference. The estimate returns the smallest
member, so aberrations must stay within ``|Q_ab| < π/(2s)`` to be recovered.
"""

from __future__ import annotations

import numpy as np

from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel, Workspace, chunk_slices
from cca_cli.optics.pupil import circular_pupils
from cca_cli.optics.zernike import zernike_basis
from cca_cli.sampling.grid import BandLayout

__all__ = [
    "max_position_offset",
    "pupil_functions",
    "capture_misfits",
    "refine_positions",
    "quadratic_to_zernike",
    "estimate_quadratic_aberration",
    "defocus_zernike",
]

def max_position_offset(layout: BandLayout) -> float:
    """Largest position offset (pixels per axis) for which every pupil disc stays inside its box."""
    b = layout.box_size
    c = layout.box_centres
    margin = np.minimum(c - layout.pupil_radius_px, (b - 1) - c - layout.pupil_radius_px)
    return float(max(0.0, np.min(margin)))


def pupil_functions(layout: BandLayout, *, offsets=None, coefficients=None, order: int = 4) -> np.ndarray:
    """Pupils of the model above: binary discs at ``centre + offset`` with a Zernike phase.

    Parameters
    ----------
    layout : BandLayout
    offsets : array_like, (K, 2), optional
        Position offsets ``[dy, dx]`` (spectrum pixels); default zero.
    coefficients : array_like, (n_modes,) or (K, n_modes), optional
        Zernike coefficients (waves) shared or per capture; default zero.
    order : int
        Radial order the coefficients refer to.

    Returns
    -------
    ndarray, complex64, (K, b, b)
    """
    centres = layout.box_centres if offsets is None else layout.box_centres + np.asarray(offsets, np.float64)
    disc = circular_pupils(layout.box_size, centres, layout.pupil_radius_px).astype(np.complex64)
    if coefficients is None:
        return disc
    coefficients = np.asarray(coefficients, np.float64)
    if not np.any(coefficients):
        return disc
    basis = zernike_basis(layout.box_size, centres, layout.pupil_radius_px, order=order)
    if coefficients.ndim == 1:
        phase = np.tensordot(coefficients.astype(np.float32), basis, axes=(0, 0))
    else:
        phase = np.einsum("kn,nkyx->kyx", coefficients.astype(np.float32), basis)
    return (disc * np.exp(1j * phase)).astype(np.complex64)


def _misfit(fields: np.ndarray, amplitudes: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    diff = np.abs(fields) - amplitudes
    diff *= diff
    if weights is not None:
        diff *= weights
    return diff.sum(axis=(1, 2), dtype=np.float64)


def capture_misfits(model: ForwardModel, spectrum: np.ndarray, amplitudes: np.ndarray,
                    weights: np.ndarray | None = None, *, workspace: Workspace | None = None) -> np.ndarray:
    """Per-capture amplitude misfit ``Σ w (|A_i S| − √I_i)²``.

    Parameters
    ----------
    model : ForwardModel
    spectrum : ndarray, complex64, (M, M)
    amplitudes : ndarray, float32, (K, m, m)
        Measured amplitudes, field layout, in the model's capture order.
    weights : ndarray, float32, (K, m, m), optional
    workspace : Workspace, optional
        Reused when given (any capacity).

    Returns
    -------
    ndarray, float64, (K,)
    """
    workspace = workspace or model.workspace(min(32, model.n_images))
    out = np.empty(model.n_images, np.float64)
    for sl in chunk_slices(model.n_images, workspace.capacity):
        fields = model.forward_into(spectrum, sl, workspace)
        out[sl] = _misfit(fields, amplitudes[sl], None if weights is None else weights[sl])
    return out


def refine_positions(layout: BandLayout, spectrum: np.ndarray, amplitudes: np.ndarray,
                     weights: np.ndarray | None, offsets: np.ndarray, *, coefficients=None,
                     order: int = 4, steps=(0.5, 0.25), max_offset: float | None = None,
                     misfits: np.ndarray | None = None, workspace: Workspace | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Move each capture's position offset to whichever neighbour lowers its misfit.

    Parameters
    ----------
    layout : BandLayout
    spectrum : ndarray, complex64, (M, M)
    amplitudes, weights : ndarray, (K, m, m)
        Measurements in the layout's capture order (weights optional).
    offsets : ndarray, (K, 2)
        Current offsets (spectrum pixels).
    coefficients : array_like, optional
        Current Zernike coefficients (see :func:`pupil_functions`).
    order : int
    steps : sequence of float
        Trial step lengths h, tried in order (pixels).
    max_offset : float, optional
        Bound on ``|δ|`` per axis; default :func:`max_position_offset`.
    misfits : ndarray, (K,), optional
        Misfits of the current offsets, if known.
    workspace : Workspace, optional

    Returns
    -------
    offsets : ndarray, float64, (K, 2)
    misfits : ndarray, float64, (K,)
        Misfit of each capture at its returned offset (never above the input).
    """
    limit = max_position_offset(layout) if max_offset is None else float(max_offset)
    offsets = np.array(offsets, np.float64)

    def evaluate(trial: np.ndarray) -> np.ndarray:
        nonlocal workspace
        model = ForwardModel(layout, pupil_functions(layout, offsets=trial, coefficients=coefficients, order=order))
        workspace = workspace or model.workspace(min(32, layout.n_images))
        return capture_misfits(model, spectrum, amplitudes, weights, workspace=workspace)

    best = evaluate(offsets) if misfits is None else np.array(misfits, np.float64)
    for h in steps:
        for direction in ((h, 0.0), (-h, 0.0), (0.0, h), (0.0, -h), (h, h), (-h, -h), (h, -h), (-h, h)):
            trial = np.clip(offsets + np.asarray(direction), -limit, limit)
            moved = np.any(trial != offsets, axis=1)
            if not np.any(moved):
                continue
            score = evaluate(trial)
            better = moved & (score < best)
            offsets[better] = trial[better]
            best[better] = score[better]
    return offsets, best


def quadratic_to_zernike(quadratic, radius_px: float) -> np.ndarray:
    """Zernike coefficients (waves) of defocus, astigmatism and oblique astigmatism for a quadratic phase.

    Parameters
    ----------
    quadratic : array_like, (2, 2)
        Symmetric ``Q`` (radians per pixel², ``[y, x]`` order) of the phase ``kᵀ Q k``.
    radius_px : float
        Pupil radius R (pixels).

    Returns
    -------
    ndarray, float64, (3,)
        Coefficients of modes (2, 0), (2, 2), (2, −2) (see :func:`~cca_cli.optics.zernike.zernike_basis`).
    """
    q = np.asarray(quadratic, np.float64)
    defocus = 2.0 * np.pi * np.sqrt(3.0) * 2.0 / radius_px ** 2
    astigmatism = 2.0 * np.pi * np.sqrt(6.0) / radius_px ** 2
    return np.array([(q[1, 1] + q[0, 0]) / (2.0 * defocus),
                     (q[1, 1] - q[0, 0]) / (2.0 * astigmatism),
                     0.5 * (q[0, 1] + q[1, 0]) / astigmatism])


def _refine_peak(cross_power: np.ndarray, coarse: np.ndarray, upsample: int) -> np.ndarray:
    """Sub-pixel peak of ``ifft2(cross_power)`` near ``coarse``, to ``1/upsample`` px.

    The inverse transform is evaluated only on a 3 x 3 px window around the
    coarse peak, ``upsample`` times finer, by two small matrix products (a
    local DFT) instead of transforming an ``upsample`` times larger array.
    """
    offsets = np.arange(-1.5 * upsample, 1.5 * upsample + 1) / upsample
    kernels = [np.exp(2j * np.pi * np.outer(coarse[a] + offsets, np.fft.fftfreq(cross_power.shape[a])))
               for a in range(2)]
    window = np.dot(np.dot(kernels[0], cross_power), np.ascontiguousarray(kernels[1].T)).real
    best = np.unravel_index(np.argmax(window), window.shape)
    return coarse + offsets[list(best)]


def _circular_span(used: np.ndarray) -> tuple[int, int]:
    """Start and length of the shortest circular run of indices that holds every True of ``used``."""
    n = used.size
    if used.all():
        return 0, n
    gap_end, longest, run = 0, 0, 0
    for i in range(2 * n):   # the longest circular run of False ends just before the span starts
        run = 0 if used[i % n] else run + 1
        if run > longest:
            longest, gap_end = run, i
    start = (gap_end + 1) % n
    return start, n - min(longest, n)


def _recorded_region(images: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    """The images over the region their weights record, each less its mean and tapered to zero at the edges.

    A guard band (weight 0 around a recorded frame or tile, which may wrap around the periodic grid) is the
    same in every capture: left in, its edges would correlate at zero shift and outweigh the object's shifts.
    Pixels of weight 0 inside the region take the image's mean; a cosine taper over the outer eighth of each
    side removes the region's own edges.
    Without weights (a periodic, simulated frame) the images are used as they are.
    """
    if weights is None:   # a periodic (simulated) frame: no edges to remove
        return images
    weight = np.broadcast_to(np.asarray(weights, np.float32), images.shape)
    recorded = np.mean(weight > 0, axis=0) > 0.5
    if not recorded.any():
        return images * weight
    for axis, used in ((-2, recorded.any(axis=1)), (-1, recorded.any(axis=0))):
        start, length = _circular_span(used)
        keep = (np.arange(length) + start) % used.size   # the region may wrap around the periodic grid
        images, weight = np.take(images, keep, axis=axis), np.take(weight, keep, axis=axis)
    total = np.maximum(weight.sum(axis=(1, 2), dtype=np.float64), 1e-30)
    mean = (np.sum(images * weight, axis=(1, 2), dtype=np.float64) / total).astype(np.float32)[:, None, None]
    out = np.where(weight > 0, images, mean) - mean
    for axis, n in ((-2, out.shape[-2]), (-1, out.shape[-1])):
        taper = np.ones(n, np.float32)
        edge = max(1, n // 8)
        ramp = (0.5 - 0.5 * np.cos(np.pi * (np.arange(edge) + 0.5) / edge)).astype(np.float32)
        taper[:edge], taper[n - edge:] = ramp, ramp[::-1]
        out *= taper.reshape((-1, 1) if axis == -2 else (1, -1))
    return out


def estimate_quadratic_aberration(layout: BandLayout, amplitudes: np.ndarray,
                                  weights: np.ndarray | None = None, *, neighbour_ratio: float = 1.2,
                                  upsample: int = 8) -> np.ndarray:
    """Estimate a shared quadratic pupil aberration from the shifts between neighbouring captures.

    Parameters
    ----------
    layout : BandLayout
    amplitudes : ndarray, (K, m, m)
        Measured amplitudes ``√I`` (field or sensor layout: only shifts matter).
    weights : ndarray, (K, m, m), optional
        Validity weights: only the region most captures record is correlated, its weight-0 pixels at the
        image's mean (see :func:`_recorded_region`).
    neighbour_ratio : float
        Pairs closer than this times the smallest pupil spacing are correlated.
    upsample : int
        Sub-pixel factor of the correlation peak search.

    Returns
    -------
    ndarray, float64, (3,)
        Coefficients (waves) of modes (2, 0), (2, 2), (2, −2); zero when fewer
        than two independent neighbour directions exist.

    Notes
    -----
    See the module notes: for each neighbour separation ``u`` the normalised
    cross-power spectra of all pairs are summed and the peak of their inverse
    transform is ``(m/π) Q u`` modulo the correlated region's size (the recorded region, or m); ``Q``
    (symmetric) follows by least squares, weighted by each peak's height.
    """
    centres = layout.centres_px
    k, m = layout.n_images, layout.lowres_size
    if k < 3:
        return np.zeros(3)
    images = _recorded_region(np.square(np.asarray(amplitudes, np.float32)), weights)
    size = np.array(images.shape[-2:], np.float64)
    spectra = fft.fft2(images).astype(np.complex64)
    spectra[:, 0, 0] = 0.0
    separation = centres[None, :, :] - centres[:, None, :]
    distance = np.hypot(separation[..., 0], separation[..., 1])
    spacing = float(np.min(distance[distance > 1e-6]))
    close = (distance > 1e-6) & (distance <= neighbour_ratio * spacing)
    # One of each ± pair: the first non-zero component positive.
    forward = (separation[..., 0] > 1e-6) | ((np.abs(separation[..., 0]) <= 1e-6) & (separation[..., 1] > 0))
    first, second = np.nonzero(close & forward)
    keys = np.round(separation[first, second] / (0.05 * spacing)).astype(np.int64)
    groups, group_of = np.unique(keys, axis=0, return_inverse=True)
    group_of = group_of.ravel()
    rows, vectors, heights = [], [], []
    for g in range(groups.shape[0]):
        members = group_of == g
        cross = np.conj(spectra[first[members]]) * spectra[second[members]]
        cross /= np.abs(cross) + 1e-3 * np.abs(cross).max(axis=(1, 2), keepdims=True) + np.float32(1e-30)
        summed = cross.sum(axis=0)
        correlation = fft.ifft2(summed).real
        coarse = np.array(np.unravel_index(np.argmax(correlation), correlation.shape), np.float64)
        peak = _refine_peak(summed, coarse, upsample)
        peak = (peak + size / 2) % size - size / 2
        u = separation[first[members], second[members]].mean(axis=0)
        scale = m / np.pi
        # (m/π) Q u with q = (Q_yy, Q_xy, Q_xx).
        rows += [scale * np.array([u[0], u[1], 0.0]), scale * np.array([0.0, u[0], u[1]])]
        vectors += [peak[0], peak[1]]
        height = float(correlation.max() / (np.abs(correlation).mean() + 1e-300))
        heights += [height, height]
    system = np.array(rows) * np.array(heights)[:, None]
    if not np.all(np.isfinite(system)) or np.linalg.matrix_rank(system) < 3:  # featureless images: no shifts
        return np.zeros(3)
    q, *_ = np.linalg.lstsq(system, np.array(vectors) * np.array(heights), rcond=None)
    return quadratic_to_zernike([[q[0], q[1]], [q[1], q[2]]], layout.pupil_radius_px)


def defocus_zernike(defocus_m: float, *, wavelength_m: float, numerical_aperture: float,
                    order: int = 4) -> np.ndarray:
    """Zernike coefficients (waves) of the pupil phase a known defocus puts on an objective.

    The field a distance ``z`` from focus reaches the objective's pupil with the
    phase ``2π z (√(1/λ² − |f|²) − 1/λ)`` at spatial frequency ``f`` (``|f| ≤
    NA/λ``); its least-squares projection on the modes of
    :func:`~cca_cli.optics.zernike.zernike_modes` is returned (defocus and spherical terms).

    Parameters
    ----------
    defocus_m : float
        Distance of the object from the focal plane (m), in the sense of the
        propagator ``exp(i 2π z f_z)``.
    wavelength_m, numerical_aperture : float
    order : int
        Highest radial order of the returned modes.

    Returns
    -------
    ndarray, float64, (n_modes,)
    """
    size = 129
    centre = np.array([[(size - 1) / 2, (size - 1) / 2]])
    radius = (size - 1) / 2
    grid = (np.arange(size) - (size - 1) / 2) / radius
    rho2 = grid[:, None] ** 2 + grid[None, :] ** 2
    inside = rho2 <= 1
    frequency2 = rho2 * (numerical_aperture / wavelength_m) ** 2
    phase = 2 * np.pi * defocus_m * (np.sqrt(1 / wavelength_m ** 2 - frequency2) - 1 / wavelength_m)
    basis = zernike_basis(size, centre, radius, order=order)[:, 0]
    columns = np.stack([np.ones(inside.sum())] + [b[inside] for b in basis], axis=1)
    solution, *_ = np.linalg.lstsq(columns, phase[inside], rcond=None)
    return solution[1:]
