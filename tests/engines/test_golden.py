"""Golden outputs: every engine, on one fixed small problem, gives what it gave when the file was written.

A change to an engine's arithmetic shows here first. Values agree to float32
rounding (FFT backends and kernels round differently: the fallbacks differ by
about 1e-6 of the peak here), not bit for bit.

After an intended change, rewrite the file and say why in the commit:
``python tests/engines/test_golden.py --write``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import cca_cli as cca

GOLDEN = Path(__file__).with_name("golden.npz")
ITERATIONS = 10
CASES = {
    "altmin": dict(engine="altmin"),
    "momentum": dict(engine="momentum"),
    "momentum_pupil": dict(engine="momentum", pupil_recovery="shared", pupil_model="full", batch=4),
}


def _problem():
    geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                               distance_m=50, field_width_m=8e-3, grid=5, overlap=0.61)
    chart = cca.resolution_chart(64, widths=(4, 3, 2, 1))
    return geometry, cca.simulate(chart.image, geometry, snr_db=35, seed=3)


def _run(name: str) -> tuple[np.ndarray, np.ndarray]:
    geometry, images = _problem()
    options = dict(CASES[name])
    engine = options.pop("engine")
    result = cca.reconstruct(images, geometry, engine=engine, iterations=ITERATIONS, tol=0, threads=1, **options)
    return result.history["residual"], result.intensity


@pytest.fixture(scope="module")
def golden():
    with np.load(GOLDEN) as data:
        return {key: data[key] for key in data.files}


@pytest.mark.parametrize("name", list(CASES))
def test_engine_output_matches_the_golden_file(golden, name):
    residual, intensity = _run(name)
    expected_residual, expected_intensity = golden[f"{name}/residual"], golden[f"{name}/intensity"]
    np.testing.assert_allclose(residual, expected_residual, rtol=2e-5)
    np.testing.assert_allclose(intensity, expected_intensity, atol=2e-5 * float(expected_intensity.max()))


def _write() -> None:
    out = {}
    for name in CASES:
        residual, intensity = _run(name)
        out[f"{name}/residual"], out[f"{name}/intensity"] = residual, intensity.astype(np.float32)
    np.savez_compressed(GOLDEN, **out)
    print(f"wrote {GOLDEN}")


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/engines/test_golden.py --write")
    _write()
