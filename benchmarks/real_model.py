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
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Recovery", "circle_pupils", "predicted_fields", "embed_centred", "ifft2c", "fft2c"]


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
