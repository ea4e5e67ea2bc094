"""Tests for cca_cli.registration.find_checkerboard on synthetic and real photos."""

from pathlib import Path

import numpy as np
import pytest

from cca_cli.errors import CheckerboardNotFound, InputError
from cca_cli.io.images import read_image
from cca_cli.registration import (
    apply_homography,
    canonical_corner_order,
    checkerboard_corners,
    estimate_homography,
    find_checkerboard,
    render_checkerboard,
    stage_homography,
)

PATTERN = (7, 5)
SQUARE = 22.0
SHAPE = (240, 320)
DATASET = Path(__file__).resolve().parents[2] / ".." / "shared" / "datasets" / "checkerboard-opencv-stereo"
REAL_PATTERN = (9, 6)
PAIRS = ["01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"]


def rms(a, b):
    return float(np.sqrt(np.mean(np.sum((np.asarray(a, float) - b) ** 2, axis=1))))


def board(origin=(83.37, 61.71), matrix=None, **kw):
    img = render_checkerboard(
        SHAPE, PATTERN, square_px=SQUARE, origin_xy=origin, matrix=matrix, blur_px=1.0, supersample=2, **kw
    )
    return img, checkerboard_corners(PATTERN, SQUARE, origin, matrix)


def test_synthetic_corners_subpixel_accurate():
    img, truth = board()
    found = find_checkerboard(img, PATTERN)
    assert found.dtype == np.float32 and found.shape == (35, 2)
    err = np.linalg.norm(found - truth, axis=1)
    assert err.max() < 0.05, err.max()


@pytest.mark.parametrize("rotation", [0.0, 35.0, 100.0, 180.0, -120.0])
def test_order_follows_the_physical_board(rotation):
    # 8x5 inner corners = 9x6 squares: the corner squares at the two ends of
    # the board differ in colour, so the order is fixed by the physical board
    # whatever the view's rotation: row-major from the inner corner next to
    # the dark top-left square.
    pattern, square, origin = (8, 5), 20.0, (70.0, 60.0)
    h = stage_homography((4.0, -3.0), rotation_deg=rotation, center_xy=(160, 120))
    img = render_checkerboard(SHAPE, pattern, square_px=square, origin_xy=origin, matrix=h, blur_px=1.0, supersample=2)
    truth = checkerboard_corners(pattern, square, origin, h)
    jj, ii = np.mgrid[0 : pattern[1], 0 : pattern[0]]
    model = np.stack([origin[0] + (ii + 1) * square, origin[1] + (jj + 1) * square], -1).reshape(-1, 2)
    np.testing.assert_allclose(truth, apply_homography(model, h), atol=1e-9)
    found = find_checkerboard(img, pattern)
    assert rms(found, truth) < 0.05


@pytest.mark.parametrize("rotation", [-20.0, 160.0])
def test_symmetric_board_ordered_by_geometry(rotation):
    # 7x5 inner corners = 8x6 squares looks the same turned by 180 degrees:
    # the order then starts at the top-left-most end of the board.
    h = stage_homography((0.0, 0.0), rotation_deg=rotation, center_xy=(160, 120))
    origin = (72.0, 54.0)
    img, truth = board(origin=origin, matrix=h)
    found = find_checkerboard(img, PATTERN)
    assert rms(found, truth) < 0.05
    assert (found[-1] - found[0]).sum() > 0


@pytest.mark.parametrize("pattern", [(8, 5), (7, 5), (6, 6)])
def test_canonical_order_undoes_any_grid_symmetry(pattern):
    # The detector may list the grid mirrored, rotated or (square boards)
    # transposed; every such listing must come back in the same order.
    cols, rows = pattern
    h = stage_homography((3.0, 2.0), rotation_deg=12.0, perspective=1e-5, center_xy=(160, 120))
    img = render_checkerboard(SHAPE, pattern, square_px=20.0, origin_xy=(70.0, 50.0), matrix=h, supersample=2)
    truth = checkerboard_corners(pattern, 20.0, (70.0, 50.0), h)
    grid = truth.reshape(rows, cols, 2)
    listings = [grid, grid[::-1], grid[:, ::-1], grid[::-1, ::-1]]
    if cols == rows:
        listings += [np.swapaxes(grid, 0, 1), np.swapaxes(grid, 0, 1)[::-1]]
    for listing in listings:
        ordered = canonical_corner_order(listing.reshape(-1, 2), pattern, image=img)
        np.testing.assert_array_equal(ordered, truth)


def test_any_intensity_range_and_dtype():
    img, truth = board()
    hdr = img.astype(np.float64) * 3.7e5 + 1.2e4  # radiance in counts/s
    assert rms(find_checkerboard(hdr, PATTERN), truth) < 0.05
    u16 = np.rint(img * 4000).astype(np.uint16)
    assert rms(find_checkerboard(u16, PATTERN), truth) < 0.06
    u8 = np.rint(img * 250).astype(np.uint8)
    assert rms(find_checkerboard(u8, PATTERN), truth) < 0.08


def test_blank_image_not_found():
    with pytest.raises(CheckerboardNotFound) as err:
        find_checkerboard(np.full(SHAPE, 0.5, np.float32), (9, 6), source="captures/x_1_2.tif")
    msg = str(err.value)
    assert isinstance(err.value, InputError)
    assert "captures/x_1_2.tif" in msg and "9x6" in msg and "\n" not in msg


def test_wrong_pattern_not_found():
    img, _ = board()
    with pytest.raises(CheckerboardNotFound, match="view 3: no 9x6"):
        find_checkerboard(img, (9, 6), source="view 3")


def _real_corners():
    if not DATASET.is_dir():
        pytest.skip(f"shared datasets not present: {DATASET}")
    corners = {}
    for side in ("left", "right"):
        for num in PAIRS:
            path = DATASET / f"{side}{num}.jpg"
            image = read_image(path)
            assert image.pixels.shape == (480, 640) and image.bit_depth == 8
            corners[f"{side}{num}"] = find_checkerboard(image.pixels, REAL_PATTERN, source=str(path))
    return corners


@pytest.fixture(scope="module")
def real_corners():
    return _real_corners()


def test_real_photos_all_found_in_corresponding_order(real_corners):
    assert len(real_corners) == 26
    cols = REAL_PATTERN[0]
    for num in PAIRS:
        left, right = real_corners[f"left{num}"], real_corners[f"right{num}"]
        assert left.shape == (54, 2) and np.isfinite(left).all()
        # The stereo cameras see the board from nearly the same direction:
        # the first row must run the same way in both views (a 180-degree
        # order flip would make this -1).
        u_left, u_right = left[cols - 1] - left[0], right[cols - 1] - right[0]
        cos = np.dot(u_left, u_right) / np.linalg.norm(u_left) / np.linalg.norm(u_right)
        assert cos > 0.9, (num, cos)


def test_real_pair_homography(real_corners):
    fit = estimate_homography(real_corners["right01"], real_corners["left01"], ransac_threshold_px=3.0)
    # Hand-held board, JPEG, uncorrected lens distortion: measured 0.61 px RMS
    # over 54/54 inliers with opencv 5.0.
    assert fit.inliers >= 50
    assert fit.rms_px < 1.0
    assert fit.max_px < 3.0


def test_a_board_without_a_white_margin_is_found_by_the_sector_detector_s_defaults():
    """A 7 x 5 board filling a camera-scan view edge to edge (no white margin around it): the classic detector
    and the sector-based one's exhaustive search miss it, the sector-based one's defaults find it."""
    image = read_image(Path(__file__).parent / "data" / "board_without_margin.png").pixels
    found = find_checkerboard(image, PATTERN)
    ideal = checkerboard_corners(PATTERN, 1.0, (0.0, 0.0))
    assert estimate_homography(ideal, found).rms_px < 0.3
