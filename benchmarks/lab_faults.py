"""Lab faults, end to end: simulated LED-array captures with one realistic fault each, through ``cca ingest``
and ``cca reconstruct`` with no options, read against the truth.

The captures come from a forward model of its own (numpy only, not cca's): a 9 × 9 LED board under a
0.1 NA objective, a 1024² object at a quarter of the object pixel (0.25 µm), each capture's field cut from
the tilted object's spectrum, 128² frames written as 16-bit TIFFs (whole counts, the brightest bright-field
pixel at 30 000) over a black level of 100 counts. Two
objects: sparse phase cells and a USAF-like chart. Faults, one per set (the table's names):

- ``base``: none; ``defocus20``, ``defocus30``: the object 20 or 30 µm out of focus, not told;
  ``defocus30_known``: 30 µm, given as ``illumination.defocus_m``;
- ``stray02``, ``stray05``, ``stray2``: light the object did not scatter, 0.2%, 0.5% and 2% of the
  bright-field mean, a gradient across the frame;
- ``hot_deadcolumn``: eight hot pixels and a dead column;
- ``distance10``: the LED distance in the manifest 10% short;
- ``drift``: the object drifts 2.5 px over the run;
- ``jitter``: LEDs ±20% in brightness and falling off as cos⁴.

The reading: the truth band-limited to the union of the pupils, resampled exactly to the recovery's grid,
aligned to it (sub-pixel), and the amplitude's correlation with the truth, plain and high-passed (the
object's detail), over the interior.

Usage::

    python benchmarks/lab_faults.py                        # every set, both objects (about 5 minutes)
    python benchmarks/lab_faults.py --objects cells --faults base,stray02
    python benchmarks/lab_faults.py --json lab_faults.json --keep work/
    python benchmarks/lab_faults.py --faults stray02,stray05 --options '{background: false}'   # light left in
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

import cca_cli as cca
from cca_cli.io.images import write_image

FAULTS = {
    "base": {},
    "defocus20": {"defocus_um": 20.0},
    "defocus30": {"defocus_um": 30.0},
    "defocus30_known": {"defocus_um": 30.0, "tell_defocus": True},
    "stray02": {"stray": 0.002},
    "stray05": {"stray": 0.005},
    "stray2": {"stray": 0.02},
    "hot_deadcolumn": {"hot": 8, "dead_column": True},
    "distance10": {"manifest_distance": 0.9},
    "drift": {"drift_px": 2.5},
    "jitter": {"jitter": 0.2, "cos4": True},
}

UP, NB, NF = 4, 1024, 128        # object samples per frame pixel, object grid, frame
GRID, NA, WAVELENGTH, PITCH, DISTANCE, CAMERA_PX, MAGNIFICATION = 9, 0.1, 530e-9, 4e-3, 70e-3, 5e-6, 5.0
BLACK = 100.0


def make_object(kind: str, rng: np.random.Generator, dx: float) -> np.ndarray:
    """Phase cells or a USAF-like chart (with smooth phase) on the NB² grid, lightly anti-aliased."""
    yy, xx = (np.mgrid[0:NB, 0:NB] - NB / 2) * dx
    amp, phase = np.ones((NB, NB)), np.zeros((NB, NB))
    if kind == "cells":
        for _ in range(140):
            cx, cy = rng.uniform(-NB * dx / 2, NB * dx / 2, 2)
            r, e = rng.uniform(2.5e-6, 7e-6), rng.uniform(0.7, 1.3)
            d2 = ((xx - cx) / r) ** 2 + ((yy - cy) / (r * e)) ** 2
            inside = d2 < 1
            phase[inside] += rng.uniform(0.8, 1.6) * np.sqrt(1 - d2[inside])
            amp[inside] *= rng.uniform(0.85, 0.97)
            nucleus = ((xx - cx - 0.2 * r) / (0.35 * r)) ** 2 + ((yy - cy) / (0.35 * r)) ** 2 < 1
            amp[nucleus] *= 0.8
        phase = np.minimum(phase, 2.0)
    else:
        periods = [1.4, 1.6, 1.8, 2.0, 2.3, 2.6, 3.0, 3.5, 4.0, 5.0, 6.0, 8.0]
        cell = 32e-6
        n = int(NB * dx / cell)
        for i in range(n):
            for j in range(n):
                period = periods[(i * 3 + j * 5) % len(periods)] * 1e-6
                x0, y0 = -NB * dx / 2 + j * cell + 3e-6, -NB * dx / 2 + i * cell + 3e-6
                length = min(5 * period, cell - 6e-6)
                for b in range(3):
                    amp[(xx >= x0 + b * period) & (xx < x0 + b * period + period / 2) & (yy >= y0)
                        & (yy < y0 + length / 2 - 1e-6)] = 0.3
                    amp[(yy >= y0 + length / 2 + b * period) & (yy < y0 + length / 2 + b * period + period / 2)
                        & (xx >= x0) & (xx < x0 + length)] = 0.3
        for _ in range(6):
            cx, cy = rng.uniform(-100e-6, 100e-6, 2)
            s = rng.uniform(15e-6, 40e-6)
            phase += rng.uniform(-1, 1) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * s ** 2))
        phase = 1.5 * phase / np.abs(phase).max()
    f = np.fft.fftfreq(NB)
    blur = np.exp(-2 * (np.pi * 0.6) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
    return np.fft.ifft2(np.fft.fft2(amp * np.exp(1j * phase)) * blur)


def simulate(folder: Path, kind: str, fault: dict, seed: int = 1) -> dict:
    """Write the TIFFs, ``leds.csv`` and ``lab.yaml`` of one set; return the truth and the geometry."""
    rng = np.random.default_rng(seed)
    dx_lo = CAMERA_PX / MAGNIFICATION
    dx = dx_lo / UP
    obj = make_object(kind, rng, dx)
    rows, cols = (v.ravel() for v in np.mgrid[0:GRID, 0:GRID])
    lx, ly = (cols - (GRID - 1) / 2) * PITCH, (rows - (GRID - 1) / 2) * PITCH
    r = np.sqrt(lx ** 2 + ly ** 2 + DISTANCE ** 2)
    sx, sy = lx / r, ly / r
    k = len(rows)
    nlo = NB // UP
    flo = (np.arange(nlo) - nlo // 2) / (NB * dx)
    fy, fx = np.meshgrid(flo, flo, indexing="ij")
    pupil = (fx ** 2 + fy ** 2 < (NA / WAVELENGTH) ** 2).astype(complex)
    if fault.get("defocus_um"):
        kz = np.sqrt(np.maximum(1 / WAVELENGTH ** 2 - fx ** 2 - fy ** 2, 0))
        pupil = pupil * np.exp(2j * np.pi * fault["defocus_um"] * 1e-6 * kz)
    brightness = np.ones(k)
    if fault.get("jitter"):
        brightness *= 1 + rng.uniform(-fault["jitter"], fault["jitter"], k)
    if fault.get("cos4"):
        brightness *= (DISTANCE / r) ** 4
    yy, xx = (np.mgrid[0:NB, 0:NB] - NB / 2) * dx
    freq = np.fft.fftfreq(NB, dx)
    images = np.empty((k, NF, NF))
    for i in range(k):
        moved = obj
        if fault.get("drift_px"):
            t = fault["drift_px"] * dx_lo * i / (k - 1)
            moved = np.fft.ifft2(np.fft.fft2(obj) * np.exp(-2j * np.pi * (freq[None, :] * 0.8 * t
                                                                           + freq[:, None] * 0.6 * t)))
        spectrum = np.fft.fftshift(np.fft.fft2(moved * np.exp(2j * np.pi * (sx[i] * xx + sy[i] * yy) / WAVELENGTH)))
        c = NB // 2
        box = spectrum[c - nlo // 2:c + nlo // 2, c - nlo // 2:c + nlo // 2]
        low = np.abs(np.fft.ifft2(np.fft.ifftshift(box * pupil)) / UP ** 2) ** 2
        images[i] = brightness[i] * low[nlo // 2 - NF // 2:nlo // 2 + NF // 2, nlo // 2 - NF // 2:nlo // 2 + NF // 2]
    bright = np.hypot(sx, sy) < NA
    counts = images * (30000.0 / images[k // 2].max())
    if fault.get("stray"):
        yv, xv = np.mgrid[0:NF, 0:NF] / NF
        counts += fault["stray"] * counts[bright].mean() * (0.5 + 0.6 * xv + 0.4 * yv)[None]
    raw = counts + BLACK   # (rounded to whole counts below)
    for _ in range(fault.get("hot", 0)):
        y, x = rng.integers(0, NF, 2)
        raw[:, y, x] += rng.uniform(2000, 20000)
    if fault.get("dead_column"):
        raw[:, :, 77] = BLACK + rng.normal(0, 2, (k, NF))
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["path,row,col,exposure_ms"]
    for i in range(k):
        write_image(folder / f"img_{i:03d}.tif", np.clip(np.round(raw[i]), 0, 65535), bit_depth=16)
        lines.append(f"img_{i:03d}.tif,{rows[i]},{cols[i]},20")
    (folder / "leds.csv").write_text("\n".join(lines) + "\n")
    defocus = f"\n  defocus_m: {fault['defocus_um'] * 1e-6}" if fault.get("tell_defocus") else ""
    (folder / "lab.yaml").write_text(
        f"illumination:\n  wavelength_m: {WAVELENGTH}\n  numerical_aperture: {NA}\n  pixel_pitch_m: {CAMERA_PX}\n"
        f"  magnification: {MAGNIFICATION}\n  led_pitch_m: {PITCH}\n"
        f"  led_distance_m: {DISTANCE * fault.get('manifest_distance', 1.0)}{defocus}\n"
        f"sensor: {{black_level: {BLACK:g}}}\nimages_csv: leds.csv\nunits: {{exposure: ms}}\n")
    half = NF * UP // 2
    return {"truth": obj[NB // 2 - half:NB // 2 + half, NB // 2 - half:NB // 2 + half], "dx": dx,
            "sines": np.stack([sx, sy], 1)}


def read_against_truth(recon: Path, truth: dict, margin: int = 14) -> dict:
    """Amplitude correlation with the band-limited truth after sub-pixel alignment, plain and high-passed."""
    result = cca.load(recon)
    recovered = np.asarray(result.amplitude) * np.exp(1j * np.asarray(result.phase))
    field, dx = truth["truth"], truth["dx"]
    n = field.shape[0]
    spectrum = np.fft.fftshift(np.fft.fft2(field))
    freq = (np.arange(n) - n // 2) / (n * dx)
    fx, fy = np.meshgrid(freq, freq)
    band = np.zeros((n, n), bool)
    for sx, sy in truth["sines"]:
        band |= (fx + sx / WAVELENGTH) ** 2 + (fy + sy / WAVELENGTH) ** 2 < (NA / WAVELENGTH) ** 2
    m = recovered.shape[0]
    pixel = CAMERA_PX / MAGNIFICATION * NF / m   # the recovery's object pixel, from the true optics
    positions = (np.arange(m) - m / 2) * pixel + n / 2 * dx
    kernel = np.exp(2j * np.pi * positions[:, None] * freq[None, :]) / n
    reference = np.abs(kernel @ (spectrum * band) @ kernel.T)
    amplitude = np.abs(recovered)

    def high(z):
        return z - gaussian_filter(z, 3.0)

    a, b = np.fft.fft2(high(reference)), np.fft.fft2(high(amplitude))
    correlation = np.real(np.fft.ifft2(a * np.conj(b)))
    peak = np.unravel_index(np.argmax(correlation), a.shape)
    shift = []
    for axis, p in enumerate(peak):   # the peak to a fraction of a pixel, by a parabola through three samples
        index = list(peak)
        values = []
        for d in (-1, 0, 1):
            index[axis] = (p + d) % m
            values.append(correlation[tuple(index)])
        curve = values[0] - 2 * values[1] + values[2]
        offset = 0.5 * (values[0] - values[2]) / curve if curve < 0 else 0.0
        shift.append((p + offset + m / 2) % m - m / 2)
    k = np.fft.fftfreq(m)
    ramp = np.exp(-2j * np.pi * (k[:, None] * shift[0] + k[None, :] * shift[1]))
    aligned = np.abs(np.fft.ifft2(np.fft.fft2(recovered) * ramp))
    inner = (slice(margin, m - margin),) * 2
    x, y = reference[inner], aligned[inner]

    def corr(u, v):
        u, v = u - u.mean(), v - v.mean()
        return float((u * v).sum() / np.sqrt((u * u).sum() * (v * v).sum()))

    return {"amplitude": corr(x, y), "detail": corr(high(x), high(y)), "passes": int(result.iterations)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", default="cells,usaf")
    parser.add_argument("--faults", default=",".join(FAULTS))
    parser.add_argument("--json", type=Path)
    parser.add_argument("--keep", type=Path, help="keep the captures and recoveries here")
    parser.add_argument("--options", default="", help="reconstruct options, YAML, e.g. '{background: false}'")
    args = parser.parse_args(argv)
    if args.keep is None:
        with tempfile.TemporaryDirectory(prefix="cca-lab-faults-") as folder:
            return run(args, Path(folder))
    return run(args, args.keep)


def run(args, work: Path) -> int:
    """Every set of ``args``: simulate in ``work``, ingest, reconstruct, read; print the table."""
    rows = []
    print(f"{'object':7s} {'fault':16s} {'amplitude':>9s} {'detail':>7s} {'passes':>6s}")
    for kind in args.objects.split(","):
        for name in args.faults.split(","):
            folder = work / f"{kind}_{name}"
            truth = simulate(folder, kind, FAULTS[name])
            config = []
            if args.options:
                (folder / "options.yaml").write_text(f"reconstruct: {{options: {args.options}}}\n")
                config = ["--config", "options.yaml"]
            for command in (["ingest", "lab.yaml", "-o", "raw.h5", "--force"],
                            ["reconstruct", "raw.h5", "-o", "recon.h5", "--force", *config]):
                subprocess.run([sys.executable, "-m", "cca_cli", *command, "-q"], cwd=folder, check=True)
            read = read_against_truth(folder / "recon.h5", truth)
            rows.append({"object": kind, "fault": name, **read})
            print(f"{kind:7s} {name:16s} {read['amplitude']:9.3f} {read['detail']:7.3f} {read['passes']:6d}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
