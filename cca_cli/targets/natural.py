"""A deterministic, natural-looking test photograph: a synthetic portrait on a 1/f background.

Natural images have a power spectrum falling roughly as 1/f², smooth shading
and a few sharp edges. The portrait below has all three: a 1/f-textured
backdrop, a shaded face with hair, eyes and mouth, and fine skin texture, so
recovering it exercises every spatial frequency of a synthetic aperture the
way the paper's portrait does, without shipping a photograph.
"""

from __future__ import annotations

import numpy as np

__all__ = ["pink_noise", "natural_portrait"]


def pink_noise(size: int, *, exponent: float = 1.0, seed: int = 0) -> np.ndarray:
    """Random field with amplitude spectrum ``1 / f**exponent``, scaled to [0, 1].

    Parameters
    ----------
    size : int
        Pixels across.
    exponent : float
        Spectral slope of the amplitude (1: natural-image 1/f).
    seed : int
        Generator seed; the same seed gives the same field.

    Returns
    -------
    ndarray, float32, (size, size)
    """
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(size)
    radius = np.hypot(f[:, None], f[None, :])
    radius[0, 0] = 1.0
    spectrum = (rng.standard_normal((size, size)) + 1j * rng.standard_normal((size, size))) / radius ** exponent
    spectrum[0, 0] = 0.0
    field = np.fft.ifft2(spectrum).real
    field -= field.min()
    peak = field.max()
    return (field / peak if peak > 0 else field).astype(np.float32)


def _ellipse(y, x, cy, cx, ry, rx, edge):
    """Soft-edged ellipse mask (1 inside, 0 outside, ``edge`` pixels of blur)."""
    r = np.sqrt(((y - cy) / ry) ** 2 + ((x - cx) / rx) ** 2)
    return np.clip((1.0 - r) * min(ry, rx) / max(edge, 1e-6) + 0.5, 0.0, 1.0)


def natural_portrait(size: int, *, seed: int = 7) -> np.ndarray:
    """A synthetic head-and-shoulders portrait, amplitude in [0.05, 1].

    Parameters
    ----------
    size : int
        Pixels across (the image is square).
    seed : int
        Seed of the textures; fixed by default so the image is reproducible.

    Returns
    -------
    ndarray, float32, (size, size)
        Amplitude (√irradiance) image.
    """
    n = int(size)
    if n < 16:
        raise ValueError(f"a portrait needs at least 16 pixels across, got {n}")
    y, x = np.mgrid[0:n, 0:n].astype(np.float64) / n
    edge = 1.5 / n
    image = 0.25 + 0.35 * pink_noise(n, exponent=1.0, seed=seed)          # backdrop
    shoulders = _ellipse(y, x, 1.05, 0.5, 0.32, 0.48, edge)
    image = image * (1 - shoulders) + shoulders * (0.30 + 0.15 * pink_noise(n, exponent=1.2, seed=seed + 1))
    neck = ((np.abs(x - 0.5) < 0.09) & (y > 0.55) & (y < 0.80)).astype(np.float64)
    image = image * (1 - neck) + neck * 0.62
    hair = _ellipse(y, x, 0.40, 0.5, 0.30, 0.25, edge)
    image = image * (1 - hair) + hair * (0.12 + 0.18 * pink_noise(n, exponent=0.6, seed=seed + 2))
    face = _ellipse(y, x, 0.46, 0.5, 0.24, 0.185, edge)
    shading = 0.72 + 0.18 * (0.5 - np.hypot(y - 0.38, x - 0.44))           # light from the upper left
    skin = shading + 0.05 * pink_noise(n, exponent=0.5, seed=seed + 3)
    image = image * (1 - face) + face * skin
    for cx in (0.42, 0.58):
        white = _ellipse(y, x, 0.42, cx, 0.022, 0.045, edge)
        image = image * (1 - white) + white * 0.95
        iris = _ellipse(y, x, 0.42, cx, 0.019, 0.019, edge)
        image = image * (1 - iris) + iris * 0.25
        pupil = _ellipse(y, x, 0.42, cx, 0.008, 0.008, edge)
        image = image * (1 - pupil) + pupil * 0.05
        brow = ((np.abs(y - 0.375 + 0.2 * (x - cx) ** 2) < 0.008) & (np.abs(x - cx) < 0.055)).astype(np.float64)
        image = image * (1 - brow) + brow * 0.18
    nose = ((np.abs(x - 0.505) < 0.006) & (y > 0.44) & (y < 0.53)).astype(np.float64)
    image -= 0.18 * nose
    mouth = _ellipse(y, x, 0.585, 0.5, 0.014, 0.07, edge) * (y > 0.58)
    image = image * (1 - mouth) + mouth * 0.35
    return np.clip(image, 0.05, 1.0).astype(np.float32)
