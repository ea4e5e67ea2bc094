"""How well a board homography registers the *object*, not just the board corners.

The reprojection RMS of the board corners says how well the homography fits
the corners; the object may lie elsewhere (beside the board, or at its
edge), where the homography extrapolates. This module estimates the
registration error at any point of the reference view from two parts:

* **statistical**: the uncertainty of the fitted homography, propagated to
  the point. The corner residuals give the noise (``σ² = Σ r² / (2N − 8)``)
  and the Jacobian ``J`` of the mapped corners with respect to the eight
  homography parameters its covariance ``σ² (JᵀJ)⁻¹``; a point's mapped
  position then has covariance ``J_p Σ J_pᵀ``. It grows quickly outside the
  corners' hull.
* **systematic**: where a homography cannot follow the board (lens
  distortion, a bent board), the corner residuals vary smoothly. A
  cubic polynomial fitted to the residual vectors ("the board fit") is
  evaluated at the point (at the nearest point of the corners' bounding
  box outside it); its length, less what the corner noise alone would
  give the fit, is the model error there.

The estimate at a point is ``sqrt(statistical² + systematic²)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cca_cli.registration.homography import apply_homography

__all__ = ["ObjectError", "homography_covariance", "point_uncertainty", "board_fit_deviation", "object_error",
           "hull_fraction", "rectangle_points"]


@dataclass(frozen=True)
class ObjectError:
    """Estimated registration error over a region of the reference view.

    Attributes
    ----------
    rms_px : float
        RMS over the region's sample points (reference px).
    max_px : float
        Largest estimate over them.
    hull_fraction : float
        Share of the sample points inside the convex hull of the board
        corners (mapped to the reference); below 1 the homography extrapolates.
    """

    rms_px: float
    max_px: float
    hull_fraction: float


def _jacobian(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``(N, 2, 8)`` derivatives of mapped points with respect to h11…h32 (h33 = 1)."""
    h = matrix / matrix[2, 2]
    x, y = points[:, 0], points[:, 1]
    w = h[2, 0] * x + h[2, 1] * y + 1.0
    u = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
    v = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    jac = np.zeros((points.shape[0], 2, 8))
    jac[:, 0, 0], jac[:, 0, 1], jac[:, 0, 2] = x / w, y / w, 1.0 / w
    jac[:, 1, 3], jac[:, 1, 4], jac[:, 1, 5] = x / w, y / w, 1.0 / w
    jac[:, 0, 6], jac[:, 0, 7] = -u * x / w, -u * y / w
    jac[:, 1, 6], jac[:, 1, 7] = -v * x / w, -v * y / w
    return jac


def homography_covariance(moving, reference, matrix) -> np.ndarray:
    """Covariance ``(8, 8)`` of the homography parameters from its corner residuals.

    Parameters
    ----------
    moving, reference : array_like, (N, 2)
        The point pairs the homography was fitted to (inliers), N ≥ 5.
    matrix : array_like, (3, 3)
        The fitted moving-to-reference homography.
    """
    src = np.asarray(moving, np.float64).reshape(-1, 2)
    dst = np.asarray(reference, np.float64).reshape(-1, 2)
    m = np.asarray(matrix, np.float64)
    resid = apply_homography(src, m) - dst
    dof = max(2 * src.shape[0] - 8, 1)
    sigma2 = float(np.sum(resid**2)) / dof
    jac = _jacobian(src, m).reshape(-1, 8)
    # Parameters differ by orders of magnitude (h31 ~ 1e-5): scale columns before inverting.
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    normal = (jac / scale).T @ (jac / scale)
    return sigma2 * np.linalg.pinv(normal) / np.outer(scale, scale)


def point_uncertainty(points_moving, matrix, covariance) -> np.ndarray:
    """RMS position error (reference px) of moving-view points mapped through an uncertain homography."""
    pts = np.asarray(points_moving, np.float64).reshape(-1, 2)
    jac = _jacobian(pts, np.asarray(matrix, np.float64))
    cov = np.einsum("nik,kl,njl->nij", jac, covariance, jac)
    return np.sqrt(np.maximum(cov[:, 0, 0] + cov[:, 1, 1], 0.0))


def _cubic_terms(points: np.ndarray, centre: np.ndarray, span: np.ndarray) -> np.ndarray:
    x, y = ((points - centre) / span).T
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y, x**3, x * x * y, x * y * y, y**3], axis=1)


def board_fit_deviation(moving, reference, matrix, points_reference) -> np.ndarray:
    """Length of the smooth residual field of the corners (cubic fit) at reference points (px).

    The part the corner noise alone would give the fit (its variance times the fit's leverage at the
    point) is subtracted, so that a homography that fits is not charged twice for the noise. Points
    outside the corners' bounding box are evaluated at its nearest point.
    """
    src = np.asarray(moving, np.float64).reshape(-1, 2)
    dst = np.asarray(reference, np.float64).reshape(-1, 2)
    resid = dst - apply_homography(src, np.asarray(matrix, np.float64))
    lo, hi = dst.min(axis=0), dst.max(axis=0)
    centre, span = (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, 1e-9)
    design = _cubic_terms(dst, centre, span)
    n_terms = design.shape[1]
    pts = np.clip(np.asarray(points_reference, np.float64).reshape(-1, 2), lo, hi)
    if src.shape[0] < 2 * n_terms:
        return np.zeros(len(pts))
    coeffs, *_ = np.linalg.lstsq(design, resid, rcond=None)
    noise_var = float(np.sum((resid - design @ coeffs) ** 2)) / (2 * (src.shape[0] - n_terms))  # per coordinate
    terms = _cubic_terms(pts, centre, span)
    leverage = np.einsum("ni,ij,nj->n", terms, np.linalg.pinv(design.T @ design), terms)
    fitted = np.sum((terms @ coeffs) ** 2, axis=1)
    return np.sqrt(np.maximum(fitted - 2.0 * noise_var * leverage, 0.0))


def rectangle_points(rect, count: int = 9) -> np.ndarray:
    """``count x count`` points spanning a rectangle ``(x0, y0, width, height)`` of pixels (centres), as (x, y)."""
    x0, y0, w, h = (float(v) for v in rect)
    xs = np.linspace(x0, x0 + w - 1, count)
    ys = np.linspace(y0, y0 + h - 1, count)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def hull_fraction(points, hull_points) -> float:
    """Share of ``points`` inside the convex hull of ``hull_points`` (both (N, 2) as (x, y))."""
    import cv2

    hull = cv2.convexHull(np.asarray(hull_points, np.float32).reshape(-1, 1, 2))
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    inside = [cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0 for x, y in pts]
    return float(np.mean(inside)) if inside else 1.0


def object_error(moving, reference, matrix, rect, *, inliers=None, count: int = 9) -> ObjectError:
    """Registration error over the rectangle ``rect`` of the reference view.

    Parameters
    ----------
    moving, reference : array_like, (N, 2)
        Board corners in the view and in the reference view.
    matrix : array_like, (3, 3)
        Fitted view-to-reference homography.
    rect : tuple of int
        ``(x0, y0, width, height)`` in reference pixels (the object region).
    inliers : array_like of bool, optional
        RANSAC inliers (default: all corners).
    count : int
        Sample points per side of the rectangle.

    Returns
    -------
    ObjectError
    """
    src = np.asarray(moving, np.float64).reshape(-1, 2)
    dst = np.asarray(reference, np.float64).reshape(-1, 2)
    if inliers is not None:
        keep = np.asarray(inliers, bool)
        src, dst = src[keep], dst[keep]
    m = np.asarray(matrix, np.float64)
    points = rectangle_points(rect, count)
    moving_points = apply_homography(points, np.linalg.inv(m))
    statistical = point_uncertainty(moving_points, m, homography_covariance(src, dst, m))
    systematic = board_fit_deviation(src, dst, m, points)
    total = np.sqrt(statistical**2 + systematic**2)
    return ObjectError(rms_px=float(np.sqrt(np.mean(total**2))), max_px=float(total.max()),
                       hull_fraction=hull_fraction(points, apply_homography(src, m)))
