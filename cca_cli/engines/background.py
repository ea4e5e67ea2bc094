"""Background light: what a capture holds that the object did not scatter.

Stray light (the room, the LED board's glow, reflections in the optics) and a camera offset left in the
images add light every capture shares but no object explains. The recovery takes it for the object's: in a
dark-field image the background can match the scattered light itself, and the object gains a haze of detail
that fits it (simulated phase cells with stray light of 0.2% of the bright-field mean: amplitude
correlation with the truth 0.98 without it, 0.37 with it).

With ``background: true`` each dark-field capture ``i`` is modelled as

    I_i = b_i |ψ_i|² + B_i,        B_i(y, x) = a_i + s_i y + t_i x,

a plane over the frame (``y``, ``x`` in pixels from its centre), fitted by weighted least squares to the
capture's measured intensity less its modelled one at each calibration round; the engine then fits the
object to ``√max(I_i − B_i, 0)``. Bright-field captures get no plane: a background is small against their
light, and a plane fitted to them would take up what the model has not yet explained of the object. Nor do
dark-field captures that fall to zero somewhere (:func:`holds_floor`): light under everything would keep them
off zero, and a dense sample's dark-field speckle, which reaches zero, would otherwise lend its own light to a
plane. A plane is held under its capture (:data:`FLOOR_PERCENTILE`) for the same reason.
"""

from __future__ import annotations

import numpy as np

from cca_cli.optics.forward import ForwardModel, Workspace, chunk_slices

__all__ = ["background_planes", "background_images", "less_background", "plane_means", "dark_field_captures",
           "holds_floor", "ZERO_SHARE", "FLOOR_PERCENTILE"]

#: Only captures whose darkest 1% of pixels lie at this share of their mean or more get a plane (ingest's note
#: on light under everything reads 0.2) ...
ZERO_SHARE = 0.1
#: ... and a plane is held under its capture's measured intensity at all but this percentage of the pixels ...
FLOOR_PERCENTILE = 5.0
#: ... smoothed over this many pixels square (the floor of a noisy image would lie under its background).
FLOOR_BOX = 5


def dark_field_captures(centres_px: np.ndarray, radius_px: float) -> np.ndarray:
    """Whether each capture's pupil centre lies outside the NA (a dark-field capture), bool (K,)."""
    centres = np.asarray(centres_px, np.float64)
    return np.hypot(centres[:, 0], centres[:, 1]) > radius_px


def _plane_grid(size: int) -> np.ndarray:
    """Pixel offsets from the frame's centre in field layout (origin at index 0), float64 (size,)."""
    return np.fft.ifftshift(np.arange(size) - size // 2).astype(np.float64)


def background_planes(model: ForwardModel, spectrum: np.ndarray, amplitudes: np.ndarray,
                      weights: np.ndarray | None, brightness: np.ndarray, fitted: np.ndarray,
                      workspace: Workspace | None = None) -> np.ndarray:
    """Each fitted capture's background plane: the weighted least-squares plane of ``I − b|ψ|²``.

    Parameters
    ----------
    model : ForwardModel
    spectrum : ndarray, complex64, (M, M)
    amplitudes : ndarray, float32, (K, m, m)
        Measured amplitudes ``√I`` (field layout, model units, the model's capture order).
    weights : ndarray, (K, m, m), optional
        Confidence of each pixel (0: not recorded).
    brightness : ndarray, (K,)
        Each capture's brightness ``b``.
    fitted : ndarray, bool, (K,)
        The captures that get a plane (the others' rows are 0).
    workspace : Workspace, optional

    Returns
    -------
    ndarray, float64, (K, 3)
        ``[a, s, t]`` per capture: the plane ``a + s y + t x`` (model intensity units, pixels from the centre).
    """
    k, m = model.n_images, model.layout.lowres_size
    out = np.zeros((k, 3))
    wanted = np.flatnonzero(fitted)
    if not wanted.size:
        return out
    grid = _plane_grid(m)
    workspace = workspace or model.workspace(min(32, k), threads=1)
    for sl in chunk_slices(k, workspace.capacity):
        inside = wanted[(wanted >= sl.start) & (wanted < sl.stop)]
        if not inside.size:
            continue
        fields = model.forward_into(spectrum, sl, workspace)
        measured = np.square(amplitudes[inside], dtype=np.float32)
        residual = np.abs(fields[inside - sl.start])
        np.square(residual, out=residual)
        residual *= np.asarray(brightness, np.float32)[inside, None, None]
        np.subtract(measured, residual, out=residual)
        w = np.ones_like(measured) if weights is None else np.asarray(weights[inside], np.float32)
        planes = _weighted_planes(w, residual, grid)
        planes[~(planes[:, 0] > 0)] = 0.0   # light is taken off, never added
        # Light under everything lies under the image: where the model has not yet explained the object's own
        # light, the fit would take that too, and rise above the image's dark parts.
        out[inside] = planes * _room_under(measured, planes, w, grid)[:, None]
    return out


def holds_floor(amplitudes: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Per capture, whether its darkest 1% of recorded pixels lie at :data:`ZERO_SHARE` of its mean or more.

    An image that falls to zero somewhere holds no light under everything: a dense sample's dark field, whose
    speckle reaches zero, would otherwise lend its own light to a plane.

    Parameters
    ----------
    amplitudes : ndarray, (K, m, m)
        Measured amplitudes ``√I``.
    weights : ndarray, (K, m, m), optional
        Confidence of each pixel (0: not recorded).

    Returns
    -------
    ndarray, bool, (K,)
    """
    out = np.zeros(len(amplitudes), bool)
    for i, image in enumerate(amplitudes):
        values = np.square(image if weights is None else image[weights[i] > 0], dtype=np.float32)
        mean = float(values.mean(dtype=np.float64)) if values.size else 0.0
        out[i] = mean > 0 and float(np.percentile(values, 1)) >= ZERO_SHARE * mean
    return out


def _weighted_planes(weights: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Per image, the weighted least-squares plane ``a + s y + t x`` of ``values``, (k, 3); 0 where undetermined."""
    def moments(image_stack: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rows = image_stack.sum(axis=2, dtype=np.float64)    # (k, y)
        cols = image_stack.sum(axis=1, dtype=np.float64)    # (k, x)
        return rows.sum(axis=1), rows @ grid, cols @ grid

    w0, wy, wx = moments(weights)
    wyy = weights.sum(axis=2, dtype=np.float64) @ grid ** 2
    wxx = weights.sum(axis=1, dtype=np.float64) @ grid ** 2
    wxy = (weights.astype(np.float64) @ grid) @ grid
    weighted = weights * values
    r0, ry, rx = moments(weighted)
    normal = np.stack([np.stack([w0, wy, wx], -1), np.stack([wy, wyy, wxy], -1), np.stack([wx, wxy, wxx], -1)], 1)
    right = np.stack([r0, ry, rx], -1)
    out = np.zeros_like(right)
    solvable = np.abs(np.linalg.det(normal)) > 1e-12 * np.maximum(w0, 1e-300) ** 3
    if solvable.any():
        out[solvable] = np.linalg.solve(normal[solvable], right[solvable][..., None])[..., 0]
    return out


def _room_under(intensity: np.ndarray, planes: np.ndarray, weights: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Per image, the largest factor in [0, 1] that keeps its plane under the image (smoothed over
    :data:`FLOOR_BOX` pixels, its noise averaged down) at all but :data:`FLOOR_PERCENTILE` percent of the
    recorded pixels; (k,). Field layout in, as the engine holds the images."""
    from scipy import ndimage

    # on the frame as the sensor saw it (the field layout puts its edges mid-array)
    shift = lambda a: np.fft.fftshift(a, axes=(-2, -1))
    level = shift(background_images(planes, intensity.shape[-1]))
    recorded = shift(weights > 0).astype(np.float32)
    box = (1, FLOOR_BOX, FLOOR_BOX)
    # judged where the whole smoothing window lies on recorded pixels (not across a frame's or guard band's edge)
    inside = ndimage.uniform_filter(recorded, box, mode="constant") > 1 - 1e-4
    smooth = ndimage.uniform_filter(shift(intensity) * recorded, box, mode="constant")
    judged = inside & (level > 0)
    # every other pixel along each axis is plenty for a percentile, and a quarter of the work
    ratio = np.where(judged, smooth / np.where(judged, level, 1.0), np.inf)[:, ::2, ::2].reshape(len(planes), -1)
    room = np.ones(len(planes))
    for i, row in enumerate(ratio):
        count = int(np.count_nonzero(np.isfinite(row)))
        if count:
            rank = int(FLOOR_PERCENTILE / 100 * (count - 1))
            room[i] = np.partition(row, rank)[rank]
    return np.clip(room, 0.0, 1.0)


def background_images(planes: np.ndarray, size: int) -> np.ndarray:
    """The planes ``a + s y + t x`` on the ``size`` × ``size`` frame, field layout, float32 (K, size, size)."""
    planes = np.asarray(planes, np.float64)
    grid = _plane_grid(size)
    return (planes[:, 0, None, None] + planes[:, 1, None, None] * grid[None, :, None]
            + planes[:, 2, None, None] * grid[None, None, :]).astype(np.float32)


def less_background(amplitudes: np.ndarray, planes: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``√max(A² − max(B, 0), 0)``: amplitudes of the light the object scattered, float32.

    ``amplitudes`` itself where no plane is set; otherwise ``out`` (a new array if None), filled a few
    captures at a time (no whole-stack temporaries). Where a plane dips under zero it takes nothing off.
    """
    planes = np.asarray(planes, np.float64)
    if not np.any(planes):
        return amplitudes
    if out is None:
        out = np.empty(np.shape(amplitudes), np.float32)
    size = out.shape[-1]
    for sl in chunk_slices(len(out), 16):
        block = np.square(amplitudes[sl], dtype=np.float32)
        block -= np.maximum(background_images(planes[sl], size), 0)
        np.maximum(block, 0, out=block)
        np.sqrt(block, out=out[sl])
    return out


def plane_means(planes: np.ndarray, size: int) -> np.ndarray:
    """Each plane's mean over a ``size`` × ``size`` frame (its pixel offsets from the centre average −1/2 for an
    even size, 0 for an odd one), float64 (K,)."""
    planes = np.asarray(planes, np.float64)
    offset = -0.5 if size % 2 == 0 else 0.0
    return planes[:, 0] + (planes[:, 1] + planes[:, 2]) * offset
