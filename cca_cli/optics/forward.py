"""The camera-array forward operator and its adjoint.

Capture ``i`` sees the object's spectrum ``S`` through its pupil ``P_i``
centred at ``c_i`` (Fraunhofer):

    ψ_i = F⁻¹{ P_i(k − c_i) · S(k) },        image_i = |ψ_i|²

Only the pupil box of ``S`` matters to capture ``i``, so ψ_i is computed on
the small m x m grid that holds its intensity band (``m > 4 R``) rather than
on the full M x M grid, in batches, in complex64.

Layouts
-------
*Spectrum*: centred M x M (DC at ``M // 2``), orthonormal with the object:
``S = fft2c(object)``.
*Fields* (what :meth:`ForwardModel.forward_into` returns): m x m with the image
origin at index 0 (FFT order) and multiplied by ``(-1)^(y+x)``. Magnitude
operations do not see the sign pattern; :func:`to_model_layout` /
:func:`to_sensor_layout` convert intensities between this order and the
sensor's centred order.

Units
-----
With orthonormal transforms, ``|ψ|²`` is ``(M/m)²`` times the sensor
irradiance (which equals 1 for an unobstructed unit plane wave). Use
:attr:`ForwardModel.intensity_scale` to convert.
"""

from __future__ import annotations

import math

import numpy as np

from cca_cli.optics import fft, kernels
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import BandLayout

__all__ = ["ForwardModel", "Workspace", "to_model_layout", "to_sensor_layout", "chunk_slices"]


def to_model_layout(images: np.ndarray) -> np.ndarray:
    """Centred sensor images → field layout (origin at index 0)."""
    return np.fft.ifftshift(images, axes=(-2, -1))


def to_sensor_layout(images: np.ndarray) -> np.ndarray:
    """Field layout (origin at index 0) → centred sensor images."""
    return np.fft.fftshift(images, axes=(-2, -1))


def chunk_slices(n_items: int, chunk: int) -> list[slice]:
    """Split ``range(n_items)`` into nearly equal contiguous slices of at most ``chunk`` items."""
    chunk = max(1, int(chunk))
    count = max(1, math.ceil(n_items / chunk))
    size = math.ceil(n_items / count)
    return [slice(start, min(start + size, n_items)) for start in range(0, n_items, size)]


class Workspace:
    """Scratch space for one thread: a field buffer with its FFTs, planned for in-place use.

    The workspace owns the FFT plans of its buffer (raw FFTW plans included, see
    :meth:`~cca_cli.optics.fft.BandedFFT2.raw_plans`); they live as long as it does, or
    until :meth:`close`.

    Parameters
    ----------
    chunk : int
        Number of captures the buffer holds.
    size : int
        Per-capture grid m.
    threads : int, optional
        FFT threads for this buffer.
    band : tuple of int, optional
        Rows ``[start, stop)`` that hold the pupil box: transforms are pruned to them.
    effort : str, optional
        FFTW planning effort (default :func:`~cca_cli.optics.fft.planning_effort`).
    """

    def __init__(self, chunk: int, size: int, *, threads: int | None = None, band: tuple[int, int] | None = None,
                 effort: str | None = None):
        self.fields = fft.zeros((chunk, size, size), np.complex64)
        self._threads = threads
        self._effort = effort
        #: Pruned transforms for fields confined to the pupil box's rows (None: use full transforms).
        self.box_fft = None if band is None else fft.BandedFFT2(self.fields, *band, threads=threads, effort=effort)
        # Without a band the full transforms do the work: plan them now.
        self._fft = None if band is not None else fft.InPlaceFFT2(self.fields, threads=threads, effort=effort)

    @property
    def fft(self) -> fft.InPlaceFFT2:
        """Full (unpruned) transforms of the buffer; with a band, planned on first use."""
        if self._fft is None:
            self._fft = fft.InPlaceFFT2(self.fields, threads=self._threads, effort=self._effort)
        return self._fft

    @property
    def capacity(self) -> int:
        """Number of captures the buffer holds."""
        return self.fields.shape[0]

    def inverse(self, count: int) -> np.ndarray:
        """Raw inverse 2-D FFT of the first ``count`` fields (pruned to the band when there is one); in place."""
        if self.box_fft is not None:
            return self.box_fft.inverse(count)
        return self.fft.inverse()

    def forward(self, count: int) -> np.ndarray:
        """Raw forward 2-D FFT of the first ``count`` fields (exact in the band when there is one); in place."""
        if self.box_fft is not None:
            return self.box_fft.forward(count)
        return self.fft.forward()

    def close(self) -> None:
        """Destroy the FFT plans now (they are also destroyed when the workspace is collected)."""
        for transform in (self.box_fft, self._fft):
            if transform is not None:
                transform.close()


class ForwardModel:
    """Spectrum → per-capture sensor fields, with adjoint and normal diagonal.

    Parameters
    ----------
    layout : BandLayout
        Grid sizes and pupil boxes.
    pupils : ndarray, (K, b, b) or (1, b, b), float32 or complex64
        Pupil function of each capture on its box (see
        :func:`~cca_cli.optics.pupil.circular_pupils`).
    pupil_boxes : ndarray, complex64, (K, b, b), optional
        ``pupils`` times ``1/m`` (see :attr:`pupil_boxes`), when the caller has made them
        already (:func:`~cca_cli.optics.kernels.map_pupil_factors`). The model then keeps both arrays
        as they are, without copies: ``pupils`` must be complex64 (K, b, b) too, and neither
        may change while the model is in use.

    Notes
    -----
    The operator ``A_i = F_m⁻¹ · P_i · R_i`` (crop, pupil, inverse FFT) has the
    adjoint ``A_iᴴ = R_iᵀ · P_i* · F_m`` and the normal operator
    ``Σ A_iᴴ A_i = Σ R_iᵀ |P_i|² R_i``, a diagonal; the paper's Tikhonov update
    divides by it.
    """

    def __init__(self, layout: BandLayout, pupils: np.ndarray, *, pupil_boxes: np.ndarray | None = None):
        pupils = np.asarray(pupils)
        b = layout.box_size
        if pupils.ndim != 3 or pupils.shape[1:] != (b, b) or pupils.shape[0] not in (1, layout.n_images):
            raise ValueError(
                f"pupils must have shape ({layout.n_images} or 1, {b}, {b}), got {pupils.shape}"
            )
        m = layout.lowres_size
        self.layout = layout
        if pupil_boxes is not None:
            full = (layout.n_images, b, b)
            for name, array in (("pupils", pupils), ("pupil_boxes", pupil_boxes)):
                if not (isinstance(array, np.ndarray) and array.dtype == np.complex64 and array.shape == full
                        and array.flags.c_contiguous):
                    raise ValueError(f"{name} must be a C-contiguous complex64 {full} array when pupil_boxes is "
                                     f"given, got {array.dtype} {array.shape}")
            self.pupils = pupils
            self._pupil_forward = pupil_boxes
        else:
            self.pupils = pupils = np.broadcast_to(pupils, (layout.n_images, b, b)).astype(np.complex64)
            # Orthonormal scaling folded into the pupils: raw FFTs then need no extra pass.
            self._pupil_forward = pupils * np.float32(1.0 / m)
        self._pupil_adjoint = None
        self._origin_array = np.ascontiguousarray(layout.box_origins, dtype=np.int64)
        kernels.warm_up()

    @classmethod
    def sharing(cls, layout: BandLayout, pupils: np.ndarray) -> ForwardModel:
        """A model that uses ``pupils`` as they are, without a copy, where they are a C-contiguous complex64
        (K, b, b) array (the caller leaves it unchanged while the model is in use); other pupils are copied as
        the constructor copies them. The same products either way."""
        b = layout.box_size
        if (isinstance(pupils, np.ndarray) and pupils.dtype == np.complex64 and pupils.flags.c_contiguous
                and pupils.shape == (layout.n_images, b, b)):
            return cls(layout, pupils, pupil_boxes=pupils * np.float32(1.0 / layout.lowres_size))
        return cls(layout, pupils)

    @classmethod
    def unaberrated(cls, layout: BandLayout) -> ForwardModel:
        """The model of ideal lenses: each capture's pupil is its (anti-aliased) NA disc."""
        return cls(layout, circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px))

    @property
    def pupil_boxes(self) -> np.ndarray:
        """Pupil boxes as :meth:`forward_into` applies them (raw-FFT scaling folded in), complex64 (K, b, b)."""
        return self._pupil_forward

    # ------------------------------------------------------------------ shapes
    @property
    def n_images(self) -> int:
        """Number of captures K."""
        return self.layout.n_images

    @property
    def field_shape(self) -> tuple[int, int]:
        """Shape (m, m) of one capture's field."""
        return (self.layout.lowres_size, self.layout.lowres_size)

    @property
    def spectrum_shape(self) -> tuple[int, int]:
        """Shape (M, M) of the high-resolution spectrum."""
        return (self.layout.hires_size, self.layout.hires_size)

    @property
    def intensity_scale(self) -> float:
        """``|ψ|²`` per unit sensor irradiance: ``(M / m)²``."""
        return (self.layout.hires_size / self.layout.lowres_size) ** 2

    def workspace(self, chunk: int | None = None, *, threads: int | None = None,
                  effort: str | None = None) -> Workspace:
        """A :class:`Workspace` sized for ``chunk`` captures (default: all).

        ``effort`` is the FFTW planning effort (default :func:`~cca_cli.optics.fft.planning_effort`,
        whose ``auto`` plans a workspace used only a few times in milliseconds).
        """
        start = self.layout.lowres_box_start
        return Workspace(chunk or self.n_images, self.layout.lowres_size, threads=threads,
                         band=(start, start + self.layout.box_size), effort=effort)

    # --------------------------------------------------------------- operators
    def forward_into(self, spectrum: np.ndarray, images: slice, workspace: Workspace) -> np.ndarray:
        """Fields of captures ``images`` for ``spectrum``, written into the workspace.

        Parameters
        ----------
        spectrum : ndarray, complex64, (M, M)
            Centred high-resolution spectrum.
        images : slice
            Contiguous range of capture indices (at most the workspace capacity).
        workspace : Workspace

        Returns
        -------
        ndarray, complex64, (k, m, m)
            A view of the workspace buffer (field layout, see module notes).
        """
        start, stop, _ = images.indices(self.n_images)
        k = stop - start
        fields = workspace.fields
        kernels.place_boxes(spectrum, self._origin_array, self._pupil_forward, fields[:k], start)
        workspace.inverse(k)
        return fields[:k]

    def adjoint_into(self, workspace: Workspace, images: slice, accumulator: np.ndarray) -> None:
        """Add ``Σ A_iᴴ ψ_i`` for captures ``images`` to ``accumulator``.

        The fields are read from (and destroyed in) the workspace buffer.

        Parameters
        ----------
        workspace : Workspace
            Holds the fields of ``images`` in its first ``k`` slots.
        images : slice
            The same contiguous range passed to :meth:`forward_into`.
        accumulator : ndarray, complex64, (M, M)
            Centred spectrum that receives the back-projection.
        """
        start, stop, _ = images.indices(self.n_images)
        k = stop - start
        workspace.forward(k)
        if self._pupil_adjoint is None:
            self._pupil_adjoint = np.conj(self._pupil_forward)
        kernels.scatter_boxes(workspace.fields[:k], self._origin_array, self._pupil_adjoint, accumulator, start)

    def normal_diagonal(self) -> np.ndarray:
        """``Σ_i R_iᵀ |P_i|²`` on the M x M spectrum grid (float32)."""
        b = self.layout.box_size
        out = np.zeros(self.spectrum_shape, dtype=np.float32)
        power = np.abs(self.pupils) ** 2
        for i, (y0, x0) in enumerate(self._origin_array):
            out[y0:y0 + b, x0:x0 + b] += power[i]
        return out

    # ------------------------------------------------------------ conveniences
    def forward(self, spectrum: np.ndarray, *, chunk: int = 64) -> np.ndarray:
        """All K fields (field layout), complex64 (K, m, m). Allocates; not for hot loops."""
        out = np.empty((self.n_images,) + self.field_shape, np.complex64)
        ws = self.workspace(min(chunk, self.n_images))
        for sl in chunk_slices(self.n_images, ws.capacity):
            out[sl] = self.forward_into(spectrum, sl, ws)
        return out

    def adjoint(self, fields: np.ndarray, *, chunk: int = 64) -> np.ndarray:
        """``Σ A_iᴴ ψ_i`` for fields in field layout, complex64 (M, M). Does not modify ``fields``."""
        acc = np.zeros(self.spectrum_shape, np.complex64)
        ws = self.workspace(min(chunk, self.n_images))
        for sl in chunk_slices(self.n_images, ws.capacity):
            k = sl.stop - sl.start
            ws.fields[:k] = fields[sl]
            self.adjoint_into(ws, sl, acc)
        return acc

    def sensor_intensity(self, spectrum: np.ndarray, *, chunk: int = 64) -> np.ndarray:
        """Noise-free captures in sensor units and centred sensor layout, float32 (K, m, m)."""
        out = np.empty((self.n_images,) + self.field_shape, np.float32)
        ws = self.workspace(min(chunk, self.n_images))
        scale = 1.0 / self.intensity_scale
        for sl in chunk_slices(self.n_images, ws.capacity):
            fields = self.forward_into(spectrum, sl, ws)
            out[sl] = to_sensor_layout(np.square(np.abs(fields)) * scale)
        return out
