"""Pupil recovery: closed-form (Gauss–Newton) pupil updates from the residuals of one pass.

Capture ``i`` sees the spectrum box ``S_i`` through its pupil
``P_i = D_i · A_{p(i)}``: the binary disc ``D_i`` of the objective's NA at the
capture's (fractional) pupil centre, times the aberration ``A_p`` of the pupil
``p(i)`` it uses (one shared pupil for a scanned camera or an LED array, one
per camera for a camera array). A pass of a sequential engine forms, for every
capture, the data step ``G_i = F(ψ'_i − ψ_i)`` on its pupil box. The
linearised least-squares fit of a pupil change to all of them,

    min_ΔA Σ_i ‖ G_i − D_i S_i ΔA_{p(i)} ‖²,

has the closed form (EPRY's pupil step, summed over the pass instead of one
capture at a time)

    ΔA_p = Σ_{i: p(i)=p} conj(D_i S_i) G_i / (Σ_{i: p(i)=p} |D_i S_i|² + δ),

which weighs every capture by the light it carries: dark-field images, whose
noise would dominate a per-image normalised step, contribute little. Two
models of ``A`` are fitted this way:

``full``
    ``A`` is a complex map on the pupil-box grid (amplitude and phase inside
    the NA), EPRY-style. Its Zernike content is reported as a projection.
``zernike``
    ``A = exp(i Σ_j a_j B_j)`` with Zernike modes from defocus up to a radial
    order (tilt and piston are left out: a tilt only shifts the image, which
    the object absorbs). The modes are evaluated at each capture's fractional
    pupil centre, and the coefficients take the Gauss–Newton step of the same
    linearised fit (see :mod:`cca_cli.engines.calibration`).

A step after which the next pass fits the data worse is undone and the step
size halved, so recovery on data from a perfect pupil stays at (nearly) no
aberration.

References
----------
Ou, Zheng & Yang, Opt. Express 22(5) (2014) (EPRY); Tian et al., Biomed. Opt.
Express 5(7) (2014) (Gauss–Newton pupil update).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cca_cli.engines.lattice import capture_lattice, periodic_filter
from cca_cli.engines.options import PUPIL_MODELS
from cca_cli.optics import kernels
from cca_cli.optics.pupil import circular_pupils
from cca_cli.optics.zernike import zernike_basis, zernike_modes
from cca_cli.sampling.grid import BandLayout

__all__ = ["PUPIL_MODELS", "PupilEstimate", "PupilRecovery", "tilt_of", "untilt_ramp", "resample_pupil"]

#: Largest change of any Zernike coefficient in one step (waves): the linearisation holds within ~0.05.
_MAX_ZERNIKE_STEP = 0.1


@dataclass(frozen=True)
class PupilEstimate:
    """Recovered pupils.

    Attributes
    ----------
    maps : ndarray, complex64, (P, b, b)
        Aberration of each pupil on the pupil-box grid (1 where unaberrated), centred on the box.
    coefficients : ndarray, float64, (P, n_modes)
        Zernike phase coefficients (waves) of each pupil: fitted (``zernike``) or
        projected from the map's phase (``full``).
    modes : tuple of (int, int)
        Zernike (radial order, azimuthal frequency) of each coefficient.
    model : str
    """

    maps: np.ndarray
    coefficients: np.ndarray
    modes: tuple[tuple[int, int], ...]
    model: str


@dataclass(frozen=True)
class _Step:
    """What undoing a pupil step needs: the state before it, the misfit that led to it, its normalisation."""

    maps: np.ndarray
    coefficients: np.ndarray
    misfit: float
    scale: complex
    tilt: np.ndarray
    reference: np.ndarray | None = None


def resample_pupil(pupil: np.ndarray, box_size: int, radius_px: float) -> np.ndarray:
    """A pupil given with its NA disc inscribed in an (n, n) array, on a pupil box of ``box_size``.

    The disc lands centred on the box at ``(box_size − 1)/2`` with radius
    ``radius_px``; values are interpolated linearly (real and imaginary parts),
    and outside the given array the nearest edge value is kept.

    Returns
    -------
    ndarray, complex64, (box_size, box_size)
    """
    from scipy import ndimage

    pupil = np.asarray(pupil, np.complex64)
    n = pupil.shape[0]
    grid = (np.arange(box_size) - (box_size - 1) / 2.0) / radius_px  # unit disc coordinates
    source = (n - 1) / 2.0 + grid * (n / 2.0)
    rows, cols = np.meshgrid(source, source, indexing="ij")
    sample = lambda part: ndimage.map_coordinates(part, [rows, cols], order=1, mode="nearest")
    return (sample(pupil.real) + 1j * sample(pupil.imag)).astype(np.complex64)


def tilt_of(field: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted mean phase gradient ``[gy, gx]`` (radians per pixel) of a complex map, free of wrapping."""
    gy = np.angle(np.sum(weights[1:, :] * weights[:-1, :] * field[1:, :] * np.conj(field[:-1, :])))
    gx = np.angle(np.sum(weights[:, 1:] * weights[:, :-1] * field[:, 1:] * np.conj(field[:, :-1])))
    return np.array([gy, gx])


def untilt_ramp(tilt: np.ndarray, size: int) -> np.ndarray:
    """``exp(−i (t_y y + t_x x))`` on a ``size`` × ``size`` box (pixel indices): multiplying by it takes tilt ``t`` off."""
    grid = np.arange(size, dtype=np.float64)
    return np.exp(-1j * (tilt[0] * grid[:, None] + tilt[1] * grid[None, :]))


#: A pass whose misfit exceeds the one before the last pupil step by this factor undoes a lattice-filtered map's
#: step (and the engine the pass's spectrum): a step that far off is not the filter's doing. The first map step,
#: taken from the object of one pass, makes the misfit leap 3–30 times on simulated LED arrays through 0.05–0.3
#: waves of defocus (kept, it left them at a correlation of 0.5–0.96 with the truth) and 2–16 times on the
#: recorded corpus (benchmarks/README.md, run 19).
SHARP_RISE = 3.0


class PupilRecovery:
    """Pupil estimates of a sequential engine and their pass-wise update.

    Parameters
    ----------
    layout : BandLayout
        Pupil boxes in the engine's capture order.
    pupil_index : ndarray, int, (K,)
        Pupil used by each capture (engine order), ``0 … P-1``.
    model : {"full", "smooth", "zernike"}
    order : int
        Highest Zernike radial order (2, 3 or 4).
    coefficients : ndarray, (P, n_modes), optional
        Starting Zernike coefficients (waves).
    amplitude : bool
        ``full`` model: recover the pupil's amplitude as well as its phase.
    step : float
        Initial step fraction in (0, 1].
    threads : int
        Number of threads that accumulate (each has its own sums).
    offsets : ndarray, (K, 2), optional
        Position offsets of the pupil centres from the layout's (spectrum pixels).
    maps : ndarray, complex, (b, b) or (P, b, b), optional
        Starting aberration maps on the box grid (``full``); for ``zernike`` their
        phase is projected on the modes.
    tilt : {"pupil", "object", "pinned"}
        Map models: a phase tilt the step finds stays in the pupil (the object stays
        where the captures put it), is handed to the object (which then moves with
        it; the model's predictions are the same), or is removed.
    smoothing : float
        ``smooth`` model: width (in pupil radii) of the Gaussian the phase left over by
        the Zernike modes is smoothed with.
    lattice : {"free", "filtered"}
        Map models: ``filtered`` removes from the maps, after each step, the patterns
        periodic on the lattice of the pupil centres, where they lie on one
        (:func:`~cca_cli.engines.lattice.periodic_filter`).
    damping : float
        Map models: a pixel's step is its sum of corrections over the light it saw
        plus ``damping`` times the most light any pixel saw (the Tikhonov weight of
        the averaged EPRY step): the larger, the less pixels that saw little light move.
    momentum : float
        Map models: each step adds ``momentum`` times the running sum of the steps
        before it (each decayed by ``momentum``), as mPIE does for its probe; the sum
        restarts when a pass fits worse than the one before. 0: plain steps.
    known : bool
        Whether the starting maps or coefficients are a pupil the captures came with (a known
        aberration or pupil), not an estimate. The lattice filter then takes its patterns from the
        map's departure from that pupil, not from 1: a known defocus has lattice harmonics too, and
        a filter measured from 1 would strip them at every step.
    """

    def __init__(self, layout: BandLayout, pupil_index: np.ndarray, *, model: str = "full", order: int = 4,
                 coefficients: np.ndarray | None = None, amplitude: bool = True, step: float = 1.0,
                 threads: int = 1, offsets: np.ndarray | None = None, maps: np.ndarray | None = None,
                 tilt: str = "pupil", smoothing: float = 0.25, lattice: str = "free", damping: float = 1e-3,
                 momentum: float = 0.0, known: bool = False):
        if model not in PUPIL_MODELS:
            raise ValueError(f"pupil model must be one of {', '.join(PUPIL_MODELS)}, got {model!r}")
        if lattice not in ("free", "filtered"):
            raise ValueError(f"pupil lattice must be free or filtered, got {lattice!r}")
        self.model = model
        self.lattice = lattice
        self.tilt = tilt
        self.smoothing = float(smoothing)
        if not 0 < damping <= 1:
            raise ValueError(f"pupil damping must be in (0, 1], got {damping!r}")
        self.damping = float(damping)
        if not 0 <= momentum < 1:
            raise ValueError(f"pupil momentum must be in [0, 1), got {momentum!r}")
        self.momentum = float(momentum)
        self.velocity = None   # the decayed sum of the map's steps (momentum > 0), on the maps' normalisation
        self.order = order
        self.modes = zernike_modes(order)
        self.amplitude = amplitude
        self.index = np.asarray(pupil_index, np.int64)
        self.n_pupils = int(self.index.max()) + 1 if self.index.size else 1
        b = layout.box_size
        self.coefficients = np.zeros((self.n_pupils, len(self.modes)))
        if coefficients is not None:
            given = np.asarray(coefficients, np.float64).reshape(self.n_pupils, -1)
            self.coefficients[:, :given.shape[1]] = given[:, :len(self.modes)]
        self._step = float(step)
        self._previous = None  # (state before the last step, misfit of the pass that made it)
        self.undone_sharply = False   # whether the last step() undid a step after which the misfit leapt
        self.stepped = False          # whether the last step() took a new step (not an undo, not nothing)
        self._num = np.zeros((threads, self.n_pupils, b, b), np.complex128)
        self._den = np.zeros((threads, self.n_pupils, b, b), np.float64)
        self._rhs = np.zeros((threads, self.n_pupils, len(self.modes)), np.float64)
        self._known_discs_key, self._known_discs = None, (None, {})   # the last geometry's discs (see _discs_at)
        self._box_basis_key = None   # what the modes on the box grid were made for (see set_geometry)
        self._periodic, self._periodic_key = None, None   # the lattice filter and the centres it was made for
        self.set_geometry(layout, self.index, offsets)
        self.maps = np.ones((self.n_pupils, b, b), np.complex64)
        if maps is not None:  # a known pupil: the map starts from it, the modes from its phase
            self.maps = np.broadcast_to(np.asarray(maps, np.complex64), (self.n_pupils, b, b)).copy()
            if model == "zernike":
                self.coefficients = self.project_zernike()
                self.maps = np.ones((self.n_pupils, b, b), np.complex64)
        elif model != "zernike" and np.any(self.coefficients):  # the map starts from the given aberration
            self.maps = self._zernike_maps(self.coefficients)
            self.coefficients[:] = 0
        # what the lattice filter measures a map's departure from (see ``known``)
        self._reference = self.maps.copy() if known and model != "zernike" else None

    @property
    def reference(self) -> np.ndarray | None:
        """The known pupil the lattice filter measures the maps' departure from, on their footing (None: 1)."""
        return self._reference

    @property
    def step_size(self) -> float:
        """The current step fraction (halved each time a step is undone)."""
        return self._step

    def restore(self, maps: np.ndarray, coefficients: np.ndarray, step_size: float,
                velocity: np.ndarray | None = None, reference: np.ndarray | None = None) -> None:
        """Continue from saved maps, coefficients, step size, momentum and known pupil on the maps' footing (a
        checkpoint); the last step cannot be undone."""
        self.maps, self.coefficients, self._step = maps, coefficients, float(step_size)
        self.velocity = velocity
        if reference is not None and self._reference is not None:
            self._reference = np.asarray(reference, np.complex64)
        self._previous = None

    # ------------------------------------------------------------------ geometry
    def set_geometry(self, layout: BandLayout, pupil_index: np.ndarray, offsets: np.ndarray | None = None) -> None:
        """Use new pupil boxes / centres (after a position update or a new visiting order)."""
        self.layout = layout
        self.index = np.asarray(pupil_index, np.int64)
        centres = layout.box_centres if offsets is None else layout.box_centres + np.asarray(offsets, np.float64)
        self._centres = centres
        self._discs = self._discs_at(layout, centres)
        self._smooth_designs = {}   # per pupil: what the smooth model's fit needs that only the geometry sets
        if self.lattice == "filtered" and self.model != "zernike":
            # the map filter of ``lattice="filtered"``, where the centres form a lattice; found from the
            # centres in a fixed order, so that a new visiting order keeps it
            centres_px = np.asarray(layout.centres_px, np.float64)
            ordered = centres_px[np.lexsort(centres_px.T[::-1])]
            key = (layout.box_size, ordered.tobytes())
            if key != self._periodic_key:
                vectors = capture_lattice(ordered)
                self._periodic = None if vectors is None else periodic_filter(layout.box_size, vectors)
                self._periodic_key = key
        else:
            self._periodic = None
        self._basis = None
        if self.model == "zernike":
            self._basis = zernike_basis(layout.box_size, centres, layout.pupil_radius_px, order=self.order)
        # Each pupil's modes on the box grid (for the curvature and for projections), at the mean centre
        # (summed in a fixed order, so that a new visiting order keeps the same basis).
        mean_centres = [self._mean_centre(p) for p in range(self.n_pupils)]
        basis_key = (layout.box_size, float(layout.pupil_radius_px), self.order, tuple(mean_centres))
        if self._box_basis_key != basis_key:
            self._box_basis = np.empty((self.n_pupils, len(self.modes), layout.box_size, layout.box_size),
                                       np.float32)
            for p, centre in enumerate(mean_centres):
                self._box_basis[p] = zernike_basis(layout.box_size, np.array([centre]), layout.pupil_radius_px,
                                                       order=self.order)[:, 0]
            self._box_basis_key = basis_key

    def _mean_centre(self, pupil: int) -> tuple[float, float]:
        """Mean box centre of ``pupil``'s captures (all captures' for a pupil without any), in any visiting order."""
        members = self.index == pupil
        centres = self._centres[members] if np.any(members) else self._centres
        return tuple(math.fsum(axis) / len(centres) for axis in centres.T.tolist())

    def _discs_at(self, layout: BandLayout, centres: np.ndarray) -> np.ndarray:
        """Every capture's NA disc at ``centres`` (float32, (K, b, b)).

        A new visiting order (each time the batches grow) only permutes the captures: when every centre
        was among the last discs made (same box and radius), those are gathered in the new order (the
        same values as made anew); otherwise all are made afresh and kept for the next call.
        """
        key = (layout.box_size, float(layout.pupil_radius_px))
        known, where = self._known_discs if self._known_discs_key == key else (None, {})
        rows = [tuple(centre) for centre in centres.tolist()]
        found = [where.get(row, -1) for row in rows]
        if known is not None and min(found, default=0) >= 0:
            # the kept discs stay the recovery's own; the last discs are refilled where they fit (fresh pages
            # cost more than the copy)
            last = getattr(self, "_discs", None)
            if (isinstance(last, np.ndarray) and last.shape == (len(found),) + known.shape[1:]
                    and last.dtype == known.dtype and last.flags.c_contiguous and last is not known):
                return np.take(known, found, axis=0, out=last, mode="clip")
            return known[found]
        discs = circular_pupils(layout.box_size, centres, layout.pupil_radius_px)
        self._known_discs_key = key
        self._known_discs = (discs.copy(), {row: i for i, row in enumerate(rows)})
        return discs

    def _zernike_maps(self, coefficients: np.ndarray) -> np.ndarray:
        """Each pupil's Zernike phase on the box grid, at the mean centre of its captures."""
        phase = np.einsum("pn,pnyx->pyx", coefficients.astype(np.float32), self._box_basis)
        return np.exp(1j * phase).astype(np.complex64)

    def pupils(self) -> np.ndarray:
        """Every capture's pupil ``D_i · A_{p(i)}`` (engine order), complex64 (K, b, b)."""
        return self._pupils(self._discs, self._basis, self.index)

    def map_parts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """What :meth:`pupils` is made of for the map models, for :func:`~cca_cli.optics.kernels.map_pupil_factors`.

        Returns
        -------
        tuple or None
            Every capture's NA disc (float32, (K, b, b)), the maps (complex64, (P, b, b)) and each
            capture's map (int64, (K,)), engine order; None for the Zernike model.
        """
        if self.model == "zernike":
            return None
        return (np.ascontiguousarray(self._discs, np.float32), np.ascontiguousarray(self.maps, np.complex64),
                np.ascontiguousarray(self.index, np.int64))

    def pupils_at(self, layout: BandLayout, pupil_index: np.ndarray) -> np.ndarray:
        """The current pupils of captures laid out by ``layout`` (any order), complex64 (K, b, b)."""
        discs = circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px)
        basis = None
        if self.model == "zernike":
            basis = zernike_basis(layout.box_size, layout.box_centres, layout.pupil_radius_px, order=self.order)
        return self._pupils(discs, basis, np.asarray(pupil_index, np.int64))

    def _pupils(self, discs: np.ndarray, basis: np.ndarray | None, index: np.ndarray) -> np.ndarray:
        if self.model != "zernike":
            return discs * self.maps[index]
        coefficients = self.coefficients[index].astype(np.float32)  # (K, n_modes)
        phase = np.einsum("kn,nkyx->kyx", coefficients, basis)
        return (discs * np.exp(1j * phase)).astype(np.complex64)

    # --------------------------------------------------------------- accumulate
    def lane_sums(self, thread: int) -> tuple | None:
        """What a fused lane adds this thread's pupil sums with (map models), or None (Zernike: step by step)."""
        if self.model == "zernike":
            return None
        return (np.ascontiguousarray(self._discs, np.float32), np.ascontiguousarray(self.index, np.int64),
                self._num[thread], self._den[thread])

    def zernike_sums(self, thread: int) -> tuple | None:
        """What a batched engine adds the Zernike model's sums with, or None (the map models: :meth:`lane_sums`).

        Returns
        -------
        discs : ndarray, float32, (K, b, b)
            Every capture's NA disc on its box (engine order).
        basis : ndarray, float32, (n_modes, K, b, b)
            Every capture's Zernike modes on its box.
        index : ndarray, int64, (K,)
            The pupil each capture uses.
        rhs : ndarray, float64, (P, n_modes)
            This thread's sums of the phase gradient on the modes (added to in place).
        denominator : ndarray, float64, (P, b, b)
            This thread's sums of the light through each pupil pixel (added to in place).
        """
        if self.model != "zernike":
            return None
        return self._discs, self._basis, self.index, self._rhs[thread], self._den[thread]

    def accumulate(self, thread: int, images: slice, spectrum: np.ndarray, origins: np.ndarray,
                   fields: np.ndarray, pupils: np.ndarray) -> None:
        """Add one batch's terms of the pupil fit.

        Parameters
        ----------
        thread : int
        images : slice
            The batch (engine order).
        spectrum : ndarray, complex64, (M, M)
            The spectrum the batch's fields were computed from (before its update).
        origins : ndarray, int64, (K, 2)
            Box corners (engine order).
        fields : ndarray, complex64, (k, m, m)
            Raw forward transforms of the batch's data steps ``ψ' − ψ``.
        pupils : ndarray, complex64, (K, b, b)
            The pupils the fields were computed with.
        """
        m = fields.shape[-1]
        if self.model != "zernike":
            kernels.accumulate_pupil(spectrum, origins, self._discs, fields, images.start, self.index,
                                     self._num[thread], self._den[thread], 1.0 / m)
            return
        b = self.layout.box_size
        s = m // 2 - b // 2
        index = self.index[images]
        seen = np.stack([spectrum[y0:y0 + b, x0:x0 + b] for y0, x0 in origins[images]])
        residual = fields[:, s:s + b, s:s + b] * np.float32(1.0 / m)
        power = np.square(np.abs(self._discs[images] * seen), dtype=np.float64)
        seen_through = pupils[images] * seen  # P_i S_i
        gradient = np.imag(np.conj(seen_through) * residual).astype(np.float32)
        terms = np.einsum("nkyx,kyx->kn", self._basis[:, images], gradient).astype(np.float64)
        np.add.at(self._rhs[thread], index, terms)
        np.add.at(self._den[thread], index, power)

    # --------------------------------------------------------------------- step
    @property
    def undoes_leaps(self) -> bool:
        """Whether a leap of the misfit (:data:`SHARP_RISE`) is what undoes a step (a lattice-filtered map)."""
        return self._periodic is not None

    def step(self, misfit: float) -> tuple[complex, np.ndarray] | None:
        """End-of-pass update; undoes the last one instead if this pass fit the data worse.

        A map whose lattice patterns are filtered out (``lattice="filtered"`` on a lattice) is
        undone only when the misfit leapt (by more than :data:`SHARP_RISE`), and its step is not
        halved: the filter takes from each step what the data cannot tell from the object, so the
        misfit may rise after a sound step, and undoing (and halving) it would stall the map. After
        such a leap ``undone_sharply`` is True: the pass run with the undone pupils has harmed the
        spectrum too, and the engine goes back to the spectrum the step was taken from.

        Parameters
        ----------
        misfit : float
            The data misfit of the pass just finished.

        Returns
        -------
        (scale, tilt) or None
            None when nothing changed. Otherwise the ``full`` map was normalised by
            dividing it by ``scale`` and removing the phase ramp ``exp(i tilt·k)``:
            the engine multiplies its spectrum by ``scale · exp(i tilt·k)`` (k the
            spectrum pixel index) so the model's predictions stay the same. The tilt
            is zero where it stays in the map (``tilt="pupil"``) or for Zernike pupils.
        """
        numerator, denominator = self._num.sum(axis=0), self._den.sum(axis=0)
        rhs = self._rhs.sum(axis=0)
        self._num[:] = 0
        self._den[:] = 0
        self._rhs[:] = 0
        previous = self._previous
        self.undone_sharply = self.stepped = False
        if previous is not None and misfit > previous.misfit:
            self.velocity = None
            leapt = self.undoes_leaps and misfit > SHARP_RISE * previous.misfit
            if self._periodic is None or leapt:
                self.maps, self.coefficients = previous.maps, previous.coefficients
                self._reference = previous.reference
                if not leapt:   # after a leap the filter's next step, from a better object, is a sound one
                    self._step *= 0.5
                self._previous = None
                self.undone_sharply = leapt
                return 1.0 / previous.scale, -previous.tilt
        peak = float(denominator.max()) if denominator.size else 0.0
        if not peak > 0:
            return None
        maps, coefficients, reference = self.maps.copy(), self.coefficients.copy(), self._reference
        if self.model == "zernike":
            self._zernike_step(rhs, denominator)
            scale, tilt = 1.0, np.zeros(2)
        else:
            scale, tilt = self._map_step(numerator, denominator, peak)
            if self.momentum:
                self._add_momentum(maps, scale, tilt, denominator > 0)
        self._previous = _Step(maps, coefficients, misfit, scale, tilt, reference)
        self.stepped = True
        return scale, tilt

    def _add_momentum(self, before: np.ndarray, scale: complex, tilt: np.ndarray, seen: np.ndarray) -> None:
        """Add the decayed sum of the steps so far to the step just made (from ``before``), where light was seen.

        The step divided the maps by ``scale`` and took the ramp ``exp(-i tilt·k)`` off them; the map before
        and the sum are put on the same footing first.
        """
        footing = (untilt_ramp(tilt, before.shape[-1])[None] / scale).astype(np.complex64)
        step = np.where(seen, self.maps - before * footing, 0)
        if self.velocity is None:
            self.velocity = step.astype(np.complex64)
        else:
            self.velocity = (self.momentum * self.velocity * footing + step).astype(np.complex64)
        maps = self.maps + np.float32(self.momentum) * self.velocity
        if not self.amplitude:
            maps = np.where(seen, np.exp(1j * np.angle(maps)), maps)
        self.maps = maps.astype(np.complex64)

    def _smooth_maps(self, maps: np.ndarray, light: np.ndarray) -> np.ndarray:
        """Each map's phase as Zernike modes plus a smooth remainder, its amplitude 1 (or smoothed too).

        The phase is fitted, weighted by the light each pixel saw, with the modes up to ``order``
        and piston and tilt; what the modes leave is smoothed with a Gaussian of ``smoothing`` pupil
        radii (normalised over the disc), so detail finer than that (the object's, or noise) cannot
        settle in the pupil. Piston is dropped (the object keeps it); the tilt is kept for the step to place
        (in the pupil, in the object, or nowhere: ``tilt``).
        """
        from scipy import ndimage

        sigma = max(self.smoothing * self.layout.pupil_radius_px, 0.5)
        out = np.ones_like(maps)
        grid = np.arange(maps.shape[-1], dtype=np.float64)
        for p in range(self.n_pupils):
            disc, columns, cover, modes = self._smooth_design(p, sigma)
            weight = light[p] * disc
            if not weight.any():
                continue
            # The tilt comes off first (measured without wrapping): a tilt kept in the pupil grows past π over the
            # disc, and the phase would wrap.
            tilt = tilt_of(maps[p], np.sqrt(weight / weight.max()))
            flat = maps[p] * untilt_ramp(tilt, maps.shape[-1])
            phase = np.angle(flat * np.conj(np.sum(flat * weight)))
            # Weighted least squares by its normal equations: the design is fixed, only the weights change.
            weighted = columns * (weight[disc] / weight.max())[:, None]
            solution, *_ = np.linalg.lstsq(weighted.T @ columns, weighted.T @ phase[disc], rcond=None)
            low_order = np.einsum("n,nyx->yx", solution[:len(modes)], modes)
            ty, tx = solution[-2] + tilt[0], solution[-1] + tilt[1]  # kept: the step places it (``tilt``)
            low_order = low_order + ty * grid[:, None] + tx * grid[None, :]
            fitted = np.zeros(disc.shape)
            fitted[disc] = columns @ solution
            mask = disc.astype(np.float64)
            remainder = ndimage.gaussian_filter((phase - fitted) * mask, sigma) / cover
            if self.amplitude:
                amplitude = ndimage.gaussian_filter(np.abs(maps[p]) * mask, sigma) / cover
            else:
                amplitude = 1.0
            out[p] = np.where(disc, amplitude * np.exp(1j * (low_order + remainder)), 1)
        return out.astype(np.complex64)

    def _smooth_design(self, p: int, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pupil ``p``'s disc, the fit's columns (modes, piston, tilts) on it, the smoothing's cover, the modes."""
        if p not in self._smooth_designs:
            from scipy import ndimage

            b = self.layout.box_size
            disc = circular_pupils(b, np.array([self._mean_centre(p)]), self.layout.pupil_radius_px)[0] > 0
            modes = self._box_basis[p].astype(np.float64)
            grid = np.arange(b, dtype=np.float64)
            columns = np.stack([m[disc] for m in modes] + [np.ones(disc.sum()), (grid[:, None] * np.ones(b))[disc],
                                                         (np.ones(b)[:, None] * grid)[disc]], axis=1)
            cover = np.maximum(ndimage.gaussian_filter(disc.astype(np.float64), sigma), 1e-6)
            self._smooth_designs[p] = (disc, columns, cover, modes)
        return self._smooth_designs[p]

    def _zernike_step(self, rhs: np.ndarray, denominator: np.ndarray) -> None:
        for p in range(self.n_pupils):
            basis = self._box_basis[p].reshape(len(self.modes), -1)
            normal = (basis * denominator[p].reshape(1, -1)) @ basis.T
            trace = float(np.trace(normal))
            if not trace > 0:
                continue
            damped = normal + 1e-3 * trace / normal.shape[0] * np.eye(normal.shape[0])
            change = self._step * np.linalg.solve(damped, rhs[p])
            largest = float(np.max(np.abs(change)))
            if largest > _MAX_ZERNIKE_STEP:
                change *= _MAX_ZERNIKE_STEP / largest
            self.coefficients[p] += change

    def _map_step(self, numerator: np.ndarray, denominator: np.ndarray, peak: float) -> tuple[complex, np.ndarray]:
        seen = denominator > 0
        change = numerator / (denominator + self.damping * peak)
        maps = self.maps + (self._step * change).astype(np.complex64)
        if self._periodic is not None:
            for p in range(self.n_pupils):   # the map's departure from 1 (or the known pupil), less its lattice patterns
                reference = 1 if self._reference is None else self._reference[p]
                departure = np.where(seen[p], maps[p] - reference, 0)
                maps[p] = reference + np.fft.ifft2(np.fft.fft2(departure) * self._periodic)
        if not self.amplitude:
            maps = np.where(seen, np.exp(1j * np.angle(maps)), maps)
        maps = np.where(seen, maps, 1).astype(np.complex64)
        if self.model == "smooth":
            maps = self._smooth_maps(maps, denominator)
        # The object absorbs a common scale and piston of the pupils. Their mean tilt stays in them ("pupil"), goes
        # to the object ("object"; it moves with it) or is dropped ("pinned").
        if self.tilt == "pupil":
            tilt = np.zeros(2)
        else:
            weights = denominator.sum(axis=0)
            tilt = tilt_of(np.sum(maps * denominator, axis=0), np.sqrt(weights / weights.max()))
        maps = maps * untilt_ramp(tilt, maps.shape[-1])[None]
        if self.tilt == "pinned":
            tilt = np.zeros(2)
        mean = np.sum(maps * denominator) / np.sum(denominator)
        scale = mean / abs(mean) * np.sum(np.abs(maps) * denominator) / np.sum(denominator)
        self.maps = (maps / scale).astype(np.complex64)
        if self._reference is not None:   # the known pupil, on the maps' footing
            self._reference = (self._reference * untilt_ramp(tilt, maps.shape[-1])[None] / scale).astype(np.complex64)
        return complex(scale), tilt

    # ------------------------------------------------------------------ results
    def estimate(self) -> PupilEstimate:
        """The current pupils, with Zernike coefficients (fitted, or projected from the maps)."""
        if self.model == "zernike":
            maps = self._zernike_maps(self.coefficients)
            return PupilEstimate(maps, self.coefficients.copy(), self.modes, self.model)
        return PupilEstimate(self.maps.copy(), self.project_zernike(), self.modes, self.model)

    def project_zernike(self) -> np.ndarray:
        """Zernike coefficients (waves) of each map's phase, fitted inside the NA disc, free of tilt and piston."""
        out = np.zeros((self.n_pupils, len(self.modes)))
        b = self.layout.box_size
        grid = np.arange(b, dtype=np.float64)
        for p in range(self.n_pupils):
            disc = circular_pupils(b, np.array([self._mean_centre(p)]), self.layout.pupil_radius_px)[0] > 0
            tilt = tilt_of(self.maps[p], disc.astype(np.float64))  # off first, so that a large tilt cannot wrap
            flat = self.maps[p] * untilt_ramp(tilt, b)
            phase = np.angle(flat * np.conj(flat[disc].mean()))
            columns = [self._box_basis[p, j][disc] for j in range(len(self.modes))]
            columns += [np.ones(disc.sum()), (grid[:, None] * np.ones(b))[disc], (np.ones(b)[:, None] * grid)[disc]]
            design = np.stack(columns, axis=1)
            # by the normal equations (a few columns): LAPACK's least squares on the tall design took 2-90 ms,
            # its threads waiting for cores the passes hold
            solution, *_ = np.linalg.lstsq(design.T @ design, design.T @ phase[disc], rcond=None)
            out[p] = solution[:len(self.modes)]  # the modes are in radians per wave
        return out
