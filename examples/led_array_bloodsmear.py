"""Recover a real LED-array capture: Zheng's blood smear (225 green LEDs, 0.1 NA), from NumPy arrays.

The images and illumination angles are read directly (SciPy, csv) and handed to cca as arrays, as a
notebook would; ``cca run configs/bloodsmear_green.yaml`` does the same through the pipeline. The data
(GPL-2.0, Pengming Song and Guoan Zheng) are not part of cca: they are read from
../shared/datasets/fpm-zheng-bloodsmear next to the repository, or from --data.

    python examples/led_array_bloodsmear.py [--data DIR] [--iterations 40] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from scipy.io import loadmat

import cca_cli as cca

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "fpm-zheng-bloodsmear"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="folder holding bloodsmear_green.mat")
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--out", type=Path, default=Path("."), help="folder for the figure and the TIFF")
    args = parser.parse_args()

    # The images: (128, 128, 225) HDR values that the authors' code uses as amplitudes → intensities.
    stack = loadmat(args.data / "bloodsmear_green.mat", variable_names=["imlow_HDR"])["imlow_HDR"]
    intensities = np.moveaxis(stack, -1, 0).astype(np.float32) ** 2
    with open(args.data / "bloodsmear_green_illumination.csv") as handle:
        rows = list(csv.DictReader(handle))
    sines = np.array([[float(r["ky_norm"]), float(r["kx_norm"])] for r in rows])   # [sin θy, sin θx]

    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=intensities.shape[-1])
    print(f"{geometry.n_images} LEDs, SAR {geometry.synthetic_aperture_ratio:.2f}, "
          f"pupil radius {geometry.pupil_radius_px:.1f} spectrum px")

    # boundary="open": recorded frames are a window on a larger scene, so they get a guard band (as ingested files do)
    result = cca.reconstruct(intensities, geometry, engine="altmin", iterations=args.iterations, tol=1e-5,
                             boundary="open")
    print(f"{result.iterations} iterations, residual {result.history['residual'][-1]:.3f}, "
          f"{result.object.shape[-1]} px of {result.pixel_size_m * 1e9:.0f} nm")

    args.out.mkdir(parents=True, exist_ok=True)
    tiff = cca.export(result, args.out / "bloodsmear_amplitude.tif", quantity="amplitude", force=True)
    half = geometry.field_width_m * 1e6 / 2
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), constrained_layout=True)
    panels = ((intensities[geometry.centre_index], "observed (centre LED)", "gray"),
              (result.intensity, "recovered intensity", "gray"),
              (np.angle(result.object), "recovered phase (rad)", "twilight"))
    for ax, (image, title, cmap) in zip(axes, panels):
        shown = ax.imshow(image, cmap=cmap, extent=(-half, half, half, -half), interpolation="nearest")
        ax.set_title(title)
        ax.set_xlabel("x (µm)")
        fig.colorbar(shown, ax=ax, shrink=0.8)
    axes[0].set_ylabel("y (µm)")
    fig.savefig(args.out / "bloodsmear.png", dpi=110)
    print(f"figure: {args.out / 'bloodsmear.png'}; amplitude: {tiff}")


if __name__ == "__main__":
    main()
