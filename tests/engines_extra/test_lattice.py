"""The lattice of pupil centres and the filter that takes its periodic patterns out of a pupil map."""

import numpy as np
import pytest

from cca_cli.engines.lattice import capture_lattice, periodic_filter
from cca_cli.engines.pupil_recovery import PupilRecovery
from cca_cli.optics.pupil import circular_pupils
from cca_cli.sampling.grid import band_layout, square_scan


def _grid(vectors, n=7, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(n) - n // 2, np.arange(n) - n // 2, indexing="ij")
    points = np.stack([i.ravel(), j.ravel()], axis=1) @ np.asarray(vectors, float)
    return points + rng.normal(0, jitter, points.shape)


def test_a_rotated_jittered_grid_is_found_and_random_centres_are_not():
    angle = np.deg2rad(20)
    vectors = 18.0 * np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]])
    found = capture_lattice(_grid(vectors, jitter=0.5))
    assert found is not None
    # the same lattice: each found vector is a whole combination of the given ones, and the cell area agrees
    combination = found @ np.linalg.inv(vectors)
    np.testing.assert_allclose(combination, np.round(combination), atol=0.05)
    assert abs(np.linalg.det(found)) == pytest.approx(18.0 ** 2, rel=0.02)
    rng = np.random.default_rng(3)
    assert all(capture_lattice(rng.uniform(-100, 100, (n, 2))) is None for n in (20, 60, 150))
    assert capture_lattice(np.zeros((3, 2))) is None                     # too few centres
    assert capture_lattice(np.array([[0, 0], [0, 5], [0, 10], [0, 15], [0, 20.0]])) is None   # a line


def test_the_filter_removes_a_lattice_periodic_pattern_and_keeps_a_smooth_one():
    box, spacing = 96, 16.0
    factor = periodic_filter(box, np.array([[spacing, 0], [0, spacing]]))
    assert factor[0, 0] == pytest.approx(1.0) and factor.min() < 1e-3
    y, x = np.mgrid[:box, :box].astype(float)
    pattern = 0.1 * np.cos(2 * np.pi * y / spacing) + 0.05 * np.cos(2 * np.pi * (x + y) / spacing)
    smooth = 0.4 * np.exp(-((y - box / 2) ** 2 + (x - box / 2) ** 2) / (2 * (box / 6) ** 2))   # a smooth bump
    filtered = np.real(np.fft.ifft2(np.fft.fft2(smooth + pattern) * factor))
    left = filtered - smooth
    assert np.abs(left[8:-8, 8:-8]).max() < 0.1 * np.abs(pattern).max()
    kept = np.real(np.fft.ifft2(np.fft.fft2(smooth) * factor))
    assert np.abs(kept - smooth).max() < 0.01 * smooth.max()


def _notch_product(box, vectors, width=0.75):
    """The filter as its definition reads: one Gaussian notch per harmonic within the band, multiplied in."""
    reciprocal = np.linalg.inv(vectors).T * box
    bins = np.fft.fftfreq(box, 1.0 / box)
    factor = np.ones((box, box))
    for n1 in range(-60, 61):
        for n2 in range(-60, 61):
            hy, hx = n1 * reciprocal[0] + n2 * reciprocal[1]
            if (n1, n2) == (0, 0) or abs(hy) > box / 2 + 3 * width or abs(hx) > box / 2 + 3 * width:
                continue
            dy = (bins - hy + box / 2) % box - box / 2
            dx = (bins - hx + box / 2) % box - box / 2
            factor *= 1 - np.exp(-(dy[:, None] ** 2 + dx[None, :] ** 2) / (2 * width * width))
    return factor


@pytest.mark.parametrize("box, vectors", [(96, [[16.0, 0], [0, 16.0]]), (104, [[40.1, 0.3], [0.2, 39.7]]),
                                          (75, [[9.3, 2.1], [-1.7, 8.8]]), (10, [[3.0, 0], [0, 3.1]])])
def test_the_filter_is_the_product_of_a_notch_at_every_harmonic(box, vectors):
    """Rotated, oblique and fine lattices, and a box smaller than a notch's reach: the same factor to rounding,
    and the same factor on every call."""
    vectors = np.array(vectors)
    factor = periodic_filter(box, vectors)
    np.testing.assert_allclose(factor, _notch_product(box, vectors), rtol=1e-9, atol=1e-12)
    assert np.array_equal(factor, periodic_filter(box, vectors))


@pytest.mark.parametrize("lattice", ["free", "filtered"])
def test_a_filtered_map_step_loses_most_of_the_lattice_pattern(lattice):
    """A pupil step on a scan's square lattice: ``filtered`` keeps a quarter of a lattice pattern, ``free`` all of it.

    (The disc's edge spreads the pattern beyond the notches; what a step leaves, the next steps take on.)
    """
    radius = 30.0
    scan = square_scan(5, 2 * radius * (1 - 0.6))
    layout = band_layout(scan.centres_yx_m, radius, sensor_size=160)
    recovery = PupilRecovery(layout, np.zeros(layout.n_images, np.int64), model="full", lattice=lattice)
    b = layout.box_size
    spacing = np.diff(np.unique(np.round(layout.centres_px[:, 0], 6)))[0]
    y = np.mgrid[:b, :b][0].astype(float)
    pattern = 0.2 * np.exp(2j * np.pi * y / spacing)
    disc = circular_pupils(b, np.array([[b / 2 - 0.5, b / 2 - 0.5]]), radius)[0] > 0
    light = np.where(disc, 1.0, 0.0)
    recovery._num[0], recovery._den[0] = (pattern * light * (light + 1e-3))[None], light[None]
    recovery.step(1.0)
    departure = np.where(disc, recovery.maps[0] * recovery._previous.scale - 1, 0)
    kept = abs(np.sum(departure * np.conj(pattern) * disc)) / np.sum(np.abs(pattern) ** 2 * disc)
    if lattice == "free":
        assert kept > 0.95
    else:
        assert kept < 0.35


def test_no_filter_where_the_harmonics_crowd_zero_frequency():
    """Pupils that barely overlap: the notches would damp the smooth aberration too, so there is none."""
    assert periodic_filter(64, np.array([[32.0, 0], [0, 32.0]])) is None
    kept = periodic_filter(64, np.array([[16.0, 0], [0, 16.0]]))
    assert kept is not None and kept[0, 0] >= 0.99
    # a coarse lattice on a large box has a great many harmonics: found out at zero frequency, at once
    import time

    start = time.perf_counter()
    assert periodic_filter(256, np.array([[1024.0, 0], [0, 1024.0]])) is None
    assert time.perf_counter() - start < 2


def test_a_phase_only_map_stays_phase_only_when_filtered():
    radius = 30.0
    scan = square_scan(5, 2 * radius * (1 - 0.6))
    layout = band_layout(scan.centres_yx_m, radius, sensor_size=160)
    recovery = PupilRecovery(layout, np.zeros(layout.n_images, np.int64), model="full", amplitude=False,
                             lattice="filtered")
    b = layout.box_size
    y = np.mgrid[:b, :b][0].astype(float)
    disc = circular_pupils(b, np.array([[b / 2 - 0.5, b / 2 - 0.5]]), radius)[0] > 0
    light = np.where(disc, 1.0, 0.0)
    recovery._num[0] = (0.3 * np.exp(2j * np.pi * y / 17.0) * light)[None]
    recovery._den[0] = light[None]
    recovery.step(1.0)
    np.testing.assert_allclose(np.abs(recovery.maps[0][disc]), np.abs(recovery.maps[0][disc]).mean(), rtol=1e-5)


def test_an_unknown_lattice_choice_is_refused():
    scan = square_scan(3, 8.0)
    layout = band_layout(scan.centres_yx_m, 10.0, sensor_size=64)
    with pytest.raises(ValueError, match="pupil lattice must be free or filtered"):
        PupilRecovery(layout, np.zeros(layout.n_images, np.int64), lattice="periodic")


def test_leds_on_concentric_rings_are_no_lattice():
    # A ring board (1 + 8 + 12 + 16 + 24 + 32 LEDs, rings 9 mm apart, 110 mm from the sample) puts its inner
    # centres near a square grid's points, but not on them: a lattice filter there would notch real pupil detail.
    points = [(0.0, 0.0)]
    for ring, count in enumerate((8, 12, 16, 24, 32), start=1):
        angles = 2 * np.pi * np.arange(count) / count
        points += [(9.0 * ring * np.cos(a), 9.0 * ring * np.sin(a)) for a in angles]
    positions = np.array(points)
    sines = positions / np.sqrt(110.0 ** 2 + np.sum(positions ** 2, axis=1, keepdims=True))
    assert capture_lattice(400.0 * sines) is None
    # a grid bent by the sine of the angle (the same pitch and distance, 15 × 15 LEDs out to 39°) still is one
    i, j = np.meshgrid(np.arange(15) - 7, np.arange(15) - 7, indexing="ij")
    grid = 9.0 * np.stack([i.ravel(), j.ravel()], axis=1)
    bent = 400.0 * grid / np.sqrt(110.0 ** 2 + np.sum(grid ** 2, axis=1, keepdims=True))
    assert capture_lattice(bent) is not None


def test_a_filtered_map_step_is_kept_when_the_next_pass_fits_worse():
    # Without a filter a step followed by a worse pass is undone (and the step halved); with the lattice filter
    # the misfit may rise after a sound step (the filter takes part of it), so the step stays.
    layout = band_layout(square_scan(5, 6.0).centres_yx_m, 8.0, hires_size=96)
    spectrum = np.ones((96, 96), np.complex64)
    fields = np.zeros((layout.n_images, layout.lowres_size, layout.lowres_size), np.complex64)
    discs = circular_pupils(layout.box_size, layout.box_centres, 8.0).astype(np.complex64)
    s = layout.lowres_size // 2 - layout.box_size // 2
    fields[:, s:s + layout.box_size, s:s + layout.box_size] = 0.1 * layout.lowres_size * discs
    kept = {}
    for lattice in ("free", "filtered"):
        recovery = PupilRecovery(layout, np.zeros(layout.n_images, int), lattice=lattice)
        recovery.accumulate(0, slice(0, layout.n_images), spectrum, layout.box_origins, fields, discs)
        recovery.step(misfit=1.0)
        after_first = recovery.maps.copy()
        recovery.step(misfit=2.0)   # the next pass fit worse
        kept[lattice] = (np.array_equal(recovery.maps, after_first), recovery.step_size)
    assert kept["free"] == (False, 0.5)
    assert kept["filtered"] == (True, 1.0)
