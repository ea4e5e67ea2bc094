"""Light under everything: dark-field images that never fall near zero.

A dark-field image holds only the light the object scatters into the objective, so a sparse sample's leaves
much of the frame near zero. Where the darkest pixels of nearly every dark-field image stay well above zero,
light the object did not scatter lies under them: a camera offset left in, or stray light from the room, the
LED board or the optics. Ingest names it in a note, and reconstruct then fits it
(:mod:`cca_cli.engines.background`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["dark_field_floor", "holds_stray_light", "FLOOR_SHARE"]

#: Dark-field images whose darkest 1% of pixels read this fraction of their mean or more (the median over them)
#: carry light the object did not scatter. The recorded corpus's sets read 0–0.10 (the blood smear's dense
#: cells 0.10); a 16-bit camera's 100-count offset left in, 0.31; simulated stray light of 0.2–2% of the
#: bright-field mean 0.40–0.57 behind sparse phase cells and a USAF chart. What a given stray light reads
#: depends on the object: over a chart whose dark field is bright, 2% read 0.18.
FLOOR_SHARE = 0.2
#: Pixels read per image at most (every s-th along each axis).
MOST_PIXELS = 65536


def dark_field_floor(images: np.ndarray, centres_px: np.ndarray, radius_px: float,
                     weights: np.ndarray | None = None, *, amplitudes: bool = False) -> tuple[float, int] | None:
    """The median, over the lit dark-field images, of their darkest 1% of pixels over their mean.

    Parameters
    ----------
    images : ndarray, (K, H, W)
        Linear captures, one exposure each.
    centres_px : ndarray, (K, 2)
        Each capture's pupil centre relative to DC (spectrum px): dark-field ones lie beyond 1.2 radii.
    radius_px : float
        The pupil's radius (spectrum px).
    weights : ndarray, (K, H, W), optional
        Pixels of weight 0 are not read.
    amplitudes : bool
        The images hold amplitudes (square roots of intensity): they are squared first, as the recovery
        reads them.

    Returns
    -------
    (share, images) or None
        The median share and how many images it is the median of; None with fewer than five lit
        dark-field images.
    """
    centres = np.asarray(centres_px, np.float64)
    dark = np.flatnonzero(np.hypot(centres[:, 0], centres[:, 1]) > 1.2 * radius_px)
    shares = []
    for k in dark:
        # a percentile reads as well from every s-th pixel along each axis (at most about 65 000 of them)
        image = np.asarray(images[k])
        step = max(1, int(np.ceil(np.sqrt(image.size / MOST_PIXELS))))
        image = image[::step, ::step]
        values = image.ravel() if weights is None else image[np.asarray(weights[k])[::step, ::step] > 0]
        if amplitudes:
            values = np.square(values, dtype=np.float64)
        mean = float(values.mean(dtype=np.float64)) if values.size else 0.0
        if mean > 0:
            shares.append(float(np.percentile(values, 1)) / mean)
    if len(shares) < 5:
        return None
    return float(np.median(shares)), len(shares)


def holds_stray_light(images: np.ndarray, centres_px: np.ndarray, radius_px: float,
                      weights: np.ndarray | None = None) -> bool:
    """Whether the dark-field images never fall near zero (:func:`dark_field_floor` ≥ :data:`FLOOR_SHARE`)."""
    found = dark_field_floor(images, centres_px, radius_px, weights)
    return found is not None and found[0] >= FLOOR_SHARE
