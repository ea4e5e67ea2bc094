"""A 3 x 3 camera array whose cameras each have their own aberration: none, one shared or per-camera pupils.

Simulates the lab sample's scene (``pipelines/make_lab_capture.py``) seen by nine cameras at a given overlap,
each through its own random Zernike aberration (defocus, astigmatism and coma, about 0.1 waves RMS), recovers
it with the momentum engine and no, one shared, or per-camera pupils (the default order 4, and order 2),
and prints each recovery's error against the band-limited truth (RMS over the peak, after a least-squares
scale) and the recovered aberrations' error against the truth.

Usage::

    python benchmarks/camera_array_pupils.py
    python benchmarks/camera_array_pupils.py --overlap 0.7 --seeds 1,2,3
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cca_cli as cca  # noqa: E402
from cca_cli.optics import fft  # noqa: E402
from cca_cli.optics.forward import ForwardModel  # noqa: E402
from cca_cli.optics.pupil import circular_pupils  # noqa: E402
from cca_cli.optics.zernike import zernike_phase  # noqa: E402
from cca_cli.sampling.geometry import camera_scan_geometry  # noqa: E402
from cca_cli.sampling.grid import band_layout  # noqa: E402
from pipelines import make_lab_capture as lab  # noqa: E402

SIZE = 128
SETTINGS = {"no pupil": {"pupil_recovery": "none"}, "shared": {"pupil_recovery": "shared"},
            "per camera": {"pupil_recovery": "per_camera"},
            "per camera, order 2": {"pupil_recovery": "per_camera", "pupil_order": 2}}


def relative_error(image: np.ndarray, truth: np.ndarray) -> float:
    """RMS of ``s·image − truth`` over the truth's peak, ``s`` the least-squares scale."""
    image, truth = image.astype(np.float64), truth.astype(np.float64)
    scale = float(np.sum(image * truth) / np.sum(image * image))
    return float(np.sqrt(np.mean((scale * image - truth) ** 2)) / truth.max())


def case(overlap: float, seed: int):
    """Images, geometry, the band-limited truth and the cameras' true coefficients (defocus … coma, waves)."""
    rng = np.random.default_rng(seed)
    field = lab.scene_field(size=256, seed=0)[64:192, 64:192]
    pitch = lab.OPTICS["pixel_pitch_m"] * lab.OPTICS["distance_m"] / lab.OPTICS["focal_length_m"]
    geometry, sensor = camera_scan_geometry(**lab.OPTICS, field_width_m=SIZE * pitch, grid=3, overlap=overlap)
    layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, sensor_size=sensor,
                         hires_size=SIZE)
    truth = rng.normal(0.0, 0.08, (9, 5))
    truth[:, 0] += rng.uniform(-0.15, 0.15, 9)
    disc = circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px)
    pupils = np.stack([disc[k] * np.exp(1j * zernike_phase(layout.box_size, layout.box_centres[k:k + 1],
                                                             layout.pupil_radius_px, truth[k])[0])
                       for k in range(9)]).astype(np.complex64)
    spectrum = fft.fft2c(field).astype(np.complex64)
    images = np.clip(fft.fourier_resample(ForwardModel(layout, pupils).sensor_intensity(spectrum), SIZE), 0, None)
    limit = np.zeros(spectrum.shape, np.float32)   # the synthetic band: every camera's disc
    for (y, x), box in zip(layout.box_origins, disc):
        b = layout.box_size
        limit[y:y + b, x:x + b] = np.maximum(limit[y:y + b, x:x + b], box)
    band_limited = np.abs(fft.ifft2c(spectrum * (limit > 0))) ** 2
    scan = cca.stage_scan(geometry.aperture_centres_yx_m, wavelength_m=lab.OPTICS["wavelength_m"],
                          focal_length_m=lab.OPTICS["focal_length_m"],
                          aperture_diameter_m=lab.OPTICS["aperture_diameter_m"],
                          pixel_pitch_m=lab.OPTICS["pixel_pitch_m"], distance_m=lab.OPTICS["distance_m"],
                          image_pixels=SIZE, camera_index=np.arange(9))
    return images, scan, band_limited, truth


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--overlap", type=float, default=0.65)
    parser.add_argument("--seeds", default="1,2,3")
    args = parser.parse_args()
    rows = {name: [] for name in SETTINGS}
    for seed in (int(s) for s in args.seeds.split(",")):
        images, scan, band_limited, truth = case(args.overlap, seed)
        centre = relative_error(images[4], band_limited)
        print(f"seed {seed}: aberration {np.sqrt(np.mean(truth ** 2)):.3f} waves RMS, centre camera's image "
              f"{centre:.4f}")
        for name, options in SETTINGS.items():
            result = cca.reconstruct(images, scan, engine="momentum", **options)
            error = relative_error(np.abs(result.object) ** 2, band_limited)
            waves = None
            if result.calibration is not None and result.calibration.pupil is not None \
                    and len(result.calibration.pupil.coefficients) == 9:
                found = np.asarray(result.calibration.pupil.coefficients)[:, :3]
                waves = float(np.sqrt(np.mean((found - truth[:, :3]) ** 2)))
            rows[name].append((error, waves, result.iterations))
            aberration = "" if waves is None else f", defocus/astigmatism error {waves:.3f} waves"
            print(f"  {name:22} image {error:.4f}{aberration} ({result.iterations} passes)")
    print("median over seeds:")
    for name, values in rows.items():
        errors = [e for e, _, _ in values]
        print(f"  {name:22} image {np.median(errors):.4f}")


if __name__ == "__main__":
    main()
