"""The HDF5 schema: every dataset the pipeline writes, with dtype, units and meaning.

This table is the single source of dataset names; ``cca info`` and the README
are generated from it.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["SCHEMA_VERSION", "INTENSITY", "WEIGHT", "SPECTRUM", "OBJECT", "RECON_INTENSITY", "OBSERVED", "REGION",
           "DatasetSpec", "DATASETS", "spec_for", "GEOMETRY_ATTRS", "markdown_table"]

SCHEMA_VERSION = "cca/1"

#: The datasets the code names most (every one is in :data:`DATASETS`).
INTENSITY = "/measurements/intensity"
WEIGHT = "/measurements/weight"
SPECTRUM = "/recon/spectrum"
OBJECT = "/recon/object"
RECON_INTENSITY = "/recon/intensity"
OBSERVED = "/observed/centre"
REGION = "/recon/region_px"


@dataclass(frozen=True)
class DatasetSpec:
    """One dataset of the schema."""

    path: str
    dtype: str
    shape: str
    units: str
    meaning: str


DATASETS: tuple[DatasetSpec, ...] = (
    DatasetSpec("/measurements/intensity", "float32", "(K, N, N)", "irradiance (unit plane wave = 1)",
                "Captured images on the sensor pixel grid, centred on the optical axis, linear. Recorded captures "
                "(counts/s) may be (K, H, W), any aspect; attribute boundary 'open' marks a window on a larger scene, "
                "which reconstruct places on a square grid with a guard band (reconstruct.padding); attribute frame_scale "
                "'per_frame' marks images each scaled on its own (their relative brightness is fitted)."),
    DatasetSpec("/measurements/weight", "float32", "(K, N, N)", "1",
                "Optional per-pixel confidence in [0, 1]; 0 = pixel ignored by the magnitude update."),
    DatasetSpec("/geometry/aperture_centres_yx_m", "float64", "(K, 2)", "m",
                "Aperture centre [y, x] in the aperture (Fourier) plane for each capture."),
    DatasetSpec("/geometry/spectrum_centres_yx_px", "float64", "(K, 2)", "spectrum px",
                "Pupil centre [y, x] relative to DC in spectrum pixels (derived from the optics)."),
    DatasetSpec("/geometry/grid_indices", "int32", "(K, 2)", "1", "Grid [row, column] of each capture."),
    DatasetSpec("/geometry/camera_index", "int32", "(K,)", "1",
                "Optional: camera of each capture in a camera array (each camera its own lens and pupil)."),
    DatasetSpec("/truth/object", "complex64", "(M, M)", "√irradiance",
                "Simulation ground truth: the object's complex field on the simulation grid."),
    DatasetSpec("/truth/bars", "int32", "(B, 8)", "px",
                "Resolution-chart layout: group, width_px, orientation (0 horizontal, 1 vertical), "
                "role (0 bar, 1 gap), y0, y1, x0, x1 on the truth grid."),
    DatasetSpec("/truth/usaf", "float64", "(B, 11)", "px, lp/mm",
                "USAF-1951 chart layout: group, element, lp_per_mm, width_px (exact), orientation "
                "(0 horizontal, 1 vertical), role (0 bar, 1 gap, 2 group box), y0, y1, x0, x1, size: boxes on the "
                "size x size grid the chart was drawn on (scene.size_px); images are resampled to it to be read."),
    DatasetSpec("/recon/spectrum", "complex64", "(M, M)", "√irradiance · px",
                "Recovered high-resolution spectrum, centred (DC at M//2), orthonormal FFT of the object."),
    DatasetSpec("/recon/object", "complex64", "(M, M)", "√irradiance",
                "Recovered complex object field; with /recon/region_px only the region (h', w') of the padded grid."),
    DatasetSpec("/recon/intensity", "float32", "(M, M)", "irradiance", "Recovered intensity |object|²."),
    DatasetSpec("/recon/residual_per_image", "float64", "(K,)", "1",
                "Relative amplitude misfit ‖s·√b_k |ψ_k| − √I_k‖ / ‖√I_k‖ of each capture under the final model "
                "(calibrated pupils, positions and brightness b_k; s one global scale), over every recorded pixel "
                "alike (weight > 0; the guard band and saturated pixels are left out). Root attributes of /recon: "
                "residual_all, residual_bright_field, residual_dark_field (the same over each set of captures) and "
                "residual_*_without_brightness."),
    DatasetSpec("/calibration/pupil", "complex64", "(P, b, b)", "1",
                "Recovered pupil of each camera (one for a scanned camera or an LED array) on the spectrum grid "
                "(pixel 1/field_width_m): NA disc (centred on box pixel b//2) × aberration."),
    DatasetSpec("/calibration/pupil_map", "complex64", "(P, b, b)", "1",
                "The recovered aberration map of each pupil on the pupil box, without the NA disc: the model's pupil "
                "of capture k is its NA disc at its own (fractional) box centre times pupil_map[pupil_index[k]]. A phase tilt in it is an image shift (kept in the map by default, pupil_tilt)."),
    DatasetSpec("/calibration/pupil_index", "int32", "(K,)", "1", "Pupil (camera) each capture uses."),
    DatasetSpec("/calibration/zernike_waves", "float64", "(P, n_modes)", "waves",
                "Zernike phase coefficients of each pupil (RMS-normalised, Noll modes listed in "
                "/calibration/zernike_modes): fitted, or projected from a full pupil map."),
    DatasetSpec("/calibration/zernike_modes", "int32", "(n_modes, 2)", "1",
                "Radial order n and azimuthal frequency m (negative: sine term) of each Zernike coefficient."),
    DatasetSpec("/calibration/spectrum_centres_yx_px", "float64", "(K, 2)", "spectrum px",
                "Refined pupil centre [y, x] of each capture relative to DC (nominal: /geometry)."),
    DatasetSpec("/calibration/aperture_centres_yx_m", "float64", "(K, 2)", "m",
                "Refined aperture centre [y, x] of each capture in /geometry's convention (LED arrays: sin θ)."),
    DatasetSpec("/calibration/brightness", "float64", "(K,)", "1",
                "Illumination brightness of each capture: the model's intensity is brightness × |ψ|² (1: not fitted)."),
    DatasetSpec("/calibration/background", "float64", "(K,)", "capture intensity",
                "With reconstruct option background: the mean over the recovery's frame of the plane of light "
                "fitted to each capture that the object did not scatter (stray light, an offset), in the captures' "
                "intensity units; 0 where none is fitted (bright-field captures, dark-field ones that fall to zero, "
                "held-back ones)."),
    DatasetSpec("/calibration/bright_field", "bool", "(K,)", "1",
                "Whether each capture is bright-field (its illumination falls inside the NA: pupil centre within "
                "one pupil radius of DC)."),
    DatasetSpec("/recon/region_px", "int32", "(2, 4)", "px",
                "Padded recoveries: [y0, x0, height, width] of the recovered region on the M x M recovery grid "
                "(row 0) and on the square sensor grid the captures were placed on (row 1); the rest of those grids "
                "is the weight-0 guard band. Attributes guard_px, apodize_px, sensor_grid_px."),
    DatasetSpec("/observed/centre", "float32", "(N, N)", "irradiance",
                "The capture nearest the optical axis (what a single camera sees); the region only when padded."),
    DatasetSpec("/history/residual", "float64", "(iterations,)", "1",
                "Relative data misfit ‖w(|ψ| − √I)‖ / ‖w √I‖ per iteration."),
    DatasetSpec("/history/change", "float64", "(iterations,)", "1", "Relative spectrum change per iteration."),
    DatasetSpec("/history/seconds", "float64", "(iterations,)", "s", "Wall time at the end of each iteration."),
    DatasetSpec("/history/held_back", "float64", "(iterations,)", "1",
                "Runs that held captures back from the updates (reconstruct.options.hold_back): their relative "
                "amplitude misfit after each iteration, which ends the run when it stays more than 1% above its best."),
    DatasetSpec("/recon/held_back_captures", "int32", "(H,)", "1",
                "Captures (indices of the recovered set) held back from the updates to judge when to stop; "
                "attribute residual_held_back of /recon: their best misfit."),
    DatasetSpec("/checkpoint/spectrum", "complex64", "(M, M)", "√irradiance · px",
                "<output>.checkpoint only (written by reconstruct every reconstruct.checkpoint_every iterations, "
                "removed once the output is written): the spectrum so far. Attributes of /checkpoint: fingerprint "
                "(SHA-256 of the captures, the reconstruct section and the cca version; another one is never "
                "resumed), iteration, change and the engine's other scalars; /history holds the iterations run."),
    DatasetSpec("/checkpoint/velocity", "complex64", "(M, M)", "√irradiance · px",
                "Checkpoint of the momentum engine: its momentum (velocity) term."),
    DatasetSpec("/checkpoint/anchor", "complex64", "(M, M)", "√irradiance · px",
                "Checkpoint of the momentum engine: the spectrum after its last momentum step."),
    DatasetSpec("/checkpoint/misfits", "float64", "(iterations,)", "irradiance · px²",
                "Checkpoint of the momentum engine: squared data misfit of every pass (plateau test)."),
    DatasetSpec("/checkpoint/brightness", "float64", "(K,)", "1",
                "Checkpoint of the momentum engine: brightness of each capture (problem order)."),
    DatasetSpec("/checkpoint/offsets", "float64", "(K, 2)", "spectrum px",
                "Checkpoint of the momentum engine: per-capture position offsets [y, x] (problem order)."),
    DatasetSpec("/checkpoint/parameters", "float64", "(G,)", "model units",
                "Checkpoint of the momentum engine: parameters of the global position model."),
    DatasetSpec("/checkpoint/pupil_maps", "complex64", "(P, b, b)", "1",
                "Checkpoint of the momentum engine: recovered pupil maps (pupil recovery)."),
    DatasetSpec("/checkpoint/pupil_velocity", "complex64", "(P, b, b)", "1",
                "Checkpoint of the momentum engine: momentum of the pupil maps' steps (pupil_momentum > 0)."),
    DatasetSpec("/checkpoint/pupil_coefficients", "float64", "(P, Z)", "waves",
                "Checkpoint of the momentum engine: recovered Zernike coefficients (pupil recovery)."),
    DatasetSpec("/multiplex/camera_centres_px", "float64", "(P, 2)", "spectrum px",
                "Multiplexed runs: camera aperture centre [y, x] relative to DC. With /multiplex present, "
                "/measurements/intensity holds G = P·T images (pattern-major, then camera) and /geometry "
                "describes the V virtual captures (one per camera, pattern and active source)."),
    DatasetSpec("/multiplex/source_shifts_px", "float64", "(Q, 2)", "spectrum px",
                "Spectrum shift [y, x] made by each illumination source (row-major over the source grid)."),
    DatasetSpec("/multiplex/pattern_sources", "int32", "(Σ N_mux,)", "1",
                "Active sources of every pattern, concatenated; pattern t is "
                "pattern_sources[pattern_offsets[t]:pattern_offsets[t+1]]."),
    DatasetSpec("/multiplex/pattern_offsets", "int64", "(T + 1,)", "1", "Start of each pattern in pattern_sources."),
    DatasetSpec("/multiplex/group_offsets", "int64", "(G + 1,)", "1",
                "Image g is the sum of virtual captures group_offsets[g]:group_offsets[g+1]."),
    DatasetSpec("/multiplex/virtual_centres_px", "float64", "(V, 2)", "spectrum px",
                "Pupil centre c_p + s_q of each virtual capture (equals /geometry/spectrum_centres_yx_px)."),
    DatasetSpec("/multiplex/virtual_camera", "int32", "(V,)", "1", "Camera of each virtual capture."),
    DatasetSpec("/multiplex/virtual_source", "int32", "(V,)", "1", "Source of each virtual capture."),
    DatasetSpec("/multiplex/virtual_pattern", "int32", "(V,)", "1", "Pattern of each virtual capture."),
    DatasetSpec("/multiplex/virtual_group", "int32", "(V,)", "1", "Image (measurement) of each virtual capture."),
    DatasetSpec("/multiplex/measurement_camera", "int32", "(G,)", "1", "Camera of each image."),
    DatasetSpec("/multiplex/measurement_pattern", "int32", "(G,)", "1", "Pattern of each image."),
    DatasetSpec("/raw/frames", "float32", "(K, E, H, W)", "counts",
                "Recorded images (ingest): linear sensor counts (N-bit codes when sensor.bit_depth is given, else "
                "stored values), black level subtracted (per pixel with dark frames) and divided by the gain map "
                "(with flat frames); values below zero are kept (noise about a dark level). Position k, exposure e "
                "(ascending). Attribute saturation_level: white minus scalar black level. With one exposure per "
                "position, ingest also writes /measurements (intensity in counts/s)."),
    DatasetSpec("/sensor/black_level", "float32", "(D, H, W)", "counts",
                "Per-pixel black level: the mean dark frame at each dark exposure (/sensor/dark_exposure_s); other "
                "exposures use the per-pixel line through them. Attributes of /sensor: white_level, black_level "
                "(scalar), read_noise (counts RMS), electrons_per_count, noise_source."),
    DatasetSpec("/sensor/dark_exposure_s", "float64", "(D,)", "s", "Exposure time of each dark level."),
    DatasetSpec("/sensor/gain_map", "float32", "(H, W)", "1",
                "Relative pixel gain from the flat frames (mean 1); the frames are divided by it."),
    DatasetSpec('/truth/aberration_waves', 'float64', '(n, n, 5)', 'waves RMS',
                "Simulations with an aberration section: Zernike coefficients of the lens's pupil phase at n x n field points (rows, columns), modes (n, m) in the attribute zernike_modes (defocus, astigmatism 0° and 45°, coma x and y); the field between them is blended bilinearly."),
    DatasetSpec('/truth/aberration_nodes_px', 'float64', '(n,)', 'sensor px',
                'Position of the field points of /truth/aberration_waves along each axis of the stored frame (pixel centres at integers).'),
    DatasetSpec('/tiles/box_px', 'int32', '(T, 4)', 'frame px',
                'Tiled reconstructions (reconstruct.tiles): the box [y0, x0, height, width] of each tile in the frame, tiles row by row. Attributes of /tiles: size_px, overlap_px, rows, cols, upsampling (blend-grid samples per frame pixel), ran (tiles recovered by the run that wrote the file; the others were finished by an earlier, stopped run) and pupil (per_tile or global).'),
    DatasetSpec('/tiles/grid_index', 'int32', '(T, 2)', '1',
                'Row and column of each tile in the tile grid.'),
    DatasetSpec('/tiles/residual', 'float64', '(T, 3)', '1',
                "Amplitude residual of each tile's final model over all, bright-field and dark-field captures (one global scale per tile)."),
    DatasetSpec('/tiles/iterations', 'int32', '(T,)', '1',
                "Iterations each tile's recovery ran."),
    DatasetSpec('/tiles/seconds', 'float64', '(T,)', 's',
                "Time each tile's recovery took on its worker."),
    DatasetSpec('/tiles/shift_px', 'float64', '(T, 2)', 'blend-grid px',
                'Shift applied to register each tile to its centre capture (tiles whose full pupil map may carry a tilt; 0 otherwise).'),
    DatasetSpec('/tiles/pupil', 'complex64', '(T, P, b, b)', '1',
                'Recovered pupil(s) of each tile on its pupil box, NA disc included.'),
    DatasetSpec('/tiles/zernike_waves', 'float64', '(T, P, modes)', 'waves RMS',
                "Zernike coefficients of each tile's pupil phase (its start was a finished neighbour's; with pupil: global the centre tile's, held fixed)."),
    DatasetSpec('/tiles/zernike_modes', 'int32', '(modes, 2)', '1',
                'Radial order n and azimuthal frequency m of each Zernike mode of /tiles/zernike_waves.'),
    DatasetSpec("/calibration/initial_pupil", "complex64", "(P, P)", "1",
                "Initial pupil from the manifest (optics.pupil / illumination.pupil): the objective's NA disc "
                "inscribed in the P x P array, for the engines. A known defocus is the /geometry attribute defocus_m."),
    DatasetSpec("/raw/exposure_s", "float64", "(K, E)", "s", "Exposure time of each frame."),
    DatasetSpec("/capture/labels", "str", "(K,)", "text", "Readable name of each position (stage position, first file)."),
    DatasetSpec("/hdr/dynamic_range_gain", "float64", "(K,)", "1",
                "Per position: /hdr/dynamic_range over the same range measured by the best single exposure (≥ 1). "
                "With hdr, /measurements/intensity is the inverse-variance merge of every unsaturated frame in "
                "counts/s (relative units: the recovery is scale-free) and /measurements/weight its amplitude-domain "
                "precision relative to a shot-limited pixel (0 = saturated in every exposure)."),
    DatasetSpec("/hdr/dynamic_range", "float64", "(K,)", "1",
                "Per position: brightest over faintest radiance (99.9th / 0.1st percentile) among pixels the merge "
                "measured with SNR ≥ 10."),
    DatasetSpec("/hdr/flux_ratio", "float64", "(K, E)", "1",
                "Per position and exposure (ascending): the exposure's flux over the merged flux on the pixels usable "
                "in every exposure; 1 when exposure times, black level and linearity agree."),
    DatasetSpec("/hdr/flux_ratio_sigma", "float64", "(K, E)", "1",
                "Standard deviation of /hdr/flux_ratio from the noise model."),
    DatasetSpec("/hdr/valid_fraction", "float64", "(K,)", "1", "Share of pixels with a usable exposure, per position."),
    DatasetSpec("/registration/homography", "float64", "(K, 3, 3)", "px",
                "Homography mapping each view's pixels onto the reference (centre) view's, from the checkerboard."),
    DatasetSpec("/registration/rms_px", "float64", "(K,)", "px", "RMS reprojection error of the board corners."),
    DatasetSpec("/registration/object_rms_px", "float64", "(K,)", "px",
                "Estimated registration error over the object region (registration.object_xywh, default the crop): "
                "the homography's uncertainty propagated from the corner residuals, combined with the deviation of "
                "a smooth fit to the corner residuals; RMS over a 9 x 9 grid of points."),
    DatasetSpec("/registration/object_max_px", "float64", "(K,)", "px",
                "Largest estimated registration error over the object region."),
    DatasetSpec("/registration/board_hull_fraction", "float64", "(K,)", "1",
                "Share of the object region inside the convex hull of the board corners (below 1 the homography "
                "extrapolates there)."),
    DatasetSpec("/registration/board_views", "float32", "(K, H, W)", "counts/s",
                "Calibration images of the board at each position (rows of kind calibration), linearised; the "
                "board is found in these instead of the captures. Views at another bit depth than the captures "
                "are in their own codes per second (gain map applied, no black level subtracted). Attribute "
                "files: each view's image file(s)."),
    DatasetSpec("/registration/kept_index", "int32", "(K,)", "1", "Index of each registered view among the ingested ones."),
    DatasetSpec("/registration/corners", "float32", "(K, N, 2)", "px", "Detected inner corners (x, y) in each view."),
    DatasetSpec("/registration/dropped", "str", "(D,)", "text", "Positions lost because no checkerboard was found."),
)

#: Attributes of /geometry (all SI).
GEOMETRY_ATTRS = {
    "wavelength_m": "m",
    "focal_length_m": "m",
    "aperture_diameter_m": "m",
    "pixel_pitch_m": "m",
    "distance_m": "m",
    "field_width_m": "m",
    "pupil_radius_px": "spectrum px",
    "overlap": "1",
    "synthetic_aperture_ratio": "1",
    "centre_index": "1",
    "defocus_m": "m (optional: known distance of the object from focus)",
    "led_distance_m": "m (optional, LED arrays: distance of the LED plane from the sample)",
}


def spec_for(path: str) -> DatasetSpec | None:
    """The schema entry of a dataset path, if any."""
    for spec in DATASETS:
        if spec.path == path:
            return spec
    return None


def markdown_table() -> str:
    """The schema as the README's Markdown table (``python -m cca_cli.io.schema`` prints it)."""
    rows = ["| dataset | dtype | shape | units | meaning |", "|---|---|---|---|---|"]
    rows += [f"| `{d.path}` | {d.dtype} | {d.shape} | {d.units} | {d.meaning} |" for d in DATASETS]
    return "\n".join(rows)


if __name__ == "__main__":
    print(markdown_table())
