"""Estimate homographies between views and warp views onto the reference.

Coordinates are OpenCV pixel coordinates: ``(x, y)`` with the centre of
pixel ``[row, col]`` at ``(col, row)``. A matrix maps moving-view
coordinates to reference-view coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "HomographyFit",
    "estimate_homography",
    "apply_homography",
    "warp_to_reference",
    "warp_views",
    "valid_region",
    "crop",
]

_INTERP = {
    "nearest": cv2.INTER_NEAREST,
    "linear": cv2.INTER_LINEAR,
    "cubic": cv2.INTER_CUBIC,
    "lanczos": cv2.INTER_LANCZOS4,
}
# Source-pixel margin each interpolation kernel needs on the low and high
# side of a sample position so that no tap falls outside the image.
_MARGIN = {"nearest": (-0.5, 0.5), "linear": (0.0, 1.0), "cubic": (1.0, 2.0), "lanczos": (3.0, 4.0)}


@dataclass(frozen=True)
class HomographyFit:
    """A fitted homography and how well it fits the points.

    Attributes
    ----------
    matrix : numpy.ndarray
        float64 ``(3, 3)`` mapping moving to reference pixel coordinates,
        scaled so that ``matrix[2, 2] == 1``.
    rms_px : float
        Root-mean-square reprojection error over the inliers, in reference
        pixels.
    max_px : float
        Largest reprojection error over the inliers.
    inliers : int
        Number of RANSAC inliers.
    n_points : int
        Number of point pairs given.
    inlier_mask : numpy.ndarray or None
        bool ``(n_points,)``, True for the RANSAC inliers.
    """

    matrix: np.ndarray
    rms_px: float
    max_px: float
    inliers: int
    n_points: int
    inlier_mask: np.ndarray | None = None


def _as_points(points, name: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim == 3 and pts.shape[1] == 1:
        pts = pts[:, 0, :]
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"{name} have shape {np.shape(points)}; expected (N, 2)")
    if not np.isfinite(pts).all():
        raise ValueError(f"{name} contain NaN or infinite coordinates")
    return pts


def _check_matrix(matrix) -> np.ndarray:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (3, 3) or not np.isfinite(m).all():
        raise ValueError(f"homography must be a finite (3, 3) matrix, got shape {m.shape}")
    return m


def apply_homography(points, matrix) -> np.ndarray:
    """Map points through a homography.

    Parameters
    ----------
    points : array_like
        ``(N, 2)`` (or ``(..., 2)``) coordinates ``(x, y)``.
    matrix : array_like
        ``(3, 3)`` homography.

    Returns
    -------
    numpy.ndarray
        float64 coordinates of the same shape. Points mapped to infinity
        come out as inf/NaN.
    """
    m = _check_matrix(matrix)
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-1] != 2:
        raise ValueError(f"points have shape {pts.shape}; the last axis must hold (x, y)")
    x, y = pts[..., 0], pts[..., 1]
    w = m[2, 0] * x + m[2, 1] * y + m[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (m[0, 0] * x + m[0, 1] * y + m[0, 2]) / w
        v = (m[1, 0] * x + m[1, 1] * y + m[1, 2]) / w
    return np.stack([u, v], axis=-1)


def estimate_homography(moving_points, reference_points, *, ransac_threshold_px: float = 1.0) -> HomographyFit:
    """Fit the homography that maps moving-view points onto reference points.

    Parameters
    ----------
    moving_points : array_like
        ``(N, 2)`` points in the view to be registered.
    reference_points : array_like
        ``(N, 2)`` corresponding points in the reference view.
    ransac_threshold_px : float, optional
        RANSAC inlier threshold in reference pixels (default 1.0).

    Returns
    -------
    HomographyFit
        Matrix (moving to reference, ``H[2, 2] == 1``) and inlier residuals.

    Raises
    ------
    ValueError
        Fewer than 4 pairs, mismatched shapes, points that are (nearly)
        collinear, or no valid homography found.

    Notes
    -----
    ``cv2.findHomography`` with RANSAC picks the inliers and refines the
    matrix on them with Levenberg-Marquardt. The residuals are the
    distances between mapped moving points and reference points.
    """
    src = _as_points(moving_points, "moving points")
    dst = _as_points(reference_points, "reference points")
    if src.shape != dst.shape:
        raise ValueError(f"moving points {src.shape} and reference points {dst.shape} differ in number")
    n = src.shape[0]
    if n < 4:
        raise ValueError(f"a homography needs at least 4 point pairs, got {n}")
    if not ransac_threshold_px > 0:
        raise ValueError(f"ransac_threshold_px {ransac_threshold_px!r} must be > 0")
    for pts, name in ((src, "moving points"), (dst, "reference points")):
        sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if sv[0] == 0 or sv[1] < 1e-6 * sv[0]:
            raise ValueError(f"{name} are (nearly) collinear; a homography needs points spread over an area")

    matrix, mask = cv2.findHomography(src, dst, cv2.RANSAC, float(ransac_threshold_px), maxIters=5000, confidence=0.999)
    if matrix is None or mask is None or not np.isfinite(matrix).all() or abs(matrix[2, 2]) < 1e-12:
        raise ValueError("no valid homography found for these points (degenerate configuration)")
    matrix = matrix / matrix[2, 2]
    if abs(np.linalg.det(matrix)) < 1e-12:
        raise ValueError("estimated homography is singular (degenerate point configuration)")
    inl = mask.ravel().astype(bool)
    if inl.sum() < 4:
        raise ValueError(f"only {int(inl.sum())} RANSAC inliers; need at least 4")
    resid = np.linalg.norm(apply_homography(src[inl], matrix) - dst[inl], axis=1)
    return HomographyFit(
        matrix=matrix,
        rms_px=float(np.sqrt(np.mean(resid**2))),
        max_px=float(resid.max()),
        inliers=int(inl.sum()),
        n_points=int(n),
        inlier_mask=inl,
    )


def _check_shape(shape) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise ValueError(f"output shape {shape!r} must be (height, width)") from None
    if h < 1 or w < 1:
        raise ValueError(f"output shape {shape!r} must be positive")
    return h, w


def _interp(interpolation: str) -> int:
    try:
        return _INTERP[interpolation]
    except KeyError:
        raise ValueError(
            f"interpolation {interpolation!r} unknown; use one of {', '.join(_INTERP)}"
        ) from None


def valid_region(source_shape, matrix, shape, *, interpolation: str = "cubic") -> np.ndarray:
    """Reference pixels whose warped value comes entirely from inside the source.

    Parameters
    ----------
    source_shape : tuple of int
        ``(H, W)`` of the moving (source) image.
    matrix : array_like
        ``(3, 3)`` moving-to-reference homography.
    shape : tuple of int
        ``(height, width)`` of the reference (output) grid.
    interpolation : str, optional
        Kernel used for the warp (``nearest``, ``linear``, ``cubic``,
        ``lanczos``); wider kernels need a wider margin inside the source.

    Returns
    -------
    numpy.ndarray
        bool ``shape`` mask, True where every interpolation tap lies inside
        the source image.
    """
    _interp(interpolation)
    h, w = _check_shape(shape)
    sh, sw = _check_shape(source_shape)
    inv = np.linalg.inv(_check_matrix(matrix))
    if abs(inv[2, 2]) > 1e-12:
        inv = inv / inv[2, 2]  # sign convention: w > 0 in front of the horizon line
    lo, hi = _MARGIN[interpolation]
    mask = np.empty((h, w), bool)
    xs = np.arange(w, dtype=np.float64)[None, :]
    step = max(1, 1_000_000 // w)  # rows per chunk, to bound memory on large frames
    for r0 in range(0, h, step):
        ys = np.arange(r0, min(h, r0 + step), dtype=np.float64)[:, None]
        den = inv[2, 0] * xs + inv[2, 1] * ys + inv[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2]) / den
            v = (inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2]) / den
        mask[r0 : r0 + step] = (
            (den > 0) & (u >= lo) & (u <= sw - 1 - hi + 1e-9) & (v >= lo) & (v <= sh - 1 - hi + 1e-9)
        )
    return mask


def warp_to_reference(image, matrix, shape, *, interpolation: str = "cubic") -> np.ndarray:
    """Resample a moving view onto the reference pixel grid.

    Parameters
    ----------
    image : array_like
        ``(H, W)`` moving view.
    matrix : array_like
        ``(3, 3)`` moving-to-reference homography.
    shape : tuple of int
        ``(height, width)`` of the reference grid.
    interpolation : str, optional
        ``nearest``, ``linear``, ``cubic`` (default) or ``lanczos``.

    Returns
    -------
    numpy.ndarray
        float32 ``shape`` image; pixels that map outside the source are 0.

    Notes
    -----
    Uses ``cv2.warpPerspective`` with a constant 0 border. OpenCV quantises
    sample positions to 1/32 pixel. Cubic and Lanczos kernels can overshoot
    at sharp edges; use :func:`valid_region` for the trustworthy pixels.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image has shape {img.shape}; expected (H, W)")
    m = _check_matrix(matrix)
    h, w = _check_shape(shape)
    src = np.ascontiguousarray(img, dtype=np.float32)
    out = cv2.warpPerspective(
        src, m, (w, h), flags=_interp(interpolation), borderMode=cv2.BORDER_CONSTANT, borderValue=0.0
    )
    return out.astype(np.float32, copy=False)


def warp_views(images, matrices, shape, *, interpolation: str = "cubic", with_mask: bool = False):
    """Warp a stack of views onto the reference grid.

    Parameters
    ----------
    images : array_like
        ``(K, H, W)`` moving views.
    matrices : array_like
        ``(K, 3, 3)`` moving-to-reference homographies.
    shape : tuple of int
        ``(height, width)`` of the reference grid.
    interpolation : str, optional
        Passed to :func:`warp_to_reference`.
    with_mask : bool, optional
        Also return the validity masks of :func:`valid_region`.

    Returns
    -------
    numpy.ndarray or tuple of numpy.ndarray
        float32 ``(K, height, width)`` views; with ``with_mask=True`` a tuple
        ``(views, masks)`` with bool masks of the same shape.
    """
    imgs = np.asarray(images)
    mats = np.asarray(matrices, dtype=np.float64)
    if imgs.ndim != 3:
        raise ValueError(f"images have shape {imgs.shape}; expected (K, H, W)")
    if mats.shape != (imgs.shape[0], 3, 3):
        raise ValueError(f"matrices have shape {mats.shape}; expected ({imgs.shape[0]}, 3, 3)")
    h, w = _check_shape(shape)
    views = np.empty((imgs.shape[0], h, w), np.float32)
    masks = np.empty((imgs.shape[0], h, w), bool) if with_mask else None
    for k in range(imgs.shape[0]):
        views[k] = warp_to_reference(imgs[k], mats[k], (h, w), interpolation=interpolation)
        if masks is not None:
            masks[k] = valid_region(imgs.shape[1:], mats[k], (h, w), interpolation=interpolation)
    return (views, masks) if with_mask else views


def crop(images, rect: tuple[int, int, int, int]) -> np.ndarray:
    """Cut a rectangle out of an image or a stack of images.

    Parameters
    ----------
    images : array_like
        ``(..., H, W)`` array (any dtype, e.g. views or masks).
    rect : tuple of int
        ``(x0, y0, width, height)`` in reference pixels.

    Returns
    -------
    numpy.ndarray
        ``(..., height, width)`` contiguous copy, same dtype.

    Raises
    ------
    ValueError
        The rectangle is empty or does not lie inside the image.
    """
    arr = np.asarray(images)
    if arr.ndim < 2:
        raise ValueError(f"images have shape {arr.shape}; expected (..., H, W)")
    try:
        x0, y0, w, h = (int(v) for v in rect)
    except (TypeError, ValueError):
        raise ValueError(f"crop rect {rect!r} must be four integers (x0, y0, width, height)") from None
    H, W = arr.shape[-2:]
    if w < 1 or h < 1 or x0 < 0 or y0 < 0 or x0 + w > W or y0 + h > H:
        raise ValueError(
            f"crop rect (x0={x0}, y0={y0}, width={w}, height={h}) does not fit inside the "
            f"image of shape {tuple(arr.shape)} ({W} wide, {H} high)"
        )
    return np.ascontiguousarray(arr[..., y0 : y0 + h, x0 : x0 + w])
