"""Register views to the centre view with checkerboard homographies (the only cv2 user)."""

from cca_cli.registration.checkerboard import canonical_corner_order, find_checkerboard
from cca_cli.registration.homography import (
    HomographyFit,
    apply_homography,
    crop,
    estimate_homography,
    valid_region,
    warp_to_reference,
    warp_views,
)
from cca_cli.registration.synthetic import checkerboard_corners, render_checkerboard, stage_homography

__all__ = [
    "HomographyFit",
    "apply_homography",
    "canonical_corner_order",
    "checkerboard_corners",
    "crop",
    "estimate_homography",
    "find_checkerboard",
    "render_checkerboard",
    "stage_homography",
    "valid_region",
    "warp_to_reference",
    "warp_views",
]
