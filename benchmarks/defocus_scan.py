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


def scan(path: Path, z_um: list[float]) -> list[dict]:
    data = cca.load(path)
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
    waves_per_um = float(defocus_zernike(1e-6, wavelength_m=532e-9, numerical_aperture=0.1)[0])
    out = {"waves_rms_per_um": waves_per_um, "readings": {}}
    for reading, folder in READINGS.items():
        path = RESULTS / "real_work" / folder / "raw.h5"
        if not path.exists():
            raise SystemExit(f"{path} is missing: run python benchmarks/bench_real.py first")
        print(f"{reading} reading ({path})")
        rows = scan(path, z_um)
        out["readings"][reading] = {"rows": rows, "best_z_um": best_z(rows)}
        print(f"  best z {best_z(rows):+.1f} µm (parabola through the lowest three)")
    print(f"+10 µm is {10 * waves_per_um:+.4f} waves RMS of Zernike defocus at NA 0.1, 532 nm")
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
