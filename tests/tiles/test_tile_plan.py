"""Tile plans: coverage, overlaps, a blend whose weights sum to 1, the walk from the centre, local LED angles."""

import numpy as np
import pytest

from cca_cli.sampling.tiles import axis_starts, local_illumination, plan_tiles, tile_order


@pytest.mark.parametrize("length,size,overlap", [(256, 128, 32), (500, 256, 32), (1000, 256, 40), (300, 256, 32),
                                                 (2048, 256, 32), (130, 64, 0)])
def test_tiles_cover_the_axis_with_at_least_the_overlap(length, size, overlap):
    starts = axis_starts(length, size, overlap)
    assert starts[0] == 0 and starts[-1] + size == length
    steps = np.diff(starts)
    assert np.all(size - steps >= overlap)           # neighbours overlap by at least the overlap
    assert len(starts) == 1 or len(starts) == max(2, int(np.ceil((length - overlap) / (size - overlap))))


@pytest.mark.parametrize("shape,size,overlap,q", [((256, 256), 128, 32, 1), ((300, 520), 128, 40, 2),
                                                  ((500, 500), 256, 32, 1), ((96, 200), 64, 16, 3)])
def test_blend_weights_sum_to_one_everywhere(shape, size, overlap, q):
    plan = plan_tiles(shape, size, overlap)
    total = np.zeros((shape[0] * q, shape[1] * q))
    for tile in plan.tiles:
        total[tile.y0 * q:(tile.y0 + size) * q, tile.x0 * q:(tile.x0 + size) * q] += plan.weight(tile, q)
    np.testing.assert_allclose(total, 1.0, atol=1e-6)


def test_blend_leaves_out_the_outer_quarter_of_each_overlap():
    plan = plan_tiles((256, 256), 128, 32)
    first = plan.tiles[0]
    weight = plan.weight(first)
    overlap = 128 - plan.col_starts[1]                  # this tile's overlap with its right neighbour
    assert np.all(weight[0, -overlap // 4:] == 0)        # never used next to its edge
    assert np.all(weight[0, :plan.col_starts[1]] == 1)   # alone before the overlap


def test_bad_plans_are_refused_with_the_fix():
    with pytest.raises(ValueError, match="below 32 px"):
        plan_tiles((256, 256), 64, 32)
    with pytest.raises(ValueError, match="at most 200 px"):
        plan_tiles((200, 300), 256, 32)


def test_tiles_run_from_the_centre_and_start_from_a_neighbour():
    plan = plan_tiles((1000, 1000), 256, 32)
    order = tile_order(plan)
    assert len(order) == len(plan) == 25
    first, parent = order[0]
    assert parent is None and (first.row, first.col) == (2, 2)
    seen = set()
    for tile, parent in order:
        if parent is not None:
            assert parent.index in seen                                  # the neighbour is already scheduled
            assert abs(parent.row - tile.row) + abs(parent.col - tile.col) == 1
        seen.add(tile.index)
    assert seen == {t.index for t in plan.tiles}


def test_local_illumination_follows_the_leds_from_an_offset_point():
    distance = 0.09
    leds = np.array([[0.0, 0.0], [0.004, 0.0], [0.0, -0.008]])       # LED positions (m) in the LED plane
    sines = leds / np.sqrt(np.sum(leds ** 2, axis=1, keepdims=True) + distance ** 2)
    np.testing.assert_allclose(local_illumination(sines, (0.0, 0.0), distance), sines, atol=1e-12)
    offset = np.array([0.001, -0.002])
    expected = (leds - offset) / np.sqrt(np.sum((leds - offset) ** 2, axis=1, keepdims=True) + distance ** 2)
    np.testing.assert_allclose(local_illumination(sines, offset, distance), expected, atol=1e-12)
    with pytest.raises(ValueError, match="positive"):
        local_illumination(sines, offset, float("nan"))
