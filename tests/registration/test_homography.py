"""Tests for homography estimation, warping and cropping on rendered boards."""

import numpy as np
import pytest

from cca_cli.registration import (
    HomographyFit,
    apply_homography,
    checkerboard_corners,
    crop,
    estimate_homography,
    find_checkerboard,
    render_checkerboard,
    stage_homography,
    valid_region,
    warp_to_reference,
    warp_views,
)

PATTERN = (7, 5)
SQUARE = 22.0
ORIGIN = (72.4, 53.8)
SHAPE = (240, 320)
CENTER = (160.0, 120.0)
# Per-view misalignment: shifts of tens of pixels, small rotation and perspective.
MISALIGN = [
    dict(shift_xy_px=(23.0, -14.0), rotation_deg=0.8, perspective=(2e-5, -1e-5)),
    dict(shift_xy_px=(-31.5, 9.2), rotation_deg=-1.5, perspective=(-3e-5, 0.0)),
    dict(shift_xy_px=(12.3, 27.7), rotation_deg=2.0, perspective=(0.0, 3e-5)),
    dict(shift_xy_px=(-18.0, -22.4), rotation_deg=-0.5, perspective=(1.5e-5, 1.5e-5)),
    dict(shift_xy_px=(40.1, 5.5), rotation_deg=1.2, perspective=(-2e-5, 2e-5)),
]


def rms(a, b):
    return float(np.sqrt(np.mean(np.sum((np.asarray(a, float) - b) ** 2, axis=1))))


def render(matrix=None):
    return render_checkerboard(
        SHAPE, PATTERN, square_px=SQUARE, origin_xy=ORIGIN, matrix=matrix, blur_px=1.0, supersample=2
    )


@pytest.fixture(scope="module")
def views():
    ref = render()
    ref_truth = checkerboard_corners(PATTERN, SQUARE, ORIGIN)
    ref_found = find_checkerboard(ref, PATTERN, source="reference")
    out = []
    for params in MISALIGN:
        h = stage_homography(center_xy=CENTER, **params)
        img = render(h)
        out.append(
            dict(
                h_true=h,
                image=img,
                truth=checkerboard_corners(PATTERN, SQUARE, ORIGIN, h),
                fit=estimate_homography(find_checkerboard(img, PATTERN), ref_found),
            )
        )
    return ref, ref_truth, out


def test_estimated_homographies_map_true_corners(views):
    _, ref_truth, out = views
    for v in out:
        fit = v["fit"]
        assert isinstance(fit, HomographyFit)
        assert fit.matrix.shape == (3, 3) and fit.matrix.dtype == np.float64
        assert fit.matrix[2, 2] == pytest.approx(1.0)
        assert fit.inliers == fit.n_points == 35
        assert fit.rms_px < 0.1
        mapped = apply_homography(v["truth"], fit.matrix)
        assert rms(mapped, ref_truth) < 0.1
        # and it is the inverse of the misalignment over the board area
        box = apply_homography(np.array([[60, 40], [260, 40], [260, 200], [60, 200]], float), v["h_true"])
        expected = apply_homography(box, np.linalg.inv(v["h_true"]))
        assert np.abs(apply_homography(box, fit.matrix) - expected).max() < 0.2


def test_warp_back_matches_reference(views):
    ref, _, out = views
    for v in out:
        warped = warp_to_reference(v["image"], v["fit"].matrix, ref.shape)
        assert warped.dtype == np.float32 and warped.shape == ref.shape
        mask = valid_region(v["image"].shape, v["fit"].matrix, ref.shape)
        interior = np.zeros_like(mask)
        interior[10:-10, 10:-10] = True
        sel = mask & interior
        assert sel.mean() > 0.6
        err = np.abs(warped - ref)[sel] / (1.0 - 0.05)  # relative to light - dark
        # measured: RMS 0.0035, max 0.03 (a 0.1 px error gives RMS 0.008)
        assert np.sqrt(np.mean(err**2)) < 0.006 and err.max() < 0.05


def test_warp_with_a_wrong_matrix_does_not_match(views):
    ref, _, out = views
    v = out[0]
    shifted = v["fit"].matrix.copy()
    shifted[0, 2] += 0.5  # half a pixel off
    warped = warp_to_reference(v["image"], shifted, ref.shape)
    sel = valid_region(v["image"].shape, shifted, ref.shape)
    err = np.abs(warped - ref)[sel] / 0.95
    assert np.sqrt(np.mean(err**2)) > 0.02  # measured 0.034


def test_warp_views_batch_and_masks(views):
    ref, _, out = views
    images = np.stack([v["image"] for v in out])
    mats = np.stack([v["fit"].matrix for v in out])
    stacked, masks = warp_views(images, mats, ref.shape, with_mask=True)
    assert stacked.shape == (5,) + ref.shape and masks.dtype == bool
    for k, v in enumerate(out):
        np.testing.assert_array_equal(stacked[k], warp_to_reference(v["image"], mats[k], ref.shape))
    assert np.array_equal(warp_views(images, mats, ref.shape), stacked)


def test_mask_of_a_translation():
    img = np.ones((50, 60), np.float32)
    h = np.array([[1, 0, 10], [0, 1, 5], [0, 0, 1]], float)  # source moves right 10, down 5
    warped, masks = warp_views(img[None], h[None], (50, 60), with_mask=True, interpolation="linear")
    mask = masks[0]
    assert not mask[:, :10].any() and not mask[:5, :].any()
    assert mask[5:, 10:].all()
    assert np.all(warped[0][mask] == 1.0) and np.all(warped[0][:, :9] == 0)
    cubic = valid_region(img.shape, h, (50, 60), interpolation="cubic")
    assert not cubic[:, 10].any() and cubic[6:-3, 11:-3].all()  # wider kernel, wider margin


def test_crop():
    stack = np.arange(2 * 20 * 30).reshape(2, 20, 30)
    c = crop(stack, (5, 3, 10, 4))
    assert c.shape == (2, 4, 10)
    np.testing.assert_array_equal(c, stack[:, 3:7, 5:15])
    with pytest.raises(ValueError) as err:
        crop(stack, (25, 3, 10, 4))
    msg = str(err.value)
    assert "x0=25" in msg and "width=10" in msg and "(2, 20, 30)" in msg
    for rect in [(-1, 0, 5, 5), (0, 0, 0, 5), (0, 18, 5, 5)]:
        with pytest.raises(ValueError):
            crop(stack, rect)


def test_estimate_rejects_degenerate_input():
    pts = np.array([[0, 0], [10, 0], [0, 10]], float)
    with pytest.raises(ValueError, match="at least 4"):
        estimate_homography(pts, pts)
    line = np.stack([np.arange(6.0), 2 * np.arange(6.0)], axis=1)
    with pytest.raises(ValueError, match="collinear"):
        estimate_homography(line, line + 1)
    with pytest.raises(ValueError):
        estimate_homography(np.zeros((5, 2)), np.zeros((6, 2)))


def test_apply_and_stage_homography():
    h = stage_homography((7.0, -3.0), rotation_deg=10.0, perspective=1e-4, center_xy=CENTER)
    assert h[2, 2] == 1.0
    np.testing.assert_allclose(apply_homography(np.array([CENTER]), h), [[167.0, 117.0]], atol=1e-9)
    pts = np.random.default_rng(0).uniform(0, 300, size=(20, 2))
    np.testing.assert_allclose(apply_homography(apply_homography(pts, h), np.linalg.inv(h)), pts, atol=1e-9)
    # positive rotation turns the x axis upwards on screen (y down)
    r = stage_homography((0, 0), rotation_deg=90.0)
    np.testing.assert_allclose(apply_homography(np.array([[1.0, 0.0]]), r), [[0.0, -1.0]], atol=1e-12)
