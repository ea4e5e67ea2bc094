"""The peer benchmark's grid resampling, alignment and target rule (no peers, no simulation)."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import bench_peers as bench  # noqa: E402  (a broken import must fail these tests, not skip them)


def _blob(n: int) -> np.ndarray:
    y, x = np.mgrid[:n, :n] - n // 2
    return (np.exp(-((y - 5) ** 2 + (x + 9) ** 2) / 40.0) + 0.5 * np.exp(-((y + 12) ** 2 + x ** 2) / 15.0)
            ).astype(np.complex64)


def test_to_grid_is_exact_for_band_limited_fields():
    rng = np.random.default_rng(0)
    spectrum = np.zeros((64, 64), np.complex64)
    spectrum[24:40, 24:40] = rng.normal(size=(16, 16)) + 1j * rng.normal(size=(16, 16))
    small = bench.fft.ifft2c(spectrum)
    big = bench.to_grid(small, 128)
    assert big.shape == (128, 128)
    np.testing.assert_allclose(bench.to_grid(big, 64), small, atol=1e-5)
    # same physical field: sample values are preserved up to the orthonormal scale 64/128
    np.testing.assert_allclose(big[::2, ::2] * 2, small, atol=1e-5)


@pytest.mark.parametrize("k", range(8))
def test_alignment_undoes_flips_and_shifts(k):
    reference = _blob(64)
    moved = np.roll(bench._dihedral(reference, k), (7, -3), axis=(0, 1))
    how = bench.alignment(moved, reference)
    np.testing.assert_allclose(np.abs(bench.apply_alignment(moved, how)), np.abs(reference), atol=1e-6)


def test_time_to_target_needs_both_resolution_and_error():
    row = {"curve": [
        {"iteration": 1, "seconds": 0.1, "amplitude_rmse": 0.05, "mtf20_px": 4},
        {"iteration": 2, "seconds": 0.2, "amplitude_rmse": 0.04, "mtf20_px": 2},
        {"iteration": 3, "seconds": 0.3, "amplitude_rmse": 0.01, "mtf20_px": None},
        {"iteration": 4, "seconds": 0.4, "amplitude_rmse": 0.01, "mtf20_px": 2},
    ], "round_seconds": [[0.1, 0.2, 0.3, 0.4], [0.2, 0.4, 0.6, 0.8], [0.1, 0.2, 0.3, 0.5]]}
    bench.time_to_target(row, 0.02)
    assert row["target_iteration"] == 4
    assert row["target_seconds"] == pytest.approx(0.5)  # median over rounds
    bench.time_to_target(row, 0.005)
    assert row["target_iteration"] is None
