"""Make data_samples/sample_capture/: a capture set recorded the way the lab camera records one.

The project's simulator images a resolution chart through a 5 x 5 scan of a
4.6 mm aperture (SAR 2.6). Each view is composited into a larger frame next
to a printed 9 x 6 checkerboard (lit incoherently: simply added, blurred by
the lens, not passed through the coherent pupil), the frame is misaligned by
a homography derived from the stage offset (perspective shift), and three
exposures are recorded with shot and read noise, a black level of 64, 12-bit
quantization and saturation at 4095 (16-bit PNG files holding 12-bit codes).
A manifest, the ground truth (truth.npy, intensity on the recovery grid) and
the true homographies (truth_homographies.npy, reference → view) go next to
the images; the pipeline never reads the truth files, tests do.

Run from the repository root::

    python pipelines/make_sample_capture.py [--out data_samples/sample_capture]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

from cca_cli.config.model import RunConfig
from cca_cli.io.images import write_image
from cca_cli.registration.homography import warp_to_reference
from cca_cli.registration.synthetic import render_checkerboard, stage_homography
from cca_cli.stages.simulate import simulate

OPTICS = {"wavelength_m": 550e-9, "focal_length_m": 0.1, "aperture_diameter_m": 4.6e-3, "pixel_pitch_m": 2.5e-6,
          "distance_m": 10.0}
FRAME_HW = (160, 208)
OBJECT_XY = (16, 32)            # top-left of the 96 x 96 object region in the reference frame
PATTERN = (9, 6)
SQUARE_PX = 9.0
BOARD_ORIGIN_XY = (110.0, 48.0)
EXPOSURES_S = (0.002, 0.008, 0.032)
GAIN = 1.0e6                    # counts per second per unit irradiance
BLACK, WHITE = 64, 4095
PARALLAX_PX_PER_MM = 0.6        # image shift per mm of stage travel
BACKGROUND = 0.3


def make(out: Path, *, seed: int = 0) -> dict:
    """Write the sample capture set into ``out`` and return its manifest dict."""
    cfg = RunConfig.model_validate({
        "optics": OPTICS,
        "scene": {"kind": "resolution_chart", "size_px": 96, "field_width_m": 0.024, "widths_px": [6, 5, 4, 3, 2]},
        "array": {"grid": 5, "overlap": 0.6}, "noise": {"model": "none"}})
    sim = simulate(cfg)
    n = sim.intensity.shape[-1]
    h, w = FRAME_HW
    x0, y0 = OBJECT_XY
    board = render_checkerboard(FRAME_HW, PATTERN, square_px=SQUARE_PX, origin_xy=BOARD_ORIGIN_XY, dark=0.04,
                                light=0.8, blur_px=1.0)
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    # The printed board (with a 3 px white margin) on a darker background.
    bx0, by0 = BOARD_ORIGIN_XY
    bw, bh = (PATTERN[0] + 1) * SQUARE_PX, (PATTERN[1] + 1) * SQUARE_PX
    yy, xx = np.mgrid[0:h, 0:w]
    off_board = (xx < bx0 - 3) | (xx > bx0 + bw + 3) | (yy < by0 - 3) | (yy > by0 + bh + 3)
    backdrop = np.where(off_board, np.float32(BACKGROUND), board).astype(np.float32)
    images, homographies = [], []
    for k, (cy, cx) in enumerate(sim.geometry.aperture_centres_yx_m):
        sx_mm, sy_mm = cx * 1e3, cy * 1e3
        # The object appears to move against the camera's travel; a slight tilt grows with the offset.
        matrix = stage_homography((-sx_mm * PARALLAX_PX_PER_MM, -sy_mm * PARALLAX_PX_PER_MM),
                                  perspective=(sx_mm * 4e-6, sy_mm * 4e-6), rotation_deg=0.05 * sx_mm,
                                  center_xy=centre)
        homographies.append(matrix)
        scene = backdrop.copy()
        scene[y0:y0 + n, x0:x0 + n] = sim.intensity[k]
        view = warp_to_reference(scene, matrix, FRAME_HW, interpolation="lanczos")
        view = np.clip(view, 0, None)
        for e, t in enumerate(EXPOSURES_S):
            electrons = rng.poisson(view * GAIN * t).astype(np.float64) + rng.normal(0, 2.0, view.shape)
            codes = np.clip(np.rint(electrons + BLACK), 0, WHITE)
            name = f"view_r{k // 5}c{k % 5}_e{e}.png"
            write_image(out / name, codes, bit_depth=16)
            images.append({"path": name, "exposure_s": t, "stage_x_mm": round(float(sx_mm), 6),
                           "stage_y_mm": round(float(sy_mm), 6)})
    manifest = {
        "optics": OPTICS,
        "sensor": {"black_level": BLACK, "white_level": WHITE},
        "checkerboard": {"pattern": list(PATTERN), "square_m": 2.25e-3},
        "images": images,
    }
    header = ("# Sample capture set made by pipelines/make_sample_capture.py (simulated, not measured):\n"
              "# 5 x 5 stage positions x 3 exposures, 12-bit codes in 16-bit PNG, black level 64.\n")
    (out / "manifest.yaml").write_text(header + yaml.safe_dump(manifest, sort_keys=False))
    np.save(out / "truth.npy", (np.abs(sim.scene.field) ** 2).astype(np.float32))
    np.save(out / "truth_homographies.npy", np.stack(homographies))
    return manifest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("data_samples/sample_capture"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    manifest = make(args.out, seed=args.seed)
    print(f"{args.out}: {len(manifest['images'])} images")


if __name__ == "__main__":
    main()
