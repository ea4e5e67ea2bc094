"""Make data_samples/lab_capture/: a capture directory laid out the way a lab records one.

One camera on an X–Y stage scans a grid of positions at 65% overlap and
records three exposures (1, 4, 16 ms) of a coherently lit object at each;
the registration board is photographed separately at every position under
incoherent light (``calib/``). The frames are 12-bit codes stored in 16-bit
TIFFs shifted left by 4 (MSB-aligned), with a per-pixel black level (mean
64 codes, fixed pattern and dark current), 1% pixel gain non-uniformity,
shot noise (1.5 electrons per code), 2 codes of read noise and clipping;
dark frames (``dark/``, 4 per exposure) and flat frames (``flat/``) come
with them. Every view is misregistered by its own homography (shift,
rotation, scale, perspective). The lab's table ``manifest.csv`` has its own
column names (``file, kind, exposure_ms, stage_x_mm, stage_y_mm, grid_row,
grid_col, bits`` and two columns cca does not use), the optics are in
``setup.json``, and ``lab.yaml`` is the manifest a user writes to name
them: nothing of the lab's is edited, renamed or pasted.

The object is a bar chart region in a textured scene that continues past
the frame. Truth files for tests only (the pipeline never reads them):
``truth_intensity.npy`` and ``truth_band.npy`` (the reference frame's
intensity and its band-limited version: the object seen through every
aperture position together), ``truth_homographies.npy`` (reference →
view) and ``truth_flux.npy`` (each view's true radiance summed over the
frame, counts/s).

Run from the repository root::

    python pipelines/make_lab_capture.py [--out data_samples/lab_capture] [--grid 7] [--seed 0]
"""

from __future__ import annotations

import argparse
import csv
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cca_cli.io.images import write_image
from cca_cli.optics import fft
from cca_cli.optics.forward import ForwardModel
from cca_cli.optics.pupil import circular_pupils
from cca_cli.registration.homography import warp_to_reference
from cca_cli.registration.synthetic import render_checkerboard, stage_homography
from cca_cli.sampling.geometry import camera_scan_geometry
from cca_cli.sampling.grid import band_layout
from cca_cli.targets.charts import resolution_chart
from cca_cli.targets.natural import pink_noise

OPTICS = {"wavelength_m": 550e-9, "focal_length_m": 0.05, "aperture_diameter_m": 1.5e-3, "pixel_pitch_m": 2.5e-6,
          "distance_m": 5.0}
FRAME_HW = (112, 160)
SIM_SIZE = 256                      # periodic simulation grid (sensor px); the frame is a window in it
OVERLAP = 0.65
EXPOSURES_MS = (1.0, 4.0, 16.0)
CAL_EXPOSURE_MS = 8.0
FLAT_EXPOSURE_MS = 4.0
DARKS_PER_EXPOSURE = 4
FLATS = 4
GAIN = 2.5e6                        # codes per second per unit irradiance (before pixel gain)
ELECTRONS_PER_CODE = 1.5
READ_NOISE = 2.0                    # codes RMS
BLACK, BLACK_PATTERN, DARK_CURRENT = 64.0, 1.5, 20.0   # codes; codes RMS; codes/s
PRNU = 0.01
BITS, SHIFT = 12, 4
PATTERN, SQUARE_PX, BOARD_ORIGIN = (11, 7), 11.0, (14.0, 12.0)
CHART_BOX = (30, 30, 52, 100)       # y0, x0, h, w of the bar charts in the reference frame
OBJECT_CROP = (26, 24, 108, 64)     # x0, y0, w, h: the object region a user gives register (inside the board)


@dataclass(frozen=True)
class LabCapture:
    """A simulated lab capture in memory (codes as the camera stores them, plus truth)."""

    coherent: np.ndarray        # (K, E, H, W) uint16 stored values
    calibration: np.ndarray     # (K, H, W) uint16
    darks: np.ndarray           # (E, n, H, W) uint16
    flats: np.ndarray           # (n, H, W) uint16
    positions_mm: np.ndarray    # (K, 2) stage [y, x]
    grid: np.ndarray            # (K, 2) row, col
    homographies: np.ndarray    # (K, 3, 3) reference → view
    truth_intensity: np.ndarray  # (H, W) object intensity on the reference frame
    truth_band: np.ndarray      # (H, W) band-limited truth intensity
    truth_flux: np.ndarray      # (K,) counts/s summed over the frame


def scene_field(size: int = SIM_SIZE, seed: int = 0) -> np.ndarray:
    """Amplitude of the scene on the periodic simulation grid: bar charts in a textured surround."""
    texture = pink_noise(size, exponent=1.2, seed=seed + 11)
    amplitude = 0.18 + 0.22 * texture
    oy, ox = (size - FRAME_HW[0]) // 2, (size - FRAME_HW[1]) // 2
    y0, x0, h, w = CHART_BOX
    left = resolution_chart(48, widths=(3, 2, 1), bars=3).image
    right = resolution_chart(52, widths=(4, 2, 1), bars=3).image
    chart = np.zeros((h, w), np.float32)
    chart[2:50, :48] = left
    chart[:, 48:] = right
    amplitude[oy + y0:oy + y0 + h, ox + x0:ox + x0 + w] = 0.05 + 0.9 * chart
    return amplitude.astype(np.complex64)


def _views(field: np.ndarray, grid: int):
    """Coherent intensities of every position on the simulation grid, the geometry and the band truth."""
    pitch_object = OPTICS["pixel_pitch_m"] * OPTICS["distance_m"] / OPTICS["focal_length_m"]
    geometry, sensor = camera_scan_geometry(**OPTICS, field_width_m=SIM_SIZE * pitch_object, grid=grid,
                                            overlap=OVERLAP)
    layout = band_layout(geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, sensor_size=sensor,
                         hires_size=SIM_SIZE)
    model = ForwardModel(layout, circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px))
    spectrum = fft.fft2c(field).astype(np.complex64)
    band = model.sensor_intensity(spectrum)
    intensity = np.clip(fft.fourier_resample(band, SIM_SIZE), 0, None)
    coverage = model.normal_diagonal() > 0
    band_truth = np.abs(fft.ifft2c(spectrum * coverage)) ** 2
    return geometry, intensity, band_truth.astype(np.float32)


def _frame(image: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """The frame window of a simulation-grid image seen through ``matrix`` (frame coordinates)."""
    oy, ox = (SIM_SIZE - FRAME_HW[0]) // 2, (SIM_SIZE - FRAME_HW[1]) // 2
    to_sim = np.array([[1, 0, ox], [0, 1, oy], [0, 0, 1]], np.float64)
    warped = warp_to_reference(image, to_sim @ matrix @ np.linalg.inv(to_sim), image.shape, interpolation="lanczos")
    return warped[oy:oy + FRAME_HW[0], ox:ox + FRAME_HW[1]]


def _misregistration(rng: np.random.Generator, stage_mm: np.ndarray) -> np.ndarray:
    h, w = FRAME_HW
    shift = rng.normal(0, 2.0, 2) - 0.8 * stage_mm[::-1]
    return stage_homography(shift, perspective=rng.normal(0, 1.5e-5, 2), rotation_deg=rng.normal(0, 0.3),
                            center_xy=((w - 1) / 2 + rng.normal(0, 20), (h - 1) / 2 + rng.normal(0, 20))) @ \
        np.diag([1 + rng.normal(0, 0.002), 1 + rng.normal(0, 0.002), 1.0])


class _Sensor:
    """The camera's fixed pattern and noise."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.black = BLACK + rng.normal(0, BLACK_PATTERN, FRAME_HW)
        self.gain = 1 + rng.normal(0, PRNU, FRAME_HW)

    def record(self, radiance: np.ndarray, exposure_s: float) -> np.ndarray:
        """Stored uint16 values of one exposure of ``radiance`` (codes/s at unit pixel gain)."""
        electrons = self.rng.poisson(np.clip(radiance, 0, None) * self.gain * exposure_s * ELECTRONS_PER_CODE)
        codes = (electrons / ELECTRONS_PER_CODE + self.black + DARK_CURRENT * exposure_s
                 + self.rng.normal(0, READ_NOISE, FRAME_HW))
        codes = np.clip(np.rint(codes), 0, 2**BITS - 1).astype(np.uint16)
        return codes << SHIFT


def simulate_lab(grid: int = 7, *, seed: int = 0, misregistered: bool = True, boards: bool = True) -> LabCapture:
    """Simulate a lab capture (see the module docstring).

    ``misregistered=False`` gives perfectly aligned views (the same scene, sensor and noise streams);
    ``boards=False`` leaves the calibration views blank (faster, for references that are not registered).
    """
    rng = np.random.default_rng(seed)
    field = scene_field(seed=seed)
    geometry, intensity, band = _views(field, grid)
    oy, ox = (SIM_SIZE - FRAME_HW[0]) // 2, (SIM_SIZE - FRAME_HW[1]) // 2
    window = (slice(oy, oy + FRAME_HW[0]), slice(ox, ox + FRAME_HW[1]))
    sensor = _Sensor(np.random.default_rng(seed + 1))
    streams = {name: np.random.default_rng([seed, i]) for i, name in enumerate(("coherent", "boards", "darks"))}
    positions_mm = geometry.aperture_centres_yx_m * 1e3
    k = len(positions_mm)
    centre = geometry.centre_index
    coherent = np.empty((k, len(EXPOSURES_MS)) + FRAME_HW, np.uint16)
    calibration = np.zeros((k,) + FRAME_HW, np.uint16)
    homographies = np.empty((k, 3, 3))
    flux = np.empty(k)
    for i in range(k):
        # The centre camera defines the reference frame (the one the truth and the recovery share).
        matrix = _misregistration(rng, positions_mm[i]) if misregistered and i != centre else np.eye(3)
        homographies[i] = matrix
        radiance = GAIN * _frame(intensity[i], matrix)
        flux[i] = float(radiance.sum(dtype=np.float64))
        sensor.rng = streams["coherent"]
        for e, t_ms in enumerate(EXPOSURES_MS):
            coherent[i, e] = sensor.record(radiance, t_ms * 1e-3)
        if boards:
            board = render_checkerboard(FRAME_HW, PATTERN, square_px=SQUARE_PX, origin_xy=BOARD_ORIGIN,
                                        matrix=matrix, dark=0.05, light=0.9, blur_px=1.0)
            sensor.rng = streams["boards"]
            calibration[i] = sensor.record(board * 4.0e5, CAL_EXPOSURE_MS * 1e-3)
    sensor.rng = streams["darks"]
    darks = np.stack([np.stack([sensor.record(np.zeros(FRAME_HW), t * 1e-3) for _ in range(DARKS_PER_EXPOSURE)])
                      for t in EXPOSURES_MS])
    flats = np.stack([sensor.record(np.full(FRAME_HW, 6.0e5), FLAT_EXPOSURE_MS * 1e-3) for _ in range(FLATS)])
    return LabCapture(coherent=coherent, calibration=calibration, darks=darks, flats=flats,
                      positions_mm=positions_mm, grid=geometry.grid_indices, homographies=homographies,
                      truth_intensity=(np.abs(field[window]) ** 2).astype(np.float32),
                      truth_band=band[window].astype(np.float32), truth_flux=flux)


def write_lab(out: Path, capture: LabCapture, *, truth: bool = True) -> Path:
    """Write the capture directory (TIFFs, manifest.csv, setup.json, lab.yaml); return the manifest a user gives cca."""
    for sub in ("coherent", "calib", "dark", "flat"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rows = []
    bits = str(BITS)
    for i, ((y_mm, x_mm), (r, c)) in enumerate(zip(capture.positions_mm, capture.grid)):
        for e, t_ms in enumerate(EXPOSURES_MS):
            name = f"coherent/pos_{r:02d}_{c:02d}_{int(t_ms):02d}ms.tif"
            write_image(out / name, capture.coherent[i, e], bit_depth=16)
            rows.append([name, "coherent", t_ms, f"{x_mm:.4f}", f"{y_mm:.4f}", r, c, bits, "21.3", f"{i * 3 + e}"])
        name = f"calib/board_{r:02d}_{c:02d}.tif"
        write_image(out / name, capture.calibration[i], bit_depth=16)
        rows.append([name, "calibration", CAL_EXPOSURE_MS, f"{x_mm:.4f}", f"{y_mm:.4f}", r, c, bits, "21.3", ""])
    for e, t_ms in enumerate(EXPOSURES_MS):
        for n, frame in enumerate(capture.darks[e]):
            name = f"dark/dark_{int(t_ms):02d}ms_{n}.tif"
            write_image(out / name, frame, bit_depth=16)
            rows.append([name, "dark", t_ms, "", "", "", "", bits, "21.2", ""])
    for n, frame in enumerate(capture.flats):
        name = f"flat/flat_{n}.tif"
        write_image(out / name, frame, bit_depth=16)
        rows.append([name, "flat", FLAT_EXPOSURE_MS, "", "", "", "", bits, "21.2", ""])
    with open(out / "manifest.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["file", "kind", "exposure_ms", "stage_x_mm", "stage_y_mm", "grid_row", "grid_col", "bits",
                         "temperature_C", "frame_counter"])
        writer.writerows(rows)
    (out / "setup.json").write_text(json.dumps({**OPTICS, "camera": "simulated 12-bit monochrome"}, indent=2) + "\n")
    (out / "lab.yaml").write_text(LAB_MANIFEST)
    if truth:
        np.save(out / "truth_intensity.npy", capture.truth_intensity)
        np.save(out / "truth_band.npy", capture.truth_band)
        np.save(out / "truth_homographies.npy", capture.homographies)
        np.save(out / "truth_flux.npy", capture.truth_flux)
    return out / "lab.yaml"


LAB_MANIFEST = f"""\
# The manifest a user writes for this lab directory (made by pipelines/make_lab_capture.py, simulated):
# it names the lab's table and setup file and maps the table's columns onto cca's names.
images_csv: manifest.csv
setup: setup.json
columns: {{path: file, kind: kind, exposure: exposure_ms, stage_x: stage_x_mm, stage_y: stage_y_mm,
          row: grid_row, col: grid_col, bit_depth: bits}}
units: {{exposure: ms, position: mm}}
sensor: {{bit_depth: {BITS}, container_bits: 16, alignment: msb}}   # 12-bit codes shifted left by 4
checkerboard: {{pattern: [{PATTERN[0]}, {PATTERN[1]}]}}                  # inner corners (columns, rows), in calib/
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("data_samples/lab_capture"))
    parser.add_argument("--grid", type=int, default=7)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    capture = simulate_lab(args.grid, seed=args.seed)
    manifest = write_lab(args.out, capture)
    print(f"{manifest}: {capture.coherent.shape[0]} positions x {capture.coherent.shape[1]} exposures")


if __name__ == "__main__":
    main()
