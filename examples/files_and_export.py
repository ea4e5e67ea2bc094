"""Move between Python and the command line: save captures for `cca reconstruct`, load its recon.h5, export.

    python examples/files_and_export.py [--out DIR]

Writes DIR/captures.h5 (a small simulated capture set), recovers it in Python, saves DIR/recon.h5 (the
file `cca report` and `cca export` read) and exports the recovered amplitude as a float32 TIFF and a
16-bit PNG carrying the object pixel size.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cca_cli as cca


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("cca-example"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    geometry = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3,
                               pixel_pitch_m=2e-6, distance_m=50.0, field_width_m=12e-3, grid=5, overlap=0.61)
    chart = cca.resolution_chart(96, widths=(6, 4, 3, 2, 1))
    captures = cca.CaptureSet(cca.simulate(chart.image, geometry, snr_db=30), geometry)
    cca.save(captures, args.out / "captures.h5", force=True)          # `cca reconstruct` reads this file

    result = cca.reconstruct(cca.load(args.out / "captures.h5"), engine="momentum", iterations=20)
    cca.save(result, args.out / "recon.h5", force=True)               # `cca report` / `cca export` read this
    again = cca.load(args.out / "recon.h5")
    print(f"recon.h5: {again.engine}, {again.iterations} iterations, MTF20 {cca.mtf20(again.intensity, chart)} px")

    for name in ("amplitude.tif", "amplitude.png"):
        path = cca.export(again, args.out / name, quantity="amplitude", force=True)
        print(f"{path}: {again.object.shape[-1]} px of {again.pixel_size_m * 1e6:.0f} µm")


if __name__ == "__main__":
    main()
