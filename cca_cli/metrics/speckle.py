"""Speckle contrast: standard deviation over mean of the intensity in a uniform region."""

from __future__ import annotations

import numpy as np

__all__ = ["speckle_contrast"]


def speckle_contrast(intensity, region: tuple[int, int, int, int] | None = None) -> float:
    """Speckle contrast ``C = σ / μ`` of an intensity image over a region.

    Parameters
    ----------
    intensity : array_like, (H, W)
        Real intensity image.
    region : tuple of int, optional
        Half-open box ``(y0, y1, x0, x1)`` over a region that is uniform in
        the object; default the whole image.

    Returns
    -------
    float
        1 for fully developed speckle, 0 for a uniform image; NaN when the
        region's mean is not positive.

    Raises
    ------
    ValueError
        If the image is not real 2-D or the region is empty or outside it.
    """
    image = np.asarray(intensity)
    if image.ndim != 2 or np.iscomplexobj(image):
        raise ValueError(f"intensity: expected a real 2-D array, got shape {image.shape} dtype {image.dtype}")
    if region is not None:
        y0, y1, x0, x1 = (int(v) for v in region)
        h, w = image.shape
        if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
            raise ValueError(f"region: box {tuple(region)} is empty or outside the {h}x{w} image")
        image = image[y0:y1, x0:x1]
    values = image.astype(np.float64)
    mean = float(values.mean())
    if not mean > 0:
        return float("nan")
    return float(values.std() / mean)
