"""The registration error estimated where the object is, against the true error of synthetic fits."""

import numpy as np
import pytest

from cca_cli.registration.accuracy import hull_fraction, object_error, rectangle_points
from cca_cli.registration.homography import apply_homography, estimate_homography
from cca_cli.registration.synthetic import checkerboard_corners, stage_homography

BOARD = checkerboard_corners((8, 5), 12.0, (18.0, 12.0))   # inner corners x 30..114, y 24..72


def _trials(rect, n=60, noise=0.03, distortion=0.0, seed=0):
    rng = np.random.default_rng(seed)
    true_rms, estimated = [], []
    points = rectangle_points(rect, 9)
    for _ in range(n):
        truth = stage_homography(rng.normal(0, 3, 2), perspective=rng.normal(0, 2e-5, 2),
                                 rotation_deg=rng.normal(0, 0.5), center_xy=(72, 48))
        centre = apply_homography(BOARD, truth).mean(axis=0)

        def lens(xy):  # radial distortion of the view's lens: the board and the object alike
            return xy + distortion * np.sum((xy - centre) ** 2, axis=-1, keepdims=True) * (xy - centre)

        view = lens(apply_homography(BOARD, truth)) + rng.normal(0, noise, BOARD.shape)
        reference = BOARD + rng.normal(0, noise, BOARD.shape)
        fit = estimate_homography(view, reference)
        estimated.append(object_error(view, reference, fit.matrix, rect, inliers=fit.inlier_mask))
        mapped = apply_homography(lens(apply_homography(points, truth)), fit.matrix)
        true_rms.append(np.sqrt(np.mean(np.sum((mapped - points) ** 2, axis=1))))
    return np.array(true_rms), estimated


@pytest.mark.parametrize("rect", [(40, 30, 60, 30), (150, 20, 40, 40)])
def test_estimate_follows_the_true_error_inside_and_outside_the_board(rect):
    true_rms, estimated = _trials(rect)
    reported = np.mean([e.rms_px for e in estimated])
    assert 0.7 * true_rms.mean() <= reported <= 2.0 * true_rms.mean(), (reported, true_rms.mean())


def test_extrapolation_is_flagged_and_grows():
    inside_true, inside = _trials((40, 30, 60, 30), n=20)
    outside_true, outside = _trials((200, 90, 40, 40), n=20)
    assert inside[0].hull_fraction == 1.0 and outside[0].hull_fraction == 0.0
    assert np.mean([e.rms_px for e in outside]) > 3 * np.mean([e.rms_px for e in inside])
    assert outside_true.mean() > 3 * inside_true.mean()


def test_a_distortion_the_homography_cannot_follow_is_reported():
    # Lens distortion moves the board and the object alike; the homography cannot follow it.
    true_rms, estimated = _trials((40, 30, 60, 30), n=10, noise=0.01, distortion=3e-6)
    reported = np.mean([e.rms_px for e in estimated])
    plain = np.mean([e.rms_px for e in _trials((40, 30, 60, 30), n=10, noise=0.01)[1]])
    assert reported > 3 * plain
    assert 0.7 * true_rms.mean() <= reported <= 1.5 * true_rms.mean(), (reported, true_rms.mean())


def test_hull_fraction():
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    assert hull_fraction([[5, 5], [20, 5]], square) == 0.5
