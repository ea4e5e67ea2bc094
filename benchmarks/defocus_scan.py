"""How strongly the blood-smear captures pin the defocus: the data residual against a fixed defocus pupil.

For each z, ``engine: momentum`` runs with its recorded-data settings but with the
pupil held at the NA disc times the defocus phase of z (``pupil_recovery: none``,
the geometry's ``defocus_m`` = z), and the residual over all / bright-field /
dark-field images is recorded. A parabola through the three lowest points gives
the best z. Run ``bench_real.py`` first: it writes the ingested files this reads.

Usage::

    python benchmarks/defocus_scan.py                 # both readings, z = -20 ... +30 µm
    python benchmarks/defocus_scan.py --z-um -10,0,10
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

import cca_cli as cca
from cca_cli.engines.calibration import defocus_zernike

RESULTS = Path(__file__).resolve().parent / "results"
READINGS = {"amplitude": "bloodsmear_green_amplitude", "intensity": "bloodsmear_green_intensity"}


def scan(data: cca.CaptureSet, z_um: list[float]) -> list[dict]:
    rows = []
    for z in z_um:
        geometry = dataclasses.replace(data.geometry, defocus_m=z * 1e-6)
        fit = cca.reconstruct(dataclasses.replace(data, geometry=geometry), engine="momentum",
                              pupil_recovery="none").fit
        rows.append({"z_um": z, "all": fit.all, "bright_field": fit.bright_field, "dark_field": fit.dark_field})
        print(f"  z {z:+6.1f} µm: residual {fit.all:.4f} / {fit.bright_field:.4f} / {fit.dark_field:.4f}", flush=True)
    return rows


def best_z(rows: list[dict]) -> float:
    """Vertex of the parabola through the lowest residual (over all images) and its two neighbours."""
    z = np.array([r["z_um"] for r in rows])
    r = np.array([r["all"] for r in rows])
    i = int(np.clip(np.argmin(r), 1, len(r) - 2))
    a, b, _ = np.polyfit(z[i - 1:i + 2], r[i - 1:i + 2], 2)
    return float(-b / (2 * a))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--z-um", default="-20,-10,-5,0,5,10,15,20,30")
    parser.add_argument("--out", default=str(RESULTS / "defocus_scan.json"))
    args = parser.parse_args()
    z_um = [float(v) for v in args.z_um.split(",")]
    out = {"readings": {}}
    for reading, folder in READINGS.items():
        path = RESULTS / "real_work" / folder / "raw.h5"
        if not path.exists():
            raise SystemExit(f"{path} is missing: run python benchmarks/bench_real.py first")
        print(f"{reading} reading ({path})")
        data = cca.load(path)
        rows = scan(data, z_um)
        z = best_z(rows)
        out["readings"][reading] = {"rows": rows, "best_z_um": z}
        print(f"  best z {z:+.1f} µm (parabola through the lowest three)")
    g = data.geometry
    out["waves_rms_per_um"] = float(defocus_zernike(1e-6, wavelength_m=g.wavelength_m,
                                                    numerical_aperture=g.numerical_aperture)[0])
    print(f"+10 µm is {10 * out['waves_rms_per_um']:+.4f} waves RMS of Zernike defocus at NA "
          f"{g.numerical_aperture:g}, {g.wavelength_m * 1e9:.0f} nm")
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
