"""The common representation every method's result is converted into, and its forward model.

A result is an object spectrum, one or more pupils and where each capture's
pupil sits:

* ``spectrum`` — complex (M, M), centred (DC at ``M // 2``); any scale.
* ``pupils`` — complex (C, n, n) on the capture's window grid (n = the sensor
  image size), the window's centre at ``n // 2``.
* ``pupil_index`` — int (K,), which pupil capture k uses.
* ``windows`` — int (K, 2), the spectrum pixel [y, x] (relative to DC) at the
  centre of capture k's n × n window.
* ``brightness`` — optional float (K,), per-capture intensity factors.

Capture k's field is ``ifft2c(S[window_k] · P[pupil_index[k]])``; sub-pixel
pupil centres live in the pupils themselves (one pupil per capture, drawn at
its fractional offset from the window centre). Numpy only, so the peer
workers (other virtual environments) can use it too.

The *common reading* (:func:`common_reading`, used by ``real_corpus.py``) judges
every tool's object the same way, whatever pupil the tool recovered with it:

1. the object on an integer upsampling of the frame grid (the whole, possibly
   padded, periodic grid Fourier-resampled, then the frame region cut:
   :func:`object_on_frame_grid`);
2. shifted by the sub-pixel offset (phase correlation, 1/20 px) that aligns its
   predicted centre capture (nominal pupil) with the measured one
   (:func:`phase_correlation`); a pupil tilt is an object shift;
3. one common complex pupil map A refitted on the pupil support with the object
   fixed: 40 averaged EPRY steps from A = 1 (:func:`refit_pupil`), the object first
   scaled by the least-squares factor of its A = 1 predictions (tools scale their
   objects as they like; without it A spends its steps on the scale);
4. the amplitude residual after one global scale over each frame's interior.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["Recovery", "circle_pupils", "predicted_fields", "embed_centred", "ifft2c", "fft2c",
           "object_on_frame_grid", "phase_correlation", "shift_spectrum", "FrameModel", "refit_pupil",
           "common_reading", "Reading"]


def fft2c(x: np.ndarray) -> np.ndarray:
    """Centred orthonormal 2-D FFT over the last two axes."""
    return np.fft.fftshift(np.fft.fft2(np.fft.ifftshift(x, axes=(-2, -1)), norm="ortho"), axes=(-2, -1))


def ifft2c(x: np.ndarray) -> np.ndarray:
    """Centred orthonormal inverse 2-D FFT over the last two axes."""
    return np.fft.fftshift(np.fft.ifft2(np.fft.ifftshift(x, axes=(-2, -1)), norm="ortho"), axes=(-2, -1))


def circle_pupils(n: int, offsets_yx, radius_px: float, edge_px: float = 0.0) -> np.ndarray:
    """Discs of radius R on n × n grids, centre ``n // 2 + offset`` (fractional offsets allowed).

    ``edge_px = 0`` gives binary discs ``|k − c| ≤ R`` (the peers' pupil); ``edge_px = 1`` the
    anti-aliased edge cca's fixed pupil has (:func:`cca_cli.optics.pupil.circular_pupils`).
    """
    off = np.asarray(offsets_yx, np.float64).reshape(-1, 2)
    grid = np.arange(n, dtype=np.float64) - n // 2
    dy = grid[None, :, None] - off[:, 0, None, None]
    dx = grid[None, None, :] - off[:, 1, None, None]
    distance = np.sqrt(dy * dy + dx * dx)
    if edge_px <= 0:
        return (distance <= radius_px).astype(np.complex64)
    return np.clip((radius_px + edge_px / 2 - distance) / edge_px, 0.0, 1.0).astype(np.complex64)


def embed_centred(boxes: np.ndarray, n: int) -> np.ndarray:
    """Place (C, b, b) boxes centred (``b // 2`` → ``n // 2``) on (C, n, n) zero grids."""
    boxes = np.asarray(boxes)
    b = boxes.shape[-1]
    out = np.zeros(boxes.shape[:-2] + (n, n), np.complex64)
    lo = n // 2 - b // 2
    if lo < 0:  # box larger than the window: crop it about its centre
        s = b // 2 - n // 2
        out[...] = boxes[..., s:s + n, s:s + n]
    else:
        out[..., lo:lo + b, lo:lo + b] = boxes
    return out


@dataclass
class Recovery:
    """One method's result in the common representation (see the module notes)."""

    spectrum: np.ndarray
    pupils: np.ndarray
    pupil_index: np.ndarray
    windows: np.ndarray
    brightness: np.ndarray | None = None
    centres_yx_px: np.ndarray | None = None   # refined fractional centres, for the record
    notes: dict = field(default_factory=dict)
    crop_yxhw: tuple | None = None   # frames recovered on a padded grid: where they sit on its windows

    @property
    def n(self) -> int:
        """Window (sensor image) size."""
        return int(self.pupils.shape[-1])

    def save(self, path) -> None:
        """Write to an ``.npz`` file."""
        extra = {} if self.brightness is None else {"brightness": self.brightness}
        if self.centres_yx_px is not None:
            extra["centres_yx_px"] = self.centres_yx_px
        np.savez(path, spectrum=self.spectrum, pupils=self.pupils, pupil_index=self.pupil_index,
                 windows=self.windows, **extra)

    @classmethod
    def load(cls, path) -> "Recovery":
        """Read an ``.npz`` file written by :meth:`save`."""
        with np.load(path) as d:
            return cls(spectrum=d["spectrum"], pupils=d["pupils"], pupil_index=d["pupil_index"],
                       windows=d["windows"], brightness=d["brightness"] if "brightness" in d else None,
                       centres_yx_px=d["centres_yx_px"] if "centres_yx_px" in d else None)


def predicted_fields(rec: Recovery, *, brightness: bool = False, chunk: int = 64) -> np.ndarray:
    """Every capture's modelled field on its n × n window (complex64, (K, n, n)).

    A recovery made on a padded grid (``crop_yxhw``) returns the frames' part of each window.

    With ``brightness`` the fields are multiplied by ``√brightness_k``.
    """
    spectrum = np.asarray(rec.spectrum, np.complex128)
    m = spectrum.shape[-1]
    n = rec.n
    pad = n
    padded = np.zeros((m + 2 * pad, m + 2 * pad), np.complex128)
    padded[pad:pad + m, pad:pad + m] = spectrum  # windows reaching past the grid read zeros
    windows = np.asarray(rec.windows, np.int64)
    origins = windows + m // 2 - n // 2 + pad
    if origins.min() < 0 or origins.max() + n > padded.shape[0]:
        raise ValueError("a capture window lies more than one window outside the spectrum grid")
    k = windows.shape[0]
    out = np.empty((k, n, n), np.complex64)
    pupils = np.asarray(rec.pupils, np.complex128)
    index = np.asarray(rec.pupil_index, np.int64)
    for start in range(0, k, chunk):
        idx = range(start, min(start + chunk, k))
        crops = np.stack([padded[origins[i, 0]:origins[i, 0] + n, origins[i, 1]:origins[i, 1] + n] for i in idx])
        out[start:start + len(idx)] = ifft2c(crops * pupils[index[list(idx)]])
    if brightness and rec.brightness is not None:
        out *= np.sqrt(np.asarray(rec.brightness, np.float64))[:, None, None].astype(np.float32)
    if rec.crop_yxhw is not None:
        y0, x0, h, w = rec.crop_yxhw
        out = np.ascontiguousarray(out[:, y0:y0 + h, x0:x0 + w])
    return out


# ----------------------------------------------------------------------------- the common reading

def _fft(x: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Centred orthonormal 2-D FFT of the last two axes (scipy's threaded FFT where it is installed)."""
    try:
        import scipy.fft as sfft

        func = sfft.ifft2 if inverse else sfft.fft2
        return sfft.fftshift(func(sfft.ifftshift(x, axes=(-2, -1)), norm="ortho", workers=-1), axes=(-2, -1))
    except ImportError:  # pragma: no cover - the peer environments
        return ifft2c(x) if inverse else fft2c(x)


def _plain_fft(x: np.ndarray, inverse: bool = False) -> np.ndarray:
    """Orthonormal 2-D FFT of the last two axes, no shifts (scipy's threaded FFT where installed)."""
    try:
        import scipy.fft as sfft

        return (sfft.ifft2 if inverse else sfft.fft2)(x, norm="ortho", workers=-1)
    except ImportError:  # pragma: no cover - the peer environments
        return (np.fft.ifft2 if inverse else np.fft.fft2)(x, norm="ortho")


def object_on_frame_grid(rec: Recovery, factor: int) -> np.ndarray:
    """A recovery's object on a ``factor``-times upsampling of the frame grid (frame region only).

    The whole recovered grid (for a padded recovery: the periodic padded grid, of
    ``rec.n`` frame pixels) is Fourier-resampled to ``factor·rec.n`` samples (its
    centred spectrum zero-padded or cropped about DC), and then the frame region
    is cut; a cut region is never resampled.

    Parameters
    ----------
    rec : Recovery
    factor : int
        Samples per frame pixel.

    Returns
    -------
    ndarray, complex128, (factor·h, factor·w)
        The object, scaled so that a flat object keeps its amplitude.
    """
    spectrum = np.asarray(rec.spectrum, np.complex128)
    m = spectrum.shape[-1]
    size = factor * rec.n
    grid = np.zeros((size, size), np.complex128)
    if m <= size:
        lo = size // 2 - m // 2
        grid[lo:lo + m, lo:lo + m] = spectrum
    else:
        lo = m // 2 - size // 2
        grid[:] = spectrum[lo:lo + size, lo:lo + size]
    obj = _fft(grid, inverse=True) * (size / m)
    if rec.crop_yxhw is not None:
        y0, x0, h, w = rec.crop_yxhw
        obj = obj[factor * y0:factor * (y0 + h), factor * x0:factor * (x0 + w)]
    return obj


def _upsampled_dft(data: np.ndarray, size: int, factor: int, offsets) -> np.ndarray:
    """Cross-correlation near ``offsets`` sampled ``factor`` times finer (Guizar-Sicairos' matrix DFT)."""
    rows, cols = data.shape
    kc = np.fft.ifftshift(np.arange(cols)) - cols // 2
    kr = np.fft.ifftshift(np.arange(rows)) - rows // 2
    col_kernel = np.exp(-2j * np.pi / (cols * factor) * np.outer(kc, np.arange(size) - offsets[1]))
    row_kernel = np.exp(-2j * np.pi / (rows * factor) * np.outer(np.arange(size) - offsets[0], kr))
    return row_kernel @ data @ col_kernel


def phase_correlation(reference: np.ndarray, moving: np.ndarray, upsample: int = 20) -> np.ndarray:
    """Shift [dy, dx] (frame pixels, to 1/``upsample`` px) with ``moving(r − d) ≈ reference(r)``.

    Phase correlation (whitened cross-power spectrum), the integer peak refined by
    an upsampled matrix DFT over ±1.5 px around it.

    Parameters
    ----------
    reference, moving : ndarray, (H, W)
        Real images of one size.
    upsample : int, optional
        Subdivisions of a pixel.

    Returns
    -------
    ndarray, float64, (2,)
    """
    a = np.fft.fft2(np.asarray(reference, np.float64) - np.mean(reference))
    b = np.fft.fft2(np.asarray(moving, np.float64) - np.mean(moving))
    cross = a * np.conj(b)
    cross /= np.maximum(np.abs(cross), 1e-30)
    corr = np.abs(np.fft.ifft2(cross))
    peak = np.array(np.unravel_index(int(np.argmax(corr)), corr.shape), np.float64)
    shape = np.array(corr.shape)
    peak = np.where(peak > shape // 2, peak - shape, peak)
    size = int(np.ceil(upsample * 1.5))
    centre = size // 2
    fine = np.abs(_upsampled_dft(np.conj(cross), size, upsample, centre - peak * upsample))
    top = np.array(np.unravel_index(int(np.argmax(fine)), fine.shape), np.float64)
    return peak + (top - centre) / upsample


def shift_spectrum(spectrum: np.ndarray, shift_yx, pixels: int) -> np.ndarray:
    """Centred spectrum of the object moved by ``shift_yx`` pixels (a grid of ``pixels`` pixels per period)."""
    m = spectrum.shape[-1]
    k = np.arange(m) - m // 2
    ramp_y = np.exp(-2j * np.pi * k * float(shift_yx[0]) / pixels)
    ramp_x = np.exp(-2j * np.pi * k * float(shift_yx[1]) / pixels)
    return spectrum * ramp_y[:, None] * ramp_x[None, :]


@dataclass
class FrameModel:
    """The measured frames and their geometry, as the common reading uses them.

    Attributes
    ----------
    intensity : ndarray, (K, n, n)
        Measured intensities.
    weight : ndarray of bool, (K, n, n) or None
        False where a pixel is not to be fitted (clipped); None: every pixel.
    centres : ndarray, (K, 2)
        Fractional pupil centres [y, x] in frame-spectrum pixels relative to DC.
    radius : float
        Pupil radius (frame-spectrum pixels).
    bright_field : ndarray of bool, (K,)
    centre_index : int
        The capture nearest to normal incidence.
    margin : int
        Pixels left out at each frame edge when replacing magnitudes and in the residual.
    """

    intensity: np.ndarray
    weight: np.ndarray | None
    centres: np.ndarray
    radius: float
    bright_field: np.ndarray
    centre_index: int
    margin: int

    @property
    def n(self) -> int:
        return int(self.intensity.shape[-1])

    def interior(self) -> np.ndarray:
        """(K, n, n) bool: the pixels the reading fits (interior, and weight > 0)."""
        n, m = self.n, self.margin
        mask = np.zeros(self.intensity.shape, bool)
        mask[:, m:n - m, m:n - m] = True
        if self.weight is not None:
            mask &= np.asarray(self.weight, bool)
        return mask

    def discs(self) -> np.ndarray:
        """(K, n, n) each capture's disc (anti-aliased edge) at its fractional offset from its window centre."""
        windows = np.rint(self.centres)
        return circle_pupils(self.n, self.centres - windows, self.radius, edge_px=1.0)


def _windows(spectrum: np.ndarray, frames: FrameModel) -> np.ndarray:
    """W_j = the object spectrum's n × n window at capture j × its disc (complex64, (K, n, n))."""
    discs = frames.discs()
    rec = Recovery(spectrum, discs, np.arange(len(discs)), np.rint(frames.centres).astype(np.int64))
    m, n = spectrum.shape[-1], frames.n
    pad = n
    padded = np.zeros((m + 2 * pad, m + 2 * pad), np.complex64)
    padded[pad:pad + m, pad:pad + m] = spectrum
    origins = rec.windows + m // 2 - n // 2 + pad
    out = np.empty((len(discs), n, n), np.complex64)
    for j, (y, x) in enumerate(origins):
        out[j] = padded[y:y + n, x:x + n] * discs[j]
    return out


def refit_pupil(windows: np.ndarray, frames: FrameModel, steps: int = 40) -> np.ndarray:
    """One common complex pupil map A fitted to the frames with the object fixed.

    Starting from A = 1, ``steps`` averaged EPRY steps
    ``A += Σ_j conj(W_j)(F ψ'_j − W_j A) / (Σ_j |W_j|² + 1e-3 max Σ_j |W_j|²)``,
    ψ'_j the field ``F⁻¹(W_j A)`` with its magnitude replaced by the measured one
    (on the frame interior and unclipped pixels; elsewhere it keeps its own).

    Parameters
    ----------
    windows : ndarray, complex, (K, n, n)
        W_j: the object's window times capture j's disc at its fractional centre.
    frames : FrameModel
    steps : int, optional

    Returns
    -------
    ndarray, complex64, (n, n)
    """
    # the loop runs in the FFTs' own (unshifted) layout: every array is ifftshifted once
    def native(x):
        return np.ascontiguousarray(np.fft.ifftshift(x, axes=(-2, -1)))

    amplitude = native(np.sqrt(np.clip(frames.intensity, 0, None)).astype(np.float32))
    mask = native(frames.interior())
    w = native(np.asarray(windows, np.complex64))
    conj = np.conj(w)
    power = np.sum((w * conj).real, axis=0)
    denominator = (power + 1e-3 * power.max()).astype(np.float32)
    pupil = np.ones(w.shape[-2:], np.complex64)
    for _ in range(steps):
        field = _plain_fft(w * pupil, inverse=True)
        magnitude = np.abs(field)
        ratio = np.divide(amplitude, magnitude, out=np.ones_like(magnitude), where=mask & (magnitude > 0))
        field *= ratio
        back = _plain_fft(field)
        back *= conj
        update = back.sum(axis=0) - pupil * power
        pupil = (pupil + update / denominator).astype(np.complex64)
    pupil = np.fft.fftshift(pupil)
    return pupil


@dataclass
class Reading:
    """One object read the common way.

    Attributes
    ----------
    obj : ndarray, complex128, (f·n, f·n)
        The aligned object on the upsampled frame grid, in units of √(measured intensity).
    shift_px : ndarray, (2,)
        The sub-pixel shift applied (frame pixels).
    pupil : ndarray, complex64, (n, n)
        The refitted common pupil map A.
    residual : dict
        ``all``, ``bright_field``, ``dark_field``, ``scale`` over the frames' interiors.
    error2, reference2 : ndarray, float64, (K,)
        Each frame's squared amplitude misfit (after the global scale) and squared measured amplitude over its
        interior: ``residual["all"]`` is ``√(Σ error2 / Σ reference2)``.
    """

    obj: np.ndarray
    shift_px: np.ndarray
    pupil: np.ndarray
    residual: dict
    error2: np.ndarray | None = None
    reference2: np.ndarray | None = None


def common_reading(rec: Recovery, frames: FrameModel, factor: int, *, steps: int = 40) -> Reading:
    """Read one recovery the common way (see the module notes).

    Parameters
    ----------
    rec : Recovery
        Any tool's result.
    frames : FrameModel
    factor : int
        Samples per frame pixel of the object grid (``factor·n`` must hold the
        synthetic band for the reading to keep all of it).
    steps : int, optional
        EPRY steps of the pupil refit.

    Returns
    -------
    Reading
    """
    obj = object_on_frame_grid(rec, factor)
    size = obj.shape[-1]
    if obj.shape != (factor * frames.n, factor * frames.n):
        raise ValueError(f"object region {obj.shape} is not {factor}× the {frames.n}² frames")
    m = frames.margin
    n = frames.n
    c = frames.centre_index
    centre = FrameModel(frames.intensity[c:c + 1], None, frames.centres[c:c + 1], frames.radius,
                        frames.bright_field[c:c + 1], 0, m)
    predicted = np.abs(_fft(_windows(_fft(obj), centre), inverse=True)[0]) ** 2
    shift = phase_correlation(frames.intensity[c, m:n - m, m:n - m], predicted[m:n - m, m:n - m])
    # the shift moves the whole (padded, periodic) grid; the frame region is cut again afterwards
    moved = replace(rec, spectrum=shift_spectrum(np.asarray(rec.spectrum, np.complex128), shift, rec.n))
    spectrum = _fft(object_on_frame_grid(moved, factor))
    windows = _windows(spectrum, frames)
    mask = frames.interior()
    measured = np.sqrt(np.clip(frames.intensity, 0, None)) * mask
    # tools scale their objects as they like: one least-squares scale first, so that A = 1 starts at the data's level
    start = np.abs(_fft(windows, inverse=True)) * mask
    level = float(np.sum(start * measured) / np.sum(start * start))
    windows *= np.float32(level)
    spectrum = spectrum * level
    pupil = refit_pupil(windows, frames, steps)
    model = np.abs(_fft(windows * pupil, inverse=True))
    from cca_cli.metrics import split_amplitude_residual  # the project's metric (main environment only)

    split = split_amplitude_residual(model * mask, measured, frames.bright_field)
    from_split = {"all": split.all, "bright_field": split.bright_field, "dark_field": split.dark_field,
                  "scale": split.scale}
    # display units: |ψ| = |object|·|A|·size/n for a flat object under orthonormal transforms
    disc = np.hypot(*np.mgrid[:n, :n] - n // 2) <= frames.radius
    gain = float(np.mean(np.abs(pupil[disc])))
    aligned = _fft(spectrum, inverse=True) * from_split["scale"] * gain * size / n
    k = model.shape[0]
    fitted = (model * mask).reshape(k, -1).astype(np.float64) * split.scale
    data = measured.reshape(k, -1).astype(np.float64)
    error2, reference2 = np.sum((fitted - data) ** 2, axis=1), np.sum(data * data, axis=1)
    return Reading(aligned, shift, pupil, from_split, error2, reference2)

