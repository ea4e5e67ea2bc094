"""Synthetic checkerboards and view misalignments for tests and sample data.

Board model
-----------
A board with ``pattern = (cols, rows)`` inner corners has ``cols + 1`` by
``rows + 1`` squares of side ``square_px``. In board-plane coordinates (the
pixel coordinates of an unwarped view) its outer top-left corner is at
``origin_xy`` and inner corner ``(i, j)`` (column ``i``, row ``j``) lies at
``origin_xy + ((i + 1) * square_px, (j + 1) * square_px)``. The top-left
square is dark and the board sits on a light background. An optional
homography maps board-plane coordinates to image coordinates. Pixel
centres are at integer coordinates, as in OpenCV.
"""

from __future__ import annotations

import cv2
import numpy as np

from cca_cli.registration.checkerboard import _check_pattern, _order
from cca_cli.registration.homography import apply_homography

__all__ = ["render_checkerboard", "checkerboard_corners", "stage_homography"]


def _filtered_axis(t: np.ndarray, rho: np.ndarray, n_squares: int) -> tuple[np.ndarray, np.ndarray]:
    """Box-filtered 1-D board factors along one axis.

    ``t`` is the coordinate in squares (board from 0 to ``n_squares``),
    ``rho`` the filter width in squares. Returns the filtered indicator of
    the board interval and the filtered square parity (+1 on even squares,
    -1 on odd ones, 0 off the board). Their products give the box-filtered
    checkerboard exactly for axis-aligned boards because a box filter is
    separable.
    """
    inside = np.minimum(np.clip(0.5 + t / rho, 0.0, 1.0), np.clip(0.5 + (n_squares - t) / rho, 0.0, 1.0))
    n = np.clip(np.rint(t), 0, n_squares)
    d = t - n
    parity = np.where(np.mod(n, 2) == 0, 1.0, -1.0)
    interior = parity * np.clip(2.0 * d / rho, -1.0, 1.0)
    first = np.clip(0.5 + d / rho, 0.0, 1.0)  # step 0 -> +1 at t = 0
    last = -parity * np.clip(0.5 - d / rho, 0.0, 1.0)  # step (-1)^(N-1) -> 0 at t = N
    sign = np.where(n == 0, first, np.where(n == n_squares, last, interior))
    return inside, sign


def render_checkerboard(
    shape,
    pattern,
    *,
    square_px: float,
    origin_xy,
    matrix=None,
    dark: float = 0.05,
    light: float = 1.0,
    supersample: int = 4,
    blur_px: float = 0.0,
) -> np.ndarray:
    """Render an antialiased checkerboard, optionally seen through a homography.

    Parameters
    ----------
    shape : tuple of int
        ``(height, width)`` of the output image.
    pattern : tuple of int
        Inner corners ``(columns, rows)``; the board has one more square
        each way.
    square_px : float
        Square side in board-plane pixels.
    origin_xy : tuple of float
        Board-plane position of the board's outer top-left corner.
    matrix : array_like or None, optional
        ``(3, 3)`` homography from board plane to image; None = identity.
    dark, light : float, optional
        Values of dark squares and of light squares and background.
    supersample : int, optional
        Sub-samples per pixel along each axis. Each sub-sample is itself
        box-filtered analytically over its footprint, so even 1 gives an
        antialiased image, exact for axis-aligned boards without blur; more
        sub-samples resolve the blur and perspective better. Default 4.
    blur_px : float, optional
        Standard deviation in pixels of a Gaussian optical blur (PSF),
        applied to the scene before pixel integration (0 = none). Real
        lenses blur edges by about a pixel; sub-pixel corner refinement is
        only unbiased for such smooth, properly sampled edges.

    Returns
    -------
    numpy.ndarray
        float32 ``(height, width)`` image.

    Notes
    -----
    The scene is evaluated on a sub-pixel grid (``supersample`` samples per
    pixel each way; each sample mapped back to the board plane with the
    inverse homography and box-filtered over its footprint using the
    distance to the nearest square edge), blurred there with the Gaussian
    PSF, and averaged over each pixel's area, so the image is what an ideal
    sensor behind a Gaussian lens records. Edges are therefore placed
    without sub-pixel bias, which the corner-accuracy tests rely on. Work is
    vectorised and done in chunks of rows (a few million samples each).
    """
    h, w = (int(v) for v in shape)
    if h < 1 or w < 1:
        raise ValueError(f"shape {shape!r} must be positive (height, width)")
    cols, rows = _check_pattern(pattern)
    if not square_px > 0:
        raise ValueError(f"square_px {square_px!r} must be > 0")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample {supersample!r} must be >= 1")
    if not blur_px >= 0:
        raise ValueError(f"blur_px {blur_px!r} must be >= 0")
    inv = np.eye(3) if matrix is None else np.linalg.inv(np.asarray(matrix, dtype=np.float64))
    if abs(inv[2, 2]) > 1e-12:
        inv = inv / inv[2, 2]  # sign convention: w > 0 in front of the horizon line
    ox, oy = (float(v) for v in origin_xy)

    def board(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Scene value at image points, box-filtered over a 1/s-pixel footprint."""
        num_u = inv[0, 0] * x + inv[0, 1] * y + inv[0, 2]
        num_v = inv[1, 0] * x + inv[1, 1] * y + inv[1, 2]
        den = inv[2, 0] * x + inv[2, 1] * y + inv[2, 2]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            u = ((num_u / den) - ox) / square_px  # board coordinates in squares
            v = ((num_v / den) - oy) / square_px
            # Footprint of a 1/s pixel along each board axis (projected box width).
            den2 = den * den * square_px * s
            rho_u = (np.abs(inv[0, 0] * den - num_u * inv[2, 0]) + np.abs(inv[0, 1] * den - num_u * inv[2, 1])) / den2
            rho_v = (np.abs(inv[1, 0] * den - num_v * inv[2, 0]) + np.abs(inv[1, 1] * den - num_v * inv[2, 1])) / den2
        ahead = den > 0
        u = np.where(ahead, u, -1e6)
        v = np.where(ahead, v, -1e6)
        rho_u = np.where(ahead & (rho_u > 0), rho_u, 1.0)
        rho_v = np.where(ahead & (rho_v > 0), rho_v, 1.0)
        in_u, sgn_u = _filtered_axis(u, rho_u, cols + 1)
        in_v, sgn_v = _filtered_axis(v, rho_v, rows + 1)
        dark_cover = 0.5 * (in_u * in_v + sgn_u * sgn_v)
        return (light + (dark - light) * dark_cover).astype(np.float32)

    # Render on a fine grid (spacing 1/s), blur there (the PSF acts before
    # the pixels integrate light), then average s x s blocks. A halo of
    # scene beyond the image edges keeps the blur correct at the borders.
    halo = int(np.ceil(4.0 * blur_px)) + 1 if blur_px > 0 else 0
    out = np.empty((h, w), np.float32)
    fine_cols = np.arange((w + 2 * halo) * s, dtype=np.float64)
    x_fine = (fine_cols + 0.5) / s - 0.5 - halo
    rows_per_chunk = max(1, int(4_000_000 // ((w + 2 * halo) * s * s)))
    for r0 in range(0, h, rows_per_chunk):
        r1 = min(h, r0 + rows_per_chunk)
        fine_rows = np.arange((r0 - halo) * s, (r1 + halo) * s, dtype=np.float64)
        y_fine = (fine_rows + 0.5) / s - 0.5
        fine = board(x_fine[None, :], y_fine[:, None])
        if blur_px > 0:
            fine = cv2.GaussianBlur(fine, (0, 0), float(blur_px) * s, borderType=cv2.BORDER_REPLICATE)
            fine = fine[halo * s : fine.shape[0] - halo * s, halo * s : fine.shape[1] - halo * s]
        out[r0:r1] = fine.reshape(r1 - r0, s, w, s).mean(axis=(1, 3), dtype=np.float64)
    return out


def checkerboard_corners(pattern, square_px: float, origin_xy, matrix=None) -> np.ndarray:
    """True inner-corner positions of a board drawn by :func:`render_checkerboard`.

    Parameters
    ----------
    pattern : tuple of int
        Inner corners ``(columns, rows)``.
    square_px : float
        Square side in board-plane pixels.
    origin_xy : tuple of float
        Board-plane position of the outer top-left corner.
    matrix : array_like or None, optional
        ``(3, 3)`` board-plane-to-image homography; None = identity.

    Returns
    -------
    numpy.ndarray
        float64 ``(columns * rows, 2)`` positions ``(x, y)`` in image pixels,
        in the canonical order :func:`find_checkerboard` returns.
    """
    cols, rows = _check_pattern(pattern)
    ox, oy = (float(v) for v in origin_xy)
    jj, ii = np.mgrid[0:rows, 0:cols].astype(np.float64)
    pts = np.stack([ox + (ii + 1) * square_px, oy + (jj + 1) * square_px], axis=-1).reshape(-1, 2)
    if matrix is not None:
        pts = apply_homography(pts, matrix)

    def corner_contrast(index_grid: np.ndarray) -> float:
        # The board's own corner square at model corner (i, j); the top-left
        # square (0, 0) is dark, so a square is dark when i + j is even.
        k = int(index_grid[0, 0])
        i, j = k % cols, k // cols
        si, sj = i + (i == cols - 1), j + (j == rows - 1)
        return -1.0 if (si + sj) % 2 == 0 else 1.0

    perm = _order(pts, cols, rows, corner_contrast)
    return np.ascontiguousarray(pts[perm.ravel()], dtype=np.float64)


def stage_homography(
    shift_xy_px,
    *,
    perspective=0.0,
    rotation_deg: float = 0.0,
    center_xy=(0.0, 0.0),
) -> np.ndarray:
    """A small homography simulating the misalignment of one stage position.

    Parameters
    ----------
    shift_xy_px : tuple of float
        Translation ``(dx, dy)`` in pixels.
    perspective : float or tuple of float, optional
        Projective terms ``(px, py)`` in 1/pixel (bottom row of the matrix,
        relative to ``center_xy``); a scalar sets both. Values around 1e-5
        change the scale by about 1 % over 1000 pixels.
    rotation_deg : float, optional
        In-plane rotation about ``center_xy`` in degrees (counter-clockwise
        on screen for positive values, y pointing down).
    center_xy : tuple of float, optional
        Fixed point of the rotation and perspective, e.g. the image centre.

    Returns
    -------
    numpy.ndarray
        float64 ``(3, 3)`` matrix with ``H[2, 2] == 1`` mapping the
        reference view to the misaligned view:
        ``T(center + shift) @ R @ P @ T(-center)``.
    """
    dx, dy = (float(v) for v in shift_xy_px)
    cx, cy = (float(v) for v in center_xy)
    p = np.broadcast_to(np.asarray(perspective, dtype=np.float64), (2,))
    a = np.deg2rad(float(rotation_deg))
    c, s = np.cos(a), np.sin(a)
    t_to = np.array([[1, 0, cx + dx], [0, 1, cy + dy], [0, 0, 1]], dtype=np.float64)
    rot = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]], dtype=np.float64)
    persp = np.array([[1, 0, 0], [0, 1, 0], [p[0], p[1], 1]], dtype=np.float64)
    t_from = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]], dtype=np.float64)
    m = t_to @ rot @ persp @ t_from
    return m / m[2, 2]
