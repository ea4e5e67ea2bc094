"""Hot sensor pixels: found in every capture of a set, and filled from their neighbours.

A capture set images one field under many illuminations. A pixel that stands far above its neighbours by
much the same amount in nearly every capture, the dark-field ones too, is the sensor's, not the object's: an
object's detail follows each capture's light. Left in, each becomes an object detail no illumination
explains: streaks and a haze over a faint object. Left out (weight 0), the object under it goes unobserved
and keeps whatever the recovery puts there. Filled with the mean of its good neighbours, it reads as the
band-limited image would. (Dead pixels are not looked for: a coherent image's own zeros, the dark lines
between bars, look like them in the bright field.)
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["hot_pixels", "fill_pixels", "HOT_SIGMAS", "MOST_PIXELS"]

#: A hot pixel stands this many noise levels (1.4826 × the median absolute deviation of a capture's pixels from
#: their 3 × 3 medians) above its neighbours' median ...
HOT_SIGMAS = 10.0
#: ... in this share of the captures.
HOT_SHARE = 0.95
#: ... by much the same amount in each: the interquartile range of its excess under this fraction of its median.
STEADY_SPREAD = 0.5
#: More hot pixels than this share of the frame are not filled: the rule, not the sensor, is then wrong.
MOST_PIXELS = 0.01


def hot_pixels(images: np.ndarray) -> np.ndarray:
    """The pixels that stand far above their neighbours, by much the same amount, in nearly every capture.

    Parameters
    ----------
    images : ndarray, (K, H, W)
        Linear captures (any scale), of one exposure each, at least five.

    Returns
    -------
    ndarray, bool, (H, W)

    Raises
    ------
    ValueError
        Images that are not (K, H, W) with K ≥ 5.
    """
    frames = np.asarray(images, np.float32)
    if frames.ndim != 3 or len(frames) < 5:
        raise ValueError(f"images must be (K, H, W) with K ≥ 5, got shape {frames.shape}")
    neighbours = ndimage.median_filter(frames, size=(1, 3, 3), mode="nearest")
    above = frames - neighbours
    centred = above - np.median(above, axis=(1, 2), keepdims=True)
    noise = 1.4826 * np.median(np.abs(centred), axis=(1, 2), keepdims=True)
    noise = np.maximum(noise, 1e-6 * max(float(np.abs(frames).max()), 1e-30))   # quantised data: no spread
    hot = np.mean(above > HOT_SIGMAS * noise, axis=0) >= HOT_SHARE
    if hot.any():   # a sensor's excess is the same in every capture; an object's follows each capture's light
        low, middle, high = np.percentile(above[:, hot], [25, 50, 75], axis=0)
        hot[hot] = (high - low) < STEADY_SPREAD * middle
    return hot


def fill_pixels(images: np.ndarray, mask: np.ndarray) -> None:
    """Give each ``mask`` pixel of every image the mean of its good neighbours, in place.

    The neighbourhood is 3 × 3 pixels, widened where it holds no good pixel.

    Parameters
    ----------
    images : ndarray, float, (..., H, W)
    mask : ndarray, bool, (H, W)
    """
    mask = np.asarray(mask, bool)
    if not mask.any():
        return
    good = (~mask).astype(np.float32)
    for index in np.ndindex(images.shape[:-2]):
        image = images[index]   # a view: filled in place
        todo, size = mask.copy(), 3
        while todo.any() and size <= 65:
            total = ndimage.uniform_filter(image * good, size, mode="nearest")
            weight = ndimage.uniform_filter(good, size, mode="nearest")
            found = todo & (weight > 1e-6)
            image[found] = (total[found] / weight[found]).astype(image.dtype)
            todo &= ~found
            size = 2 * size + 1
