"""Sensor defects found in every capture of a set, and filled from their neighbours: hot pixels, dead lines.

A capture set images one field under many illuminations. A pixel that stands far above its neighbours by
much the same amount in nearly every capture, the dark-field ones too, is the sensor's, not the object's: an
object's detail follows each capture's light. Left in, each becomes an object detail no illumination
explains: streaks and a haze over a faint object. Left out (weight 0), the object under it goes unobserved
and keeps whatever the recovery puts there. Filled with the mean of its good neighbours, it reads as the
band-limited image would.

A whole column (or row) of pixels that does not follow its two neighbours at all, over the bright captures,
is a dead (or stuck) line of the sensor: an image band-limited by the objective varies smoothly from one
pixel to the next, so each line of a live sensor follows its neighbours with a slope near 1. Single
dead pixels are not looked for: a coherent image's own zeros, the dark lines between bars, look like them in
the bright field.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["hot_pixels", "dead_lines", "fill_pixels", "HOT_SIGMAS", "MOST_PIXELS", "LINE_SLOPE"]

#: A hot pixel stands this many noise levels (1.4826 × the median absolute deviation of a capture's pixels from
#: their 3 × 3 medians) above its neighbours' median ...
HOT_SIGMAS = 10.0
#: ... in this share of the captures.
HOT_SHARE = 0.95
#: ... by much the same amount in each: the interquartile range of its excess under this fraction of its median.
STEADY_SPREAD = 0.5
#: More hot pixels than this share of the frame are not filled: the rule, not the sensor, is then wrong.
MOST_PIXELS = 0.01
#: A dead line follows each of its neighbours with a slope under this share of the median line's (on the
#: corpus's recorded sets every live line's is 0.39 of the median or more, on simulated sets of 30 photons in
#: the brightest dark-field pixel 0.22 or more; a dead column's 0.00) ...
LINE_SLOPE = 0.1
#: ... where those neighbours vary by at least this share of the median line's neighbours (a line through a
#: dark, featureless part of the frame follows nothing and is not judged) ...
LIVE_SHARE = 0.3
#: ... over the captures with at least this share of the brightest capture's mean (noise-dominated dark-field
#: images would pull every line's slope down) ...
BRIGHT_SHARE = 0.1
#: ... and only where the median line follows its neighbours with a slope of at least this (an image of
#: detail; in a flat or featureless field the lines follow nothing, and chance would pick some).
FOLLOWS = 0.5


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
    frames = _stack(images).astype(np.float32, copy=False)
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


def _stack(images: np.ndarray) -> np.ndarray:
    """``images`` as an array, refused unless (K, H, W) with K ≥ 5."""
    frames = np.asarray(images)
    if frames.ndim != 3 or len(frames) < 5:
        raise ValueError(f"images must be (K, H, W) with K ≥ 5, got shape {frames.shape}")
    return frames


def dead_lines(images: np.ndarray) -> np.ndarray:
    """The pixels of whole columns and rows that do not follow their neighbours: dead or stuck lines.

    For every inner column, over every row of the bright captures, the least-squares slopes of the column's
    values on its left and on its right neighbour's; a column whose slopes are both under :data:`LINE_SLOPE`
    times the median column's, where both neighbours vary (:data:`LIVE_SHARE`), is dead; likewise on the
    columns two away, under half that (two dead columns side by side; live lines follow those less). Rows
    likewise. The outermost lines have one neighbour and are not judged; nor is a set whose median line
    hardly follows its next neighbours (:data:`FOLLOWS`).

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
    frames = _stack(images)
    means = frames.mean(axis=(1, 2), dtype=np.float64)
    bright = np.flatnonzero(means >= BRIGHT_SHARE * max(float(means.max()), 0.0))
    dead = np.zeros(frames.shape[1:], bool)
    for axis in (1, 0):   # columns, then rows (the lines along each image's first axis)
        found = np.zeros(frames.shape[1 + axis], bool)
        # judged by the lines next to each (gap 1), and by those two away (gap 2): two dead lines side by side
        # each have a dead neighbour
        for gap in (1, 2):
            slope, live = _line_slopes(frames, bright, axis, gap)
            typical = float(np.median(slope[live])) if live.any() else 0.0
            if gap == 1 and typical < FOLLOWS:   # lines that do not follow each other (a flat or featureless
                break                            # field): no judgement
            if typical <= 0:
                continue
            found[gap:-gap] |= live & (slope < LINE_SLOPE / gap * typical)
        if axis == 1:
            dead[:, found] = True
        else:
            dead[found, :] = True
    return dead


def _line_slopes(frames: np.ndarray, captures: np.ndarray, axis: int, gap: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Each line's slope on each of the two lines ``gap`` away (the larger of the two), and whether both vary
    enough to judge it by; for the lines ``gap`` … ``n − gap − 1``.

    Judged by each neighbour on its own, a line at the edge of a dark band (one neighbour as dark as itself) is
    not taken for dead. Sums are taken capture by capture (one image's temporaries at a time), in float64.
    """
    inner = frames.shape[1 + axis] - 2 * gap
    if inner < 1:
        return np.ones(0), np.zeros(0, bool)
    sums = {name: np.zeros(inner) for name in ("p", "l", "r", "pl", "pr", "ll", "rr")}
    count = 0
    for k in captures:
        image = np.asarray(frames[k], np.float64)
        if axis == 0:
            image = image.T
        line, left, right = image[:, gap:-gap], image[:, :-2 * gap], image[:, 2 * gap:]
        for name, value in (("p", line), ("l", left), ("r", right), ("pl", line * left), ("pr", line * right),
                            ("ll", left * left), ("rr", right * right)):
            sums[name] += value.sum(axis=0)
        count += image.shape[0]
    if count == 0:
        return np.ones(inner), np.zeros(inner, bool)
    mean = {name: value / count for name, value in sums.items()}
    slopes, spreads = [], []
    for side in ("l", "r"):
        variance = np.maximum(mean[side + side] - mean[side] ** 2, 0.0)
        slopes.append((mean["p" + side] - mean["p"] * mean[side]) / np.maximum(variance, 1e-300))
        spreads.append(np.sqrt(variance))
    typical = np.median(np.concatenate(spreads))
    live = (spreads[0] > LIVE_SHARE * typical) & (spreads[1] > LIVE_SHARE * typical)
    return np.maximum(slopes[0], slopes[1]), live


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
