"""Acceptance figures of the lab capture path, measured against the simulation's truth.

Generates a lab capture directory (pipelines/make_lab_capture.py: 11 x 11 positions by default, as in the
report that motivated this path) and the same capture with perfectly aligned views, then measures:

* HDR: each view's merged flux against the true flux (median, 99th percentile, worst, darkest view);
* registration: the true registration error over the object region (truth homographies) against the
  error the register stage reports;
* recovery: the documented route (configs/lab_capture.yaml: whole frame, calibration views) against the
  band-limited truth in the object region, next to the same engine on the perfectly registered full frame,
  a rectangle cut around the object, and the old way (a square crop, no guard band);
* region edges: what the content outside a recovered rectangle leaks into it, against the distance from
  the rectangle's edge (two scenes that differ only outside the rectangle).

Run from the repository root (several minutes on 2 cores; the machine may be shared, so timings are noisy
and only the error figures are compared)::

    python benchmarks/lab_capture.py [--grid 11] [--iterations 60] [--engine momentum] [--out benchmarks/results/lab]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "pipelines"))

from make_lab_capture import CHART_BOX, FRAME_HW, OBJECT_CROP, simulate_lab, write_lab  # noqa: E402

from cca_cli.config.load import load_config, parse_config  # noqa: E402
from cca_cli.metrics import rmse  # noqa: E402
from cca_cli.registration.accuracy import rectangle_points  # noqa: E402
from cca_cli.registration.homography import apply_homography  # noqa: E402
from cca_cli.report.summary import on_grid  # noqa: E402
from cca_cli.stages.runner import run_pipeline  # noqa: E402

OBJECT_XYWH = (CHART_BOX[1], CHART_BOX[0], CHART_BOX[3], CHART_BOX[2])


def hdr_figures(hdr_path: Path, truth_flux: np.ndarray, grid: np.ndarray) -> dict:
    """Per-view flux error of the merge against the truth."""
    with h5py.File(hdr_path) as f:
        radiance = f["/measurements/intensity"][()]
        attrs = dict(f["hdr"].attrs)
        gain = f["/hdr/dynamic_range_gain"][()]
    error = np.abs(radiance.sum(axis=(1, 2), dtype=np.float64) / truth_flux - 1)
    n = grid.max(axis=0)
    corners = [i for i, (r, c) in enumerate(grid) if r in (0, n[0]) and c in (0, n[1])]
    darkest = int(np.argmin(truth_flux))
    return {"views": len(error), "flux_error_median": float(np.median(error)),
            "flux_error_p99": float(np.percentile(error, 99)), "flux_error_max": float(error.max()),
            "views_within_3pct": float(np.mean(error <= 0.03)),
            "corner_view_errors": [float(error[i]) for i in corners],
            "darkest_view": {"grid": grid[darkest].tolist(), "flux_error": float(error[darkest]),
                             "flux_vs_brightest": float(truth_flux[darkest] / truth_flux.max())},
            "read_noise": float(attrs["read_noise"]), "electrons_per_count": float(attrs["electrons_per_count"]),
            "noise_source": str(attrs["noise_source"]), "dynamic_range_gain_median": float(np.median(gain))}


def registration_figures(registered: Path, truth_homographies: np.ndarray) -> dict:
    """True registration error over the object region against the reported estimate."""
    with h5py.File(registered) as f:
        estimated = f["/registration/homography"][()]
        reported = f["/registration/object_rms_px"][()]
        corner_rms = f["/registration/rms_px"][()]
    points = rectangle_points(OBJECT_XYWH, 15)
    true = np.array([np.sqrt(np.mean(np.sum((apply_homography(apply_homography(points, t), e) - points) ** 2, axis=1)))
                     for t, e in zip(truth_homographies, estimated)])
    return {"object_error_true_mean_px": float(true.mean()), "object_error_true_max_px": float(true.max()),
            "object_error_reported_mean_px": float(reported.mean()),
            "object_error_reported_max_px": float(reported.max()),
            "corner_rms_mean_px": float(corner_rms.mean())}


def recovery_error(recon: Path, frame_box: tuple[int, int, int, int], truth: np.ndarray) -> float:
    """RMSE (scale-fitted, over the truth's max) of the recovered region against the truth in the object box."""
    with h5py.File(recon) as f:
        recovered = f["/recon/intensity"][()]
    y0, x0, h, w = frame_box
    image = on_grid(recovered, (h, w))
    cy, cx, ch, cw = CHART_BOX
    return float(rmse(image[cy - y0:cy - y0 + ch, cx - x0:cx - x0 + cw], truth[cy:cy + ch, cx:cx + cw]))


def run(manifest: Path, out: Path, stages: list[str], *, engine: str, iterations: int, registration=None,
        padding=None) -> float:
    """The documented route (configs/lab_capture.yaml) on ``manifest`` with the given stages and overrides."""
    config = load_config(ROOT / "configs" / "lab_capture.yaml").model_dump(mode="json")
    config["run"] = {"stages": stages}
    config["ingest"] = {"manifest": str(manifest)}
    config["reconstruct"].update(engine=engine, iterations=iterations, tol=0.0)
    config["report"]["figures"] = False
    config["registration"].update(registration or {})
    if padding is not None:
        config["reconstruct"]["padding"].update(padding)
    start = time.perf_counter()
    run_pipeline(parse_config(config), out, force=True)
    return time.perf_counter() - start


def edge_leak(iterations: int) -> dict:
    """What a recovered window's surroundings leak into it, by depth from its edge (simulated, no noise).

    Two scenes identical inside a window of a 96 px field and different outside it (a portrait, and a
    fingerprint outside the window) are imaged by a 5 x 5 scan; the window is cut out of every capture
    and recovered as a recorded region (open boundary: guard band, crop back), or, for comparison, a
    square window as it is (``padding.mode: off``, periodic). Reported per window: the error of each
    recovery against the band-limited truth, and the RMS difference of the two recoveries (over the
    window's largest value) in bands of one coherent resolution cell of depth from the window's edge.
    """
    from cca_cli.config.model import PaddingSection, ReconstructSection
    from cca_cli.optics import fft
    from cca_cli.optics.forward import ForwardModel
    from cca_cli.report.summary import band_limited_truth
    from cca_cli.sampling.capture import with_field_width
    from cca_cli.sampling.region import resolution_cell_px
    from cca_cli.library.data import CaptureSet
    from cca_cli.workflows.recovery import reconstruct_captures
    from cca_cli.stages.simulate import simulate

    base = {"optics": {"wavelength_m": 550e-9, "focal_length_m": 0.8, "aperture_diameter_m": 45e-3,
                       "pixel_pitch_m": 2e-6, "distance_m": 50.0},
            "scene": {"kind": "natural", "size_px": 96, "field_width_m": 12e-3},
            "array": {"grid": 5, "overlap": 0.61}, "noise": {"model": "none"}}
    sim = simulate(parse_config(base))
    other = simulate(parse_config({**base, "scene": {**base["scene"], "kind": "fingerprint"}}))
    layout = sim.layout
    model = ForwardModel.unaberrated(layout)
    out = {}
    for name, (y0, x0, h, w), mode in (("rectangle_48x72_guard_band", (24, 12, 48, 72), "auto"),
                                       ("square_48x48_guard_band", (24, 24, 48, 48), "auto"),
                                       ("square_48x48_periodic", (24, 24, 48, 48), "off")):
        inside = np.zeros(sim.scene.field.shape, bool)
        inside[y0:y0 + h, x0:x0 + w] = True
        mixed = np.where(inside, sim.scene.field, other.scene.field).astype(np.complex64)
        mixed_images = fft.fourier_resample(model.sensor_intensity(fft.fft2c(mixed)), 96)
        geometry = with_field_width(sim.geometry, sim.geometry.field_width_m * w / 96)
        section = ReconstructSection(iterations=iterations, tol=0.0, padding=PaddingSection(mode=mode))
        recovered, errors = [], []
        for field, images in ((sim.scene.field, sim.intensity), (mixed, mixed_images)):
            captures = CaptureSet(intensity=images[:, y0:y0 + h, x0:x0 + w], geometry=geometry, boundary="open")
            obj = reconstruct_captures(captures, section, source=Path("window")).intensity
            recovered.append(on_grid(obj.astype(np.float32), (h, w)))
            truth = band_limited_truth(field, sim.geometry)[y0:y0 + h, x0:x0 + w]
            errors.append(round(float(rmse(recovered[-1], truth)), 4))
        cell = resolution_cell_px(w, geometry.pupil_radius_px)
        leak = (recovered[0] - recovered[1]) / recovered[0].max()
        depth = np.minimum(np.minimum(np.arange(h), np.arange(h)[::-1])[:, None],
                           np.minimum(np.arange(w), np.arange(w)[::-1])[None, :]) / cell
        bands = [round(float(np.sqrt(np.mean(leak[(depth >= n) & (depth < n + 1)] ** 2))), 4)
                 for n in range(int(depth.max()) + 1)]
        out[name] = {"rmse_vs_band_truth": errors, "leak_rms_by_depth_in_cells": bands,
                     "resolution_cell_px": round(cell, 2)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", type=int, default=11)
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--engine", default="momentum")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "lab")
    args = parser.parse_args()
    out = args.out / f"grid{args.grid}_seed{args.seed}"
    figures: dict = {"grid": args.grid, "engine": args.engine, "iterations": args.iterations}
    lab = simulate_lab(args.grid, seed=args.seed)
    manifest = write_lab(out / "lab", lab)
    aligned = write_lab(out / "aligned", simulate_lab(args.grid, seed=args.seed, misregistered=False), truth=False)
    common = {"engine": args.engine, "iterations": args.iterations}

    seconds = run(manifest, out / "route", ["ingest", "hdr", "register", "reconstruct"], **common)
    figures["hdr"] = hdr_figures(out / "route" / "hdr.h5", lab.truth_flux, lab.grid)
    figures["registration"] = registration_figures(out / "route" / "registered.h5", lab.homographies)
    full = (0, 0) + FRAME_HW
    x0, y0, w, h = OBJECT_CROP
    recovery = {"route_full_frame": recovery_error(out / "route" / "recon.h5", full, lab.truth_band),
                "route_seconds": round(seconds, 1)}
    run(aligned, out / "reference", ["ingest", "hdr", "reconstruct"], **common)
    recovery["reference_aligned_full_frame"] = recovery_error(out / "reference" / "recon.h5", full, lab.truth_band)
    run(manifest, out / "object_rectangle", ["ingest", "hdr", "register", "reconstruct"],
        registration={"crop_xywh": list(OBJECT_CROP), "object_xywh": None}, **common)
    recovery["route_object_rectangle"] = recovery_error(out / "object_rectangle" / "recon.h5", (y0, x0, h, w),
                                                        lab.truth_band)
    side = FRAME_HW[0]
    square = ((FRAME_HW[1] - side) // 2, 0, side, side)
    run(manifest, out / "square_unpadded", ["ingest", "hdr", "register", "reconstruct"],
        registration={"crop_xywh": list(square), "object_xywh": None}, padding={"mode": "off"}, **common)
    recovery["square_crop_without_guard_band"] = recovery_error(out / "square_unpadded" / "recon.h5",
                                                                (0, square[0], side, side), lab.truth_band)
    with h5py.File(out / "route" / "recon.h5") as f:
        observed = f["/observed/centre"][()]
    cy, cx, ch, cw = CHART_BOX
    recovery["observed_centre"] = float(rmse(observed[cy:cy + ch, cx:cx + cw], lab.truth_band[cy:cy + ch, cx:cx + cw]))
    recovery["route_over_reference"] = recovery["route_full_frame"] / recovery["reference_aligned_full_frame"]
    figures["recovery_rmse_vs_band_truth"] = recovery
    figures["edge_leak"] = edge_leak(100)
    text = json.dumps(figures, indent=2)
    (out / "figures.json").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
