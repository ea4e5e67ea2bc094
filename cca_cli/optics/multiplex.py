"""Single-shot camera arrays with multiplexed illumination.

P cameras whose apertures sit at ``c_p`` in the aperture plane look at a
scene lit by Q mutually incoherent coherent sources; source ``q`` tilts the
illumination and so shifts the object's spectrum by ``s_q``. Under pattern
``t`` a subset ``M(t)`` of the sources is on, and camera ``p`` records the sum
of the intensities of the spectrum regions the active sources bring to it:

    I_{p,t} = Σ_{q ∈ M(t)} |F⁻¹{ P(k − c_p − s_q) · S(k) }|²

Every (camera, pattern, active source) triple is one *virtual capture*: a
pupil centred at ``c_p + s_q``. A :class:`~cca_cli.optics.forward.ForwardModel`
over all virtual captures is the linear part of the multiplexed model, and a
measurement is the sum of a contiguous *group* of virtual captures (ordered
pattern-major, then camera, then the pattern's sources).

References
----------
Holloway et al., IEEE Trans. Comput. Imaging 2(3), 2016, Section VII.
:DOI:`10.1109/TCI.2016.2557067`
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from cca_cli.optics.forward import ForwardModel, to_sensor_layout
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import band_layout

__all__ = [
    "MultiplexGeometry",
    "MultiplexedForwardModel",
    "rect_lattice",
    "random_patterns",
    "group_chunk_slices",
    "coverage_map",
    "design_band",
]


def rect_lattice(rows: int, cols: int, pitch) -> np.ndarray:
    """A ``rows x cols`` lattice of ``[y, x]`` positions centred on the origin, row-major.

    Parameters
    ----------
    rows, cols : int
        Lattice shape.
    pitch : float
        Spacing between neighbours (any unit; the result has the same unit).

    Returns
    -------
    ndarray, float64, (rows * cols, 2)
    """
    if rows < 1 or cols < 1:
        raise ValueError(f"a lattice needs at least one row and column, got {rows}x{cols}")
    y = (np.arange(rows) - (rows - 1) / 2.0) * float(pitch)
    x = (np.arange(cols) - (cols - 1) / 2.0) * float(pitch)
    yy, xx = np.meshgrid(y, x, indexing="ij")
    return np.stack([yy.ravel(), xx.ravel()], axis=1)


def random_patterns(n_sources: int, n_mux: int, n_patterns: int, *, seed: int = 0) -> tuple[tuple[int, ...], ...]:
    """``n_patterns`` random sets of ``n_mux`` distinct sources (sorted indices), reproducible from ``seed``."""
    if not 1 <= n_mux <= n_sources:
        raise ValueError(f"n_mux must be in 1..{n_sources} (the number of sources), got {n_mux}")
    rng = np.random.default_rng(seed)
    return tuple(tuple(int(q) for q in np.sort(rng.choice(n_sources, size=n_mux, replace=False)))
                 for _ in range(int(n_patterns)))


def group_chunk_slices(offsets: np.ndarray, chunk: int) -> list[slice]:
    """Contiguous slices of virtual captures that never split a group.

    Consecutive groups are packed until a slice would exceed ``chunk`` captures;
    a group larger than ``chunk`` gets a slice of its own.

    Parameters
    ----------
    offsets : ndarray, int, (G + 1,)
        Group ``g`` is captures ``offsets[g]:offsets[g + 1]``.
    chunk : int
        Preferred captures per slice.
    """
    offsets = np.asarray(offsets, dtype=np.int64)
    slices = []
    start = int(offsets[0])
    for g in range(1, len(offsets)):
        stop = int(offsets[g])
        if stop - start > chunk and int(offsets[g - 1]) > start:
            slices.append(slice(start, int(offsets[g - 1])))
            start = int(offsets[g - 1])
    if int(offsets[-1]) > start:
        slices.append(slice(start, int(offsets[-1])))
    return slices


@dataclass(frozen=True)
class MultiplexGeometry:
    """Cameras, sources and illumination patterns in spectrum pixels.

    Attributes
    ----------
    camera_centres_px : ndarray, float64, (P, 2)
        Aperture centres ``[y, x]`` relative to DC (spectrum pixels).
    source_shifts_px : ndarray, float64, (Q, 2)
        Spectrum shift ``[y, x]`` each source makes (spectrum pixels).
    patterns : tuple of tuple of int
        T patterns, each the indices of its active sources (0 … Q−1, distinct).
    pupil_radius_px : float
        Camera pupil radius R (spectrum pixels).
    camera_shape, source_shape : tuple of int
        ``(rows, cols)`` of the two arrays (for display and grid indices).

    Notes
    -----
    Measurement ``g = t · P + p`` is camera ``p`` under pattern ``t``; its
    virtual captures are ``group_offsets[g]:group_offsets[g + 1]``, one per
    active source of pattern ``t`` in the pattern's order.
    """

    camera_centres_px: np.ndarray
    source_shifts_px: np.ndarray
    patterns: tuple[tuple[int, ...], ...]
    pupil_radius_px: float
    camera_shape: tuple[int, int] = (0, 0)
    source_shape: tuple[int, int] = (0, 0)

    def __post_init__(self):
        q = self.n_sources
        if not self.patterns:
            raise ValueError("at least one illumination pattern is needed")
        for t, pattern in enumerate(self.patterns):
            if not pattern:
                raise ValueError(f"pattern {t} has no active source")
            bad = [s for s in pattern if not 0 <= s < q]
            if bad:
                raise ValueError(f"pattern {t} names source {bad[0]}, but sources are numbered 0…{q - 1}")
            if len(set(pattern)) != len(pattern):
                raise ValueError(f"pattern {t} names a source more than once: {list(pattern)}")

    # ------------------------------------------------------------------ counts
    @property
    def n_cameras(self) -> int:
        """P."""
        return int(self.camera_centres_px.shape[0])

    @property
    def n_sources(self) -> int:
        """Q."""
        return int(self.source_shifts_px.shape[0])

    @property
    def n_patterns(self) -> int:
        """T."""
        return len(self.patterns)

    @property
    def n_measurements(self) -> int:
        """G = P · T images."""
        return self.n_cameras * self.n_patterns

    @property
    def n_virtual(self) -> int:
        """V = P · Σ_t |M(t)| virtual captures."""
        return int(self.group_offsets[-1])

    # ------------------------------------------------------- virtual captures
    @cached_property
    def group_offsets(self) -> np.ndarray:
        """int64 (G + 1,): measurement ``g`` owns virtual captures ``offsets[g]:offsets[g+1]``."""
        sizes = np.repeat([len(p) for p in self.patterns], self.n_cameras)
        return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    @cached_property
    def virtual_camera(self) -> np.ndarray:
        """int32 (V,): camera of each virtual capture."""
        return np.concatenate([np.repeat(np.arange(self.n_cameras), len(p)) for p in self.patterns]).astype(np.int32)

    @cached_property
    def virtual_source(self) -> np.ndarray:
        """int32 (V,): source of each virtual capture."""
        return np.concatenate([np.tile(np.asarray(p), self.n_cameras) for p in self.patterns]).astype(np.int32)

    @cached_property
    def virtual_pattern(self) -> np.ndarray:
        """int32 (V,): pattern of each virtual capture."""
        return np.concatenate([np.full(self.n_cameras * len(p), t) for t, p in enumerate(self.patterns)]).astype(np.int32)

    @cached_property
    def virtual_group(self) -> np.ndarray:
        """int32 (V,): measurement (group) of each virtual capture."""
        return np.repeat(np.arange(self.n_measurements), np.diff(self.group_offsets)).astype(np.int32)

    @cached_property
    def virtual_centres_px(self) -> np.ndarray:
        """float64 (V, 2): pupil centre ``c_p + s_q`` of each virtual capture."""
        return self.camera_centres_px[self.virtual_camera] + self.source_shifts_px[self.virtual_source]

    @property
    def measurement_camera(self) -> np.ndarray:
        """int32 (G,): camera of each measurement."""
        return np.tile(np.arange(self.n_cameras), self.n_patterns).astype(np.int32)

    @property
    def measurement_pattern(self) -> np.ndarray:
        """int32 (G,): pattern of each measurement."""
        return np.repeat(np.arange(self.n_patterns), self.n_cameras).astype(np.int32)

    def all_region_centres_px(self) -> np.ndarray:
        """float64 (P · Q, 2): every region the array could measure (all cameras × all sources)."""
        return (self.camera_centres_px[:, None, :] + self.source_shifts_px[None, :, :]).reshape(-1, 2)

    def neighbour_overlap(self) -> float:
        """Linear overlap of the regions of two neighbouring sources, ``1 − pitch / 2R`` (≤ 0: none)."""
        s = self.source_shifts_px
        if len(s) < 2:
            return float("nan")
        d = np.hypot(*(s[:, None, :] - s[None, :, :]).transpose(2, 0, 1))
        pitch = float(d[d > 1e-9].min())
        return 1.0 - pitch / (2.0 * self.pupil_radius_px)


class MultiplexedForwardModel:
    """Spectrum → multiplexed camera images, with the virtual-capture linear part exposed.

    Parameters
    ----------
    geometry : MultiplexGeometry
    sensor_size : int, optional
        Pixels across a sensor image (bounds the per-capture grid, see
        :func:`~cca_cli.sampling.grid.band_layout`).
    hires_size : int, optional
        Force the high-resolution grid M; default: the smallest grid that holds
        every region the design could measure (all cameras × all sources), so
        that every pattern choice of one design shares one grid.

    Attributes
    ----------
    model : ForwardModel
        The linear part: one capture per virtual capture.
    geometry : MultiplexGeometry
    """

    def __init__(self, geometry: MultiplexGeometry, *, sensor_size: int | None = None, hires_size: int | None = None):
        if hires_size is None:
            hires_size = band_layout(geometry.all_region_centres_px(), geometry.pupil_radius_px,
                                     sensor_size=sensor_size).hires_size
        layout = band_layout(geometry.virtual_centres_px, geometry.pupil_radius_px,
                             sensor_size=sensor_size, hires_size=hires_size)
        self.geometry = geometry
        self.model = ForwardModel.unaberrated(layout)

    @property
    def layout(self):
        """The :class:`~cca_cli.sampling.grid.BandLayout` of the virtual captures."""
        return self.model.layout

    @property
    def group_offsets(self) -> np.ndarray:
        """Virtual-capture range of each measurement (see :class:`MultiplexGeometry`)."""
        return self.geometry.group_offsets

    @property
    def n_measurements(self) -> int:
        """G."""
        return self.geometry.n_measurements

    def chunk_slices(self, chunk: int) -> list[slice]:
        """Group-aligned slices of virtual captures for a :class:`~cca_cli.engines.passes.ChunkedPass`."""
        return group_chunk_slices(self.group_offsets, chunk)

    # --------------------------------------------------------------- operators
    def fields(self, spectrum: np.ndarray) -> np.ndarray:
        """The linear part ``A S``: every virtual capture's field (field layout), complex64 (V, m, m)."""
        return self.model.forward(spectrum)

    def adjoint(self, fields: np.ndarray) -> np.ndarray:
        """``Aᴴ Ψ = Σ_i A_iᴴ ψ_i`` over all virtual captures, complex64 (M, M)."""
        return self.model.adjoint(fields)

    def group_sum(self, values: np.ndarray) -> np.ndarray:
        """Sum per measurement of per-virtual-capture arrays: (V, …) → (G, …)."""
        return np.add.reduceat(values, self.group_offsets[:-1], axis=0)

    def group_spread(self, values: np.ndarray) -> np.ndarray:
        """Adjoint of :meth:`group_sum`: copy each measurement's array to its virtual captures."""
        return np.repeat(values, np.diff(self.group_offsets), axis=0)

    def sensor_intensity(self, spectrum: np.ndarray, *, chunk: int = 64) -> np.ndarray:
        """Noise-free multiplexed images in sensor units and centred layout, float32 (G, m, m)."""
        model = self.model
        offsets = self.group_offsets
        out = np.empty((self.n_measurements,) + model.field_shape, np.float32)
        ws = model.workspace(max(chunk, int(np.diff(offsets).max())))
        scale = np.float32(1.0 / model.intensity_scale)
        for sl in self.chunk_slices(ws.capacity):
            fields = model.forward_into(spectrum, sl, ws)
            g0, g1 = np.searchsorted(offsets, [sl.start, sl.stop])
            power = np.square(np.abs(fields))
            out[g0:g1] = to_sensor_layout(np.add.reduceat(power, offsets[g0:g1] - sl.start, axis=0) * scale)
        return out

    # ---------------------------------------------------------------- coverage
    def coverage(self) -> np.ndarray:
        """How many measurements constrain each spectrum pixel, int32 (M, M).

        A pixel inside two regions of the same measurement counts once: the
        measurement is one image. Pixels with count 0 are holes, never measured.
        """
        return coverage_map(self.geometry, self.layout.hires_size)


def _disc_boxes(centres_px: np.ndarray, radius: float, size: int):
    """Yield ``(y0, y1, x0, x1, mask)`` of each disc clipped to a ``size`` grid (DC at size // 2)."""
    r = int(np.ceil(radius)) + 1
    for cy, cx in np.asarray(centres_px, dtype=np.float64):
        yc, xc = cy + size // 2, cx + size // 2
        top, left = int(np.floor(yc)) - r, int(np.floor(xc)) - r
        y0, y1 = max(top, 0), min(top + 2 * r + 2, size)
        x0, x1 = max(left, 0), min(left + 2 * r + 2, size)
        if y0 >= y1 or x0 >= x1:
            continue
        disc = circular_pupils(2 * r + 2, [[yc - top, xc - left]], radius, edge_px=0)[0] > 0
        yield y0, y1, x0, x1, disc[y0 - top:y1 - top, x0 - left:x1 - left]


def coverage_map(geometry: MultiplexGeometry, size: int) -> np.ndarray:
    """Measurements constraining each pixel of a centred ``size`` x ``size`` spectrum (int32)."""
    coverage = np.zeros((size, size), np.int32)
    offsets = geometry.group_offsets
    centres = geometry.virtual_centres_px
    for g in range(geometry.n_measurements):
        seen = np.zeros((size, size), bool)
        for y0, y1, x0, x1, mask in _disc_boxes(centres[offsets[g]:offsets[g + 1]], geometry.pupil_radius_px, size):
            seen[y0:y1, x0:x1] |= mask
        coverage += seen
    return coverage


def design_band(geometry: MultiplexGeometry, size: int) -> np.ndarray:
    """Union of every (camera, source) region the array could measure, bool (size, size)."""
    band = np.zeros((size, size), bool)
    for y0, y1, x0, x1, mask in _disc_boxes(geometry.all_region_centres_px(), geometry.pupil_radius_px, size):
        band[y0:y1, x0:x1] |= mask
    return band
