"""Deterministic synthetic scenes: a fingerprint-like ridge pattern, a face-like image, a printed label.

Stand-ins for the paper's Fig. 10 (fingerprint at 30 m), Fig. 11 (face at
1 km) and Fig. 9 (a diffuse water-bottle label). Amplitude images in [0, 1],
float32, no randomness.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fingerprint", "face", "label"]


def _coords(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates in [-1, 1) (y down, x right)."""
    t = (np.arange(size, dtype=np.float64) - size / 2.0) / (size / 2.0)
    return t[:, None], t[None, :]


def fingerprint(size: int, *, period_px: float) -> np.ndarray:
    """A whorl fingerprint: ridges of period ``period_px`` spiralling around a core, inside a finger outline.

    Parameters
    ----------
    size : int
        Side of the square image (px).
    period_px : float
        Ridge period (px); a real fingerprint has about 0.5 mm.

    Returns
    -------
    ndarray, float32, (size, size)
        Ridges ≈ 1, valleys ≈ 0.15, background 0.05.
    """
    if period_px < 2:
        raise ValueError(f"ridge period must be at least 2 px, got {period_px}")
    y, x = _coords(size)
    cy, cx = -0.05, 0.02
    yy, xx = (y - cy) * 0.85, (x - cx)
    r = np.hypot(yy, xx) * size / 2.0
    theta = np.arctan2(yy, xx)
    # Concentric rings plus one spiral turn (a whorl), bent by a slow warp.
    phase = r / period_px + theta / (2 * np.pi) + 0.6 * np.sin(1.7 * x + 0.9 * y)
    ridges = 0.5 + 0.5 * np.tanh(2.5 * np.cos(2 * np.pi * phase))
    outline = ((y - 0.05) / 0.9) ** 2 + (x / 0.68) ** 2
    inside = np.clip((1.0 - outline) * 12.0, 0.0, 1.0)
    image = 0.05 + inside * (0.1 + 0.85 * ridges)
    return image.astype(np.float32)


def _ellipse(y, x, cy, cx, ry, rx, soft: float = 0.02):
    d = np.hypot((y - cy) / ry, (x - cx) / rx)
    return np.clip((1.0 - d) / soft, 0.0, 1.0)


def face(size: int) -> np.ndarray:
    """A simple face: shaded oval head with hair, eyes, brows, nose and mouth on a grey background.

    Returns
    -------
    ndarray, float32, (size, size)
    """
    y, x = _coords(size)
    image = np.full((size, size), 0.35)
    head = _ellipse(y, x, 0.05, 0.0, 0.78, 0.58)
    shading = 0.75 + 0.2 * (-x * 0.6 - y * 0.3)  # light from the upper left
    image = image * (1 - head) + head * shading
    hair = _ellipse(y, x, -0.55, 0.0, 0.35, 0.62) * (y < -0.45)
    image = image * (1 - hair) + hair * 0.12
    for side in (-1, 1):
        cx = 0.24 * side
        white = _ellipse(y, x, -0.12, cx, 0.07, 0.14)
        iris = _ellipse(y, x, -0.12, cx, 0.065, 0.065)
        pupil = _ellipse(y, x, -0.12, cx, 0.028, 0.028)
        brow = _ellipse(y, x, -0.27, cx, 0.03, 0.16)
        image = image * (1 - white) + white * 0.95
        image = image * (1 - iris) + iris * 0.35
        image = image * (1 - pupil) + pupil * 0.05
        image = image * (1 - brow) + brow * 0.15
    nose = _ellipse(y, x, 0.15, 0.03, 0.16, 0.045)
    image = image * (1 - 0.35 * nose)
    nostrils = _ellipse(y, x, 0.29, -0.05, 0.02, 0.03) + _ellipse(y, x, 0.29, 0.05, 0.02, 0.03)
    image = image * (1 - 0.7 * np.clip(nostrils, 0, 1))
    mouth = _ellipse(y, x, 0.47, 0.0, 0.035, 0.2)
    image = image * (1 - mouth) + mouth * 0.25
    return np.clip(image, 0.0, 1.0).astype(np.float32)


def label(size: int) -> np.ndarray:
    """A printed label: uniform white (amplitude 1) with dark text-like stripes in its lower third.

    The upper half is uniform, so it serves to measure speckle contrast.

    Returns
    -------
    ndarray, float32, (size, size)
    """
    image = np.ones((size, size), np.float32)
    y, x = _coords(size)
    rows = (y > 0.4) & (y < 0.9)
    line = np.floor((y - 0.4) / 0.1)
    in_line = ((y - 0.4) % 0.1) < 0.06
    word = np.sin(2 * np.pi * (x * (6 + 2 * line) + 0.37 * line)) > 0.2
    text = rows & in_line & word & (np.abs(x) < 0.85)
    image[text] = 0.1
    return image
