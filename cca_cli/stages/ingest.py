"""Stage `ingest`: a capture manifest and its image files → raw.h5.

Every image is read (OpenImageIO, or one MATLAB variable for LED-array
datasets) and decoded to counts (:mod:`cca_cli.io.sensor`: containers, bit
depths, channels). Dark frames give a per-pixel black level per exposure,
flat frames a gain map (:mod:`cca_cli.hdr.calibration`); the coherent frames
are black-subtracted (negative values kept: clipping them would bias dim
pixels upwards), divided by the gain map and grouped by position into
``(K, E, H, W)`` exposure brackets. Calibration (board) images are stored
per position for the register stage; they may come at another bit depth
than the captures (the board shot in another camera mode) and are then read
at their own depth. Positions become pupil centres in
spectrum pixels in :mod:`cca_cli.sampling.capture`. Single-exposure
datasets also get ``/measurements`` so they can go straight to
`reconstruct` (or `register`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from cca_cli.errors import ConfigError, InputError
from cca_cli.hdr.calibration import (dark_model, electrons_per_count_from_flats, gain_map,
                                     read_noise_from_darks)
from cca_cli.io.captures import BOUNDARY_OPEN, SensorCalibration, read_labels, read_sensor, write_labels
from cca_cli.io.geometry import write_geometry
from cca_cli.io.h5 import Provenance, atomic_h5, check_output, write_dataset
from cca_cli.io.images import read_stored
from cca_cli.io.manifest import CapturePlan, plan_captures, read_manifest, read_pupil
from cca_cli.io.ptylab import read_ptylab_images
from cca_cli.io.records import write_sensor_records
from cca_cli.io.stacks import read_stack
from cca_cli.library.axis import axis_offset
from cca_cli.library.defects import MOST_PIXELS, dead_lines, fill_pixels, hot_pixels
from cca_cli.library.stray_light import FLOOR_SHARE, dark_field_floor
from cca_cli.library.orientation import recorded_orientation_advice
from cca_cli.library.recovery import UNLIT_FACTOR, judge_bright_field
from cca_cli.io.sensor import (Decoding, FrameValues, SensorRule, board_decodings, decide_decoding, frame_values,
                               same_depth)
from cca_cli.sampling.capture import led_array_geometry, stage_scan_geometry
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.grid import band_sizes
from cca_cli.sampling.region import plan_embedding
from cca_cli.stages.progress import ProgressEvent, ProgressFn, silent

__all__ = ["SECTIONS", "MAX_GRID_PX", "Ingested", "SensorCalibration", "ingest", "check_geometry", "write_raw", "run",
           "write_labels", "read_labels", "read_sensor", "BOUNDARY_OPEN"]

SECTIONS = ("ingest",)
#: Widest recovery grid a manifest may imply (px): one such complex grid alone takes 34 GB, so a wider one
#: comes from a wrong position or wrong optics, not from a capture set.
MAX_GRID_PX = 1 << 16

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Ingested:
    """Linear frames of a capture set, their calibration and their geometry."""

    plan: CapturePlan
    frames: np.ndarray          # (K, E, H, W) float32 counts, black subtracted, gain corrected (negatives kept)
    exposure_s: np.ndarray      # (K, E)
    saturation_level: float     # white level − black level (counts; the scalar case)
    geometry: CaptureGeometry
    sensor: SensorCalibration | None = None
    board_views: np.ndarray | None = None       # (K, H, W) float32 counts/s
    initial_pupil: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)


def _read_mat(plan: CapturePlan) -> np.ndarray:
    """The images of ``source.mat`` (one per row of the illumination table) or of ``source.ptylab``, (K, 1, H, W),
    float32."""
    source = plan.manifest.source
    if source.ptylab is not None:
        stack, where = read_ptylab_images(source.ptylab, len(plan.labels)), source.ptylab
    else:
        stack, where = read_stack(source.mat, source.variable, len(plan.labels), table=source.illumination_csv.name), \
            source.mat
    bad = ~np.isfinite(stack).reshape(stack.shape[0], -1).all(axis=1)
    if bad.any():
        raise InputError(f"{where}: {plan.labels[int(np.argmax(bad))]} contains NaN or infinite pixels; fix or drop it")
    return stack[:, None]


#: Sensor keys that decode stored codes (containers, colour sites): a MATLAB variable's values are read as they are.
_DECODING_KEYS = ("container_bits", "alignment", "channel", "bayer")


def _mat_levels(frames: np.ndarray, manifest, manifest_path: Path) -> tuple[np.ndarray, float | None]:
    """A MATLAB stack less ``sensor.black_level``, and its clipping level (white level, or that of ``bit_depth``).

    Keys that decode stored codes cannot apply to a variable's numbers and are refused naming the key.
    """
    sensor = manifest.sensor
    stated = sorted(key for key in _DECODING_KEYS if key in sensor.model_fields_set and getattr(sensor, key) is not None)
    if stated:
        raise ConfigError(f"{manifest_path}: sensor.{stated[0]} does not apply to a MATLAB variable (source.mat): its "
                          "values are read as they are; remove it (or store the images as files)")
    white = sensor.white_level
    if white is None and sensor.bit_depth is not None:
        white = float(2 ** sensor.bit_depth - 1)
    if white is not None and white <= sensor.black_level:
        raise ConfigError(f"{manifest_path}: sensor.black_level ({sensor.black_level:g}) is not below the white level "
                          f"({white:g}); check both")
    if sensor.black_level:
        frames -= np.float32(sensor.black_level)
    return frames, None if white is None else float(white - sensor.black_level)


def _sensor_rule(plan: CapturePlan) -> SensorRule:
    s = plan.manifest.sensor
    return SensorRule(bit_depth=s.bit_depth or plan.bit_depth, container_bits=s.container_bits, alignment=s.alignment,
                      channel=s.channel, bayer_pattern=s.bayer.pattern if s.bayer else None,
                      bayer_colour=s.bayer.colour if s.bayer else None, source=str(plan.path))


class _Reader:
    """Reads every file once, checking that all frames have one size."""

    def __init__(self, rule: SensorRule):
        self.rule = rule
        self.stats: list[FrameValues] = []
        self.shape: tuple[int, int] | None = None
        self.first: str | None = None

    def read(self, path: Path) -> np.ndarray:
        frame = frame_values(read_stored(path), self.rule)
        if self.shape is None:
            self.shape, self.first = frame.values.shape, frame.path
        elif frame.values.shape != self.shape:
            h0, w0 = self.shape
            h1, w1 = frame.values.shape
            raise InputError(f"{path}: image is {w1}x{h1} px but {self.first} is {w0}x{h0}; "
                             "all images of a capture set must have the same size")
        self.stats.append(replace(frame, values=np.empty(0, np.float32)))  # facts only; values live elsewhere
        return frame.values


def _read_files(plan: CapturePlan, progress: ProgressFn):
    """All frames of the plan in counts and the decoding decided from them; each calibration frame comes with
    whether it is read at its own depth (:func:`_board_depths`)."""
    rule = _sensor_rule(plan)
    reader = _Reader(rule)
    k, e = plan.exposure_s.shape
    total = k * e + len(plan.darks) + len(plan.flats) + sum(len(v) for v in plan.calibration or ())
    done = 0
    frames = None
    for i, row in enumerate(plan.files):
        for j, path in enumerate(row):
            values = reader.read(path)
            if frames is None:
                frames = np.empty((k, e) + values.shape, np.float32)
            frames[i, j] = values
            done += 1
        progress(ProgressEvent("ingest", "images", done, total))

    def read_list(items):
        nonlocal done
        out = []
        for path, _ in items:
            out.append(reader.read(path))
            done += 1
            progress(ProgressEvent("ingest", "images", done, total))
        return out

    darks = read_list(plan.darks)
    flats = read_list(plan.flats)
    captured = len(reader.stats)
    boards = [read_list(views) for views in plan.calibration or ()]
    own, notes = _board_depths(plan, reader.stats[:captured], reader.stats[captured:], rule)
    with_captures = reader.stats[:captured] + [f for f, d in zip(reader.stats[captured:], own) if d is None]
    decoding = decide_decoding(with_captures, rule, white_level=plan.manifest.sensor.white_level)
    decoding = replace(decoding, notes=decoding.notes + notes)
    if decoding.shift:
        scale = np.float32(1.0 / 2**decoding.shift)
        frames *= scale
        darks = [d * scale for d in darks]
        flats = [f * scale for f in flats]
    owns = iter(own)
    boards = [[_board_counts(frame, next(owns), decoding) for frame in views] for views in boards]
    return frames, darks, flats, boards, decoding


def _board_counts(frame: np.ndarray, own: Decoding | None, captures: Decoding) -> tuple[np.ndarray, bool]:
    """A calibration frame in counts, and whether it is at its own depth (then not in the captures' codes)."""
    shift = (captures if own is None else own).shift
    return (frame * np.float32(1.0 / 2**shift) if shift else frame), own is not None


def _board_depths(plan: CapturePlan, captures: list[FrameValues], boards: list[FrameValues],
                  rule: SensorRule) -> tuple[list[Decoding | None], list[str]]:
    """Which calibration views are read at their own bit depth (their decoding; None: read like the captures).

    A view whose file holds another kind of values than the captures (an 8-bit photo beside 16-bit files), or whose
    row states another bit depth, is read at its own depth: only its board corners are used.
    """
    if not boards:
        return [], []
    stated = [plan.calibration_bit_depths.get(path) for views in plan.calibration for path, _ in views]
    captures_bits = rule.bit_depth
    differs = [not same_depth(frame, captures[0]) or (bits is not None and bits != captures_bits)
               for frame, bits in zip(boards, stated)]
    if not any(differs):
        return [None] * len(boards), []
    others = [i for i, d in enumerate(differs) if d]
    decided = board_decodings([boards[i] for i in others], [stated[i] for i in others], rule)
    own: list[Decoding | None] = [None] * len(boards)
    for i, decoding in zip(others, decided):
        own[i] = decoding
    first = boards[others[0]]
    more = f" and {len(others) - 1} more" if len(others) > 1 else ""
    note = (f"calibration views at another bit depth than the captures ({_depth_text(first, stated[others[0]])} "
            f"beside {_depth_text(captures[0], captures_bits)}: {first.path}{more}) are read at their own depth; "
            "only the board's corners are taken from them")
    return own, [note]


def _depth_text(frame: FrameValues, stated: int | None = None) -> str:
    if stated is not None:
        return f"{stated}-bit"
    return "float" if frame.significant_bits is None else f"{frame.significant_bits}-bit"


def _calibrate(plan: CapturePlan, decoding: Decoding, darks, flats, notes: list[str]) -> SensorCalibration:
    sensor = plan.manifest.sensor
    white = sensor.white_level if sensor.white_level is not None else decoding.full_scale
    if white is not None and white <= sensor.black_level:
        raise InputError(f"{plan.path}: sensor white level {white:g} is not above the black level "
                         f"{sensor.black_level:g}; fix sensor.black_level / white_level")
    model = None
    read_noise, epc, source = sensor.read_noise, sensor.electrons_per_count, "manifest"
    if darks:
        model = dark_model(darks, [t for _, t in plan.darks])
        measured = read_noise_from_darks(darks, [t for _, t in plan.darks])
        if read_noise is None and measured is not None:
            read_noise, source = measured, "dark frames"
        if white is not None and (model.black >= white).any():
            raise InputError(f"{plan.darks[0][0]}: dark frames reach the white level; they are not dark frames")
    calibration = SensorCalibration(white_level=white, black_level=sensor.black_level, darks=model,
                                    read_noise=read_noise, electrons_per_count=epc, noise_source=source)
    if flats:
        blacks, unmeasured = [], []
        for path, t in plan.flats:
            level, note = calibration.black_at(t)
            if note and t not in unmeasured:
                unmeasured.append(t)
            blacks.append(np.broadcast_to(np.asarray(level, np.float32), flats[0].shape))
        if unmeasured:
            notes.append(f"flat frames: {calibration.darks.unmeasured_note(sorted(unmeasured))}")
        if white is not None:
            hot = next((p for (p, _), f in zip(plan.flats, flats) if (f >= white * 0.99).any()), None)
            if hot is not None:
                raise InputError(f"{hot}: the flat frame reaches the white level; expose the flats darker")
        try:
            gain = gain_map(flats, blacks)
        except ValueError as exc:
            raise InputError(f"{plan.flats[0][0]}: {exc}") from None
        if epc is None and read_noise is not None:
            epc = electrons_per_count_from_flats(flats, blacks, [t for _, t in plan.flats], read_noise)
            if epc is not None:
                source = f"{source} and flat pairs" if source != "manifest" else "flat pairs"
        calibration = replace(calibration, gain=gain, electrons_per_count=epc, noise_source=source)
    return calibration


def _linearise(frames: np.ndarray, exposure_s: np.ndarray, calibration: SensorCalibration, notes: list[str]) -> None:
    """Subtract the black level of each frame's exposure and divide by the gain map, in place."""
    levels: dict[float, np.ndarray | float] = {}
    unmeasured = []
    for t in np.unique(exposure_s):
        level, note = calibration.black_at(float(t))
        if note:
            unmeasured.append(float(t))
        levels[float(t)] = np.asarray(level, np.float32)
    if unmeasured:
        notes.append(calibration.darks.unmeasured_note(unmeasured))
    inverse_gain = None if calibration.gain is None else (1.0 / calibration.gain).astype(np.float32)
    for i in range(frames.shape[0]):
        for j in range(frames.shape[1]):
            frames[i, j] -= levels[float(exposure_s[i, j])]
            if inverse_gain is not None:
                frames[i, j] *= inverse_gain


def _board_views(plan: CapturePlan, boards: list[list[tuple[np.ndarray, bool]]],
                 calibration: SensorCalibration) -> np.ndarray:
    """One board image per position (counts/s): the mean of its calibration frames, linearised.

    Frames at their own bit depth are divided by the gain map and their exposure only: the black level is in the
    captures' codes.
    """
    out = None
    for k, (views, frames) in enumerate(zip(plan.calibration, boards)):
        rates = []
        for (path, t), (frame, own_depth) in zip(views, frames):
            linear = frame
            if not own_depth:
                level, _ = calibration.black_at(t)
                linear = frame - np.asarray(level, np.float32)
            if calibration.gain is not None:
                linear = linear / calibration.gain
            rates.append(linear / np.float32(t))
        mean = np.mean(rates, axis=0, dtype=np.float64).astype(np.float32)
        if out is None:
            out = np.empty((len(boards),) + mean.shape, np.float32)
        out[k] = mean
    return out


def _same_peak_note(frames: np.ndarray, sensor, full_scale: float | None) -> list[str]:
    """A note when every frame (one exposure a position) peaks at exactly one value, at different pixels: frames
    scaled each to its own maximum look so, and recorded ones do not (unless each clips there, or one hot pixel
    is every frame's brightest). A pixel at that value in every frame is named as a hot pixel instead."""
    if sensor.frame_scale != "shared" or sensor.white_level is not None or frames.shape[1] != 1 or len(frames) < 4:
        return []
    flat = frames[:, 0].reshape(len(frames), -1)
    peaks = flat.max(axis=1)
    if not (peaks[0] > 0 and np.all(peaks == peaks[0])) or len(np.unique(flat.argmax(axis=1))) == 1:
        return []
    everywhere = np.all(flat == peaks[0], axis=0)
    if everywhere.any():   # one pixel at the peak in every frame: a hot pixel, not frames scaled each on its own
        y, x = divmod(int(np.argmax(everywhere)), frames.shape[-1])
        clipped = (full_scale is not None and peaks[0] >= full_scale)
        fate = ("it counts as clipped (weight 0)" if clipped else
                f"it is fitted as recorded unless sensor.white_level is at most {float(peaks[0]):g}")
        return [f"pixel (x {x}, y {y}) sits at {float(peaks[0]):g} in every frame: a hot pixel? {fate}"]
    clipped = "" if full_scale is not None and peaks[0] >= full_scale else " (if each clips there, sensor.white_level)"
    return [f"every frame peaks at exactly {float(peaks[0]):g}: if they were scaled each to its own maximum, say "
            f"sensor.frame_scale: per_frame{clipped}"]


def ingest(manifest_path: Path, *, progress: ProgressFn = silent) -> Ingested:
    """Read a manifest and all its images (no file output)."""
    loaded = read_manifest(manifest_path)
    manifest = loaded.manifest
    plan = plan_captures(manifest, manifest_path, notes=loaded.notes)
    if manifest.sensor.frame_scale == "per_frame" and plan.exposure_s.shape[1] > 1:
        raise ConfigError(f"{manifest_path}: sensor.frame_scale is per_frame but the positions have "
                          f"{plan.exposure_s.shape[1]} exposures each: frames scaled each on its own cannot be merged "
                          "by their exposure times; give one exposure per position, or frame_scale: shared")
    notes = list(plan.notes)
    boards = None
    calibration = None
    binning = 1
    if manifest.source is not None:
        frames, saturation = _mat_levels(_read_mat(plan), manifest, manifest_path)
    else:
        frames, darks, flats, board_frames, decoding = _read_files(plan, progress)
        notes += decoding.notes
        notes += _same_peak_note(frames, manifest.sensor, decoding.full_scale)
        calibration = _calibrate(plan, decoding, darks, flats, notes)
        _linearise(frames, plan.exposure_s, calibration, notes)
        if plan.calibration is not None and manifest.checkerboard is not None:
            boards = _board_views(plan, board_frames, calibration)
        saturation = None if calibration.white_level is None else float(calibration.white_level
                                                                            - calibration.black_level)
        binning = 2 if manifest.sensor.bayer is not None else 1
    if saturation is None:  # float data without a white level: nothing counts as clipped (the brightest value
        saturation = float(np.max(frames)) * 2.0 + 1e-30    # stays below any saturation margin under 50%)
    pupil = None
    known = manifest.known_pupil
    if known.pupil is not None:
        pupil = read_pupil(known.pupil, str(manifest_path))
    h, w = frames.shape[-2:]
    if manifest.optics is not None:
        o = manifest.optics
        pitch = o.pixel_pitch_m * binning
        field_width = w * pitch * o.distance_m / o.focal_length_m
        try:
            geometry = stage_scan_geometry(plan.positions, wavelength_m=o.wavelength_m,
                                           focal_length_m=o.focal_length_m, aperture_diameter_m=o.aperture_diameter_m,
                                           pixel_pitch_m=pitch, distance_m=o.distance_m, field_width_m=field_width,
                                           grid_indices=plan.grid_indices)
        except ValueError as exc:   # optics no lens has (their keys named), or positions no geometry takes
            key = str(exc).split(" ")[0].rstrip(":")
            where = "optics." if key in type(o).model_fields else ""
            raise ConfigError(f"{manifest_path}: {where}{exc}") from None
    else:
        il = manifest.illumination
        pitch = il.pixel_pitch_object_m * binning
        geometry = led_array_geometry(plan.positions, wavelength_m=il.wavelength_m,
                                      numerical_aperture=il.numerical_aperture,
                                      pixel_pitch_object_m=pitch, field_width_m=w * pitch, sign=il.sign,
                                      grid_indices=plan.grid_indices)
    if plan.camera_index is not None:
        geometry = replace(geometry, camera_index=plan.camera_index)
    check_geometry(plan, geometry, (h, w))
    check_neighbours_overlap(plan, geometry)
    notes += fill_dead_lines(frames, saturation)   # first: a stuck bright line would pass for hot pixels
    notes += fill_hot_pixels(frames, saturation)
    off_axis = off_axis_board(plan, geometry, frames)
    # captures an off-axis board puts in the bright field look unlit: the board, not their LEDs, is the cause
    notes += (stray_positions(plan, geometry) + crowded_neighbours(plan, geometry)
              + ([] if off_axis else dark_bright_field(plan, geometry, frames)))
    levelled = bool(plan.darks) or "black_level" in manifest.sensor.model_fields_set
    notes += offset_left_in(plan, geometry, frames, levelled=levelled)
    if manifest.sensor.frame_scale == "per_frame":
        notes.append("sensor.frame_scale is per_frame: the images' relative brightness is unknown, so reconstruct's "
                     "momentum engine (engine: auto on recorded captures) fits each capture's brightness "
                     "(brightness: true)")
    seen: set[str] = set()
    unique_notes = [n for n in notes if not (n in seen or seen.add(n))]
    for note in unique_notes:
        _log.warning("note: %s", note)
    if off_axis:
        _log.warning("%s: %s", manifest_path, off_axis)
        unique_notes.append(off_axis)
    return Ingested(plan=plan, frames=frames, exposure_s=plan.exposure_s, saturation_level=saturation,
                    geometry=geometry, sensor=calibration, board_views=boards, initial_pupil=pupil,
                    notes=unique_notes)


def check_geometry(plan: CapturePlan, geometry: CaptureGeometry, frame_shape: tuple[int, int]) -> None:
    """Refuse optics or positions no recovery could represent, naming the manifest keys or the position.

    The pupil must span at least one spectrum pixel and fit the grid the frames are recovered on
    (:func:`~cca_cli.sampling.region.plan_embedding`, :func:`~cca_cli.sampling.grid.band_sizes`: the choice
    reconstruct makes), and every pupil must lie within :data:`MAX_GRID_PX` of the recovery grid.

    Raises
    ------
    ConfigError
        One line naming the manifest, the keys to check and, for a position, its row.
    """
    radius = geometry.pupil_radius_px
    optics = _optics_keys(plan)
    width = frame_shape[1]
    if radius < 1:
        raise ConfigError(f"{plan.path}: the optics give a pupil of {radius:.3g} spectrum px in radius, less than "
                          f"one resolution cell across the {width}-px frames; check {optics}")
    try:
        band_sizes(0.0, radius, sensor_size=plan_embedding(frame_shape, radius).size)
    except ValueError:
        raise ConfigError(f"{plan.path}: the optics give a pupil of {radius:.3g} spectrum px in radius, more than "
                          f"{width}-px frames can sample; check {optics}") from None
    reach = np.max(np.abs(geometry.spectrum_centres_yx_px), axis=1)
    far = int(np.argmax(reach))
    # reconstruct recovers the frames on a grid with a guard band: spectrum distances grow with it
    widened = plan_embedding(frame_shape, radius).size / width
    needed = 2.0 * (float(reach[far]) + radius) * widened
    if needed > MAX_GRID_PX:
        raise ConfigError(f"{plan.path}: {plan.labels[far]} lies {reach[far]:.3g} spectrum px from the axis, so "
                          f"the recovery grid would be {needed:.3g} px wide (at most {MAX_GRID_PX}); "
                          f"{_position_fix(plan, optics)}")


#: A capture is reported when its nearest neighbour lies this many times the usual spacing away and it reaches
#: that much beyond every other capture (a mistyped position).
STRAY_SPACINGS = 10.0


def stray_positions(plan: CapturePlan, geometry: CaptureGeometry) -> list[str]:
    """Notes on captures that lie apart from every other one and widen the recovery grid to reach them.

    A capture is stray when its nearest neighbour is more than :data:`STRAY_SPACINGS` times the median
    distance between neighbours away and it lies that much farther from the axis than every capture that is
    not (a position typed in the wrong unit, or with a slipped decimal point). A centre LED inside a ring, or
    a ring of sparse dark-field LEDs around a dense grid, are not.

    Returns
    -------
    list of str
        One note per such capture, naming its row and what to check there.
    """
    from scipy.spatial import cKDTree

    centres = np.asarray(geometry.spectrum_centres_yx_px, np.float64)
    if len(centres) < 4:
        return []
    nearest = cKDTree(centres).query(centres, k=2)[0][:, 1]
    spacing = float(np.median(nearest))
    if not spacing > 0:
        return []
    apart = nearest > STRAY_SPACINGS * spacing
    if apart.all():
        return []
    reach = np.max(np.abs(centres), axis=1)
    beyond = apart & (reach > reach[~apart].max() + STRAY_SPACINGS * spacing)
    if beyond.sum() > 2:   # more than a slip or two: a layout (sparse outer LEDs), not a typo
        return []
    fix = {"led": "check that row's kx_norm/ky_norm (or LED position)", "grid": "check that row's grid: [row, col]",
           "stage": "check that row's stage position (stage_x_mm/stage_y_mm, or a table's columns and "
                    "units.position)"}[_positions_from(plan)]
    return [f"{plan.labels[i]} lies {nearest[i] / spacing:.3g} times the usual spacing of the captures from any "
            f"other ({nearest[i]:.4g} against {spacing:.4g} spectrum px) and widens the recovery grid to reach "
            f"it; a mistyped position? {fix}"
            for i in np.flatnonzero(beyond)]


def check_neighbours_overlap(plan: CapturePlan, geometry: CaptureGeometry) -> None:
    """Refuse captures whose usual spacing exceeds the pupil's diameter: no two share any part of the spectrum, so
    phase retrieval cannot join them (a position unit wrong by a thousand, or optics that make the pupil too small).

    Raises
    ------
    ConfigError
        One line naming the spacing, the diameter and what to check.
    """
    spacing, diameter = _usual_spacing(geometry), 2 * geometry.pupil_radius_px
    if not spacing > diameter:
        return
    raise ConfigError(f"{plan.path}: neighbouring captures lie {spacing:.4g} spectrum px apart, more than the pupil's "
                      f"diameter ({diameter:.4g} px): no two overlap, so phase retrieval cannot join them "
                      f"(synthetic aperture {geometry.synthetic_aperture_ratio:.4g} times the lens's); "
                      f"{_spacing_fix(plan)}")


def _usual_spacing(geometry: CaptureGeometry) -> float:
    """Median distance from each capture's pupil centre to its nearest neighbour's (spectrum px; nan for one)."""
    from scipy.spatial import cKDTree

    centres = np.asarray(geometry.spectrum_centres_yx_px, np.float64)
    if len(centres) < 2:
        return float("nan")
    return float(np.median(cKDTree(centres).query(centres, k=2)[0][:, 1]))


def _spacing_fix(plan: CapturePlan) -> str:
    """What sets the captures' spacing against the pupil's size: their positions, then the optics."""
    return {"led": "check the LEDs' kx_norm/ky_norm (or their positions' unit, illumination.led_pitch_m and "
                   "led_distance_m)",
            "grid": "check stage_pitch_mm",
            "stage": "check the positions' unit (units.position, or the columns' suffixes)"}[_positions_from(plan)] \
        + f" and {_optics_keys(plan)}"


#: Neighbouring captures closer than this share of the pupil's diameter (an overlap above 95%), with a synthetic
#: aperture under :data:`CROWDED_SAR` lens apertures, are named in a note.
CROWDED_SPACING = 0.05
#: Closer than this share of the diameter (an overlap above 99%), with the same small SAR, the ingest is refused.
IMPOSSIBLE_SPACING = 0.01
CROWDED_SAR = 1.2


def crowded_neighbours(plan: CapturePlan, geometry: CaptureGeometry) -> list[str]:
    """A note when the captures overlap almost wholly and the synthetic aperture hardly grows (positions in a unit a
    thousand times too small, or optics that make the pupil too large); a dense scan that still reaches far out
    (many LEDs at a high NA) is not named.

    Returns
    -------
    list of str
        Empty, or one note naming the spacing, the diameter, the SAR and what to check.

    Raises
    ------
    ConfigError
        Below :data:`IMPOSSIBLE_SPACING` of the diameter: no board or scan is that dense (a unit slip).
    """
    spacing, diameter = _usual_spacing(geometry), 2 * geometry.pupil_radius_px
    if not (spacing < CROWDED_SPACING * diameter and geometry.synthetic_aperture_ratio < CROWDED_SAR):
        return []
    if spacing < IMPOSSIBLE_SPACING * diameter:
        raise ConfigError(f"{plan.path}: neighbouring captures lie {spacing:.3g} spectrum px apart, "
                          f"{spacing / diameter:.2%} of the pupil's diameter ({diameter:.4g} px): no LED board or scan "
                          f"is that dense (the positions' unit is likely a thousand times too small), and the "
                          f"synthetic aperture would be {geometry.synthetic_aperture_ratio:.3g} times the lens's; "
                          f"{_spacing_fix(plan)}")
    return [f"neighbouring captures lie {spacing:.3g} spectrum px apart, under {CROWDED_SPACING:.0%} of the pupil's "
            f"diameter ({diameter:.4g} px): they overlap almost wholly and the synthetic aperture is "
            f"{geometry.synthetic_aperture_ratio:.3g} times the lens's (SAR); {_spacing_fix(plan)}"]


def dark_bright_field(plan: CapturePlan, geometry: CaptureGeometry, frames: np.ndarray) -> list[str]:
    """Notes on LED-array captures the geometry puts in the bright field that recorded far less light than the
    others there (an LED that did not fire, or a row of the table that names another LED), judged as reconstruct
    judges them (:func:`~cca_cli.library.recovery.judge_bright_field`).

    Returns
    -------
    list of str
        One note per such capture, naming its row; or, when too many bright-field captures are so dark, one note
        that the LEDs' geometry is off.
    """
    if plan.kind != "led_array" or plan.manifest.sensor.frame_scale != "shared":   # per_frame: brightness unknown
        return []
    rate = frames[:, 0].mean(axis=(-2, -1)) / plan.exposure_s[:, 0]
    judged = judge_bright_field(rate, geometry.spectrum_centres_yx_px, geometry.pupil_radius_px)
    if judged is None:
        return []
    if judged.wrong_geometry.size:
        return [f"{judged.wrong_geometry.size} of the {judged.bright.size} captures the geometry puts in the bright "
                f"field recorded {UNLIT_FACTOR:g} times less light than the brightest of them or less (first: "
                f"{plan.labels[judged.wrong_geometry[0]]}): "
                f"the LEDs' geometry does not match the light recorded; check the illumination's positions "
                f"(led_pitch_m, led_distance_m, led_axis_m, or kx_norm/ky_norm), its sign and {_optics_keys(plan)}"]

    def how_much(times: float) -> str:
        return "no light" if not np.isfinite(times) else f"{times:.3g} times less light"

    return [f"{plan.labels[i]} is in the bright field but recorded {how_much(t)} than the median bright-field "
            "capture: did its LED fire? (reconstruct leaves it out; check that row)"
            for i, t in zip(judged.unlit, judged.times_darker)]


def fill_hot_pixels(frames: np.ndarray, saturation: float) -> list[str]:
    """Fill the sensor's hot pixels (:func:`~cca_cli.library.defects.hot_pixels`, found on each position's first
    exposure) in ``frames`` (K, E, H, W), in place, with the mean of their good neighbours; a note naming them.

    A pixel clipped (at ``saturation``) in every frame is left to the clipped pixels' rule (weight 0, named by
    :func:`_same_peak_note`). Not filled where more than :data:`~cca_cli.library.defects.MOST_PIXELS` of the
    frame would be.
    """
    if len(frames) < 5:
        return []
    hot = hot_pixels(frames[:, 0]) & ~np.all(frames[:, 0] >= np.float32(0.99 * saturation), axis=0)
    count = int(hot.sum())
    if not count:
        return []
    y, x = np.argwhere(hot)[0]
    said = (f"{count} pixel(s) stand far above their neighbours by the same amount in every capture (first at x {x}, "
            f"y {y}): hot pixels of the sensor")
    if hot.mean() > MOST_PIXELS:
        return [said + f"? Over {MOST_PIXELS:.0%} of the frame, so they are left as they are: check the sensor's "
                       "settings (black level, binning)"]
    fill_pixels(frames, hot)
    return [said + "; each now reads the mean of its good neighbours"]


#: More dead lines than this share of the frame's columns and rows are not filled: the rule is then wrong.
MOST_LINES = 0.05


def fill_dead_lines(frames: np.ndarray, saturation: float) -> list[str]:
    """Fill the sensor's dead or stuck columns and rows (:func:`~cca_cli.library.defects.dead_lines`, found on
    each position's first exposure) in ``frames`` (K, E, H, W), in place, with the mean of their good neighbours;
    a note naming them.

    A line clipped (at ``saturation``) in every frame is left to the clipped pixels' rule (weight 0). Not filled
    where more than :data:`MOST_LINES` of the lines would be.
    """
    if len(frames) < 5:
        return []
    lines = dead_lines(frames[:, 0])
    dead = lines & ~np.all(frames[:, 0] >= np.float32(0.99 * saturation), axis=0)
    if not dead.any():
        return []
    columns = np.flatnonzero(lines.all(axis=0) & dead.any(axis=0))   # named whole, though a clipped pixel stays
    rows = np.flatnonzero(lines.all(axis=1) & dead.any(axis=1))
    named = [f"column{'s' if len(columns) > 1 else ''} x {', '.join(map(str, columns))}"] if len(columns) else []
    named += [f"row{'s' if len(rows) > 1 else ''} y {', '.join(map(str, rows))}"] if len(rows) else []
    one = len(columns) + len(rows) == 1
    if len(columns) + len(rows) > MOST_LINES * sum(dead.shape):
        return [f"{' and '.join(named)} do not follow their neighbours over the bright captures? Over "
                f"{MOST_LINES:.0%} of the lines, so they are left as they are: check the sensor's settings"]
    fill_pixels(frames, dead)
    return [f"{' and '.join(named)} {'does' if one else 'do'} not follow {'its' if one else 'their'} neighbours "
            "over the bright captures: a dead or stuck line of the sensor; each pixel now reads the mean of its "
            "good neighbours"]


def off_axis_board(plan: CapturePlan, geometry: CaptureGeometry, frames: np.ndarray) -> str:
    """A warning where the bright-field images put the optical axis elsewhere among the LEDs than the manifest
    does (:func:`~cca_cli.library.axis.axis_offset`), with the ``led_axis_m`` (or the sines' correction) that
    puts it there; empty otherwise.

    An LED board half a pitch off its axis, or a grid whose listed rows and columns do not centre on it, passes
    every other check: the recovery fits it with a tilted phase and stripes.
    """
    if plan.kind != "led_array":
        return ""
    light = frames[:, 0].mean(axis=(-2, -1), dtype=np.float64) / plan.exposure_s[:, 0]
    found = axis_offset(frames[:, 0], geometry.spectrum_centres_yx_px, geometry.pupil_radius_px, light)
    if found is None or not found.off_axis:
        return ""
    illumination = plan.manifest.illumination
    per_sine = geometry.field_width_m / geometry.wavelength_m          # spectrum px per unit of sin θ
    sine_y, sine_x = illumination.sign * found.shift_yx_px / per_sine   # what the given sines lack
    text = (f"the bright-field images put the optical axis {found.radii:.2f} pupil radii from where the LED positions "
            f"put it: their sin θ [x, y] read [{sine_x:+.4f}, {sine_y:+.4f}] off (from the edges of the pupil circles "
            f"in the images' spectra, {found.gain:.1f} times sharper there; the shift puts "
            f"{found.misplaced_shifted} captures' light on the wrong side of the pupil's edge, the positions as given "
            f"{found.misplaced_given}). ")
    depth = _led_depths_mm(plan)
    source = plan.manifest.source
    if source is not None and source.ptylab is not None:
        found_z = plan.manifest.illumination.led_distance_m
        text += (f"Is the LED board off the axis? Add [{round(sine_y * found_z, 5):g}, {round(sine_x * found_z, 5):g}] "
                 f"(metres, [y, x]) to every position of {source.ptylab.name}'s encoder")
    elif depth is not None:
        axis = illumination.led_axis_m
        moved = (axis[0] - sine_x * depth / 1e3, axis[1] - sine_y * depth / 1e3)
        text += (f"Is the LED board off the axis? Set illumination.led_axis_m: [{round(moved[0], 5):g}, {round(moved[1], 5):g}] "
                 "(metres, where the axis meets the LED plane)")
    else:
        text += f"Add [{sine_x:+.4f}, {sine_y:+.4f}] to every [kx_norm, ky_norm]"
    return text + ("; reconstruct cannot fit a shift common to every LED (it tilts the object's phase), and its "
                   "images then show stripes")


def offset_left_in(plan: CapturePlan, geometry: CaptureGeometry, frames: np.ndarray, *, levelled: bool) -> list[str]:
    """A note where an LED array's dark-field images never fall near zero: a camera offset (black level) left in
    or, where ``levelled`` (a black level or dark frames given), stray light.

    Either adds light to every dark-field capture that the object did not scatter, which the recovery then takes
    for the object's (a haze over a faint object, and a worse fit of the dark field).
    """
    if plan.kind != "led_array":
        return []
    found = dark_field_floor(frames[:, 0], geometry.spectrum_centres_yx_px, geometry.pupil_radius_px,
                             amplitudes=plan.manifest.values == "amplitude")
    if found is None or found[0] < FLOOR_SHARE:
        return []
    share, read = found
    said = (f"the dark-field images never fall near zero (their darkest 1% of pixels at {share:.0%} of their mean, "
            f"the median of {read} images): ")
    if not levelled:
        return [said + "is the camera's offset left in? Set sensor.black_level (the reading with no light) or give "
                       "dark frames; an offset adds light the object did not scatter (reconstruct fits and takes off "
                       "a plane of it from each dark-field capture: option background)"]
    return [said + "stray light, or an offset beyond the black level? It adds light the object did not scatter, "
                   "which the recovery would take for the object's (a haze over a faint one): reconstruct fits and "
                   "takes off a plane of it from each dark-field capture (option background); better, shield the "
                   "setup from room and LED light, and check sensor.black_level or the dark frames"]


def _led_depths_mm(plan: CapturePlan) -> float | None:
    """The LEDs' median distance from the sample (mm) where the manifest gives their positions in its plane, else
    None (sines given)."""
    coherent = [e for e in plan.manifest.images or [] if e.kind == "coherent"]
    if not coherent or any(e.led_x_mm is None for e in coherent):
        return None
    distance = plan.manifest.illumination.led_distance_m
    depths = [e.led_z_mm if e.led_z_mm is not None else (None if distance is None else distance * 1e3)
              for e in coherent]
    return None if any(d is None for d in depths) else float(np.median(depths))


def _optics_keys(plan: CapturePlan) -> str:
    """The manifest keys that set the pupil's size in the spectrum."""
    if plan.kind == "camera_scan":
        return "optics.aperture_diameter_m, pixel_pitch_m, focal_length_m, distance_m and wavelength_m (all in metres)"
    return ("illumination.numerical_aperture, pixel_pitch_object_m (the camera's pixel over the magnification) and "
            "wavelength_m")


def _positions_from(plan: CapturePlan) -> str:
    """What gives the captures' positions: ``led`` (sines of an LED array), ``grid`` (grid indices and a stage
    pitch) or ``stage`` (stage readings)."""
    if plan.kind == "led_array":
        return "led"
    if all(e.position_kind == "grid" for e in plan.manifest.images if e.kind == "coherent"):
        return "grid"
    return "stage"


def _position_fix(plan: CapturePlan, optics: str) -> str:
    """What sets a position's distance from the axis: the stage reading, the stage pitch, or (LED arrays) the optics."""
    return {"led": f"check {optics}", "grid": "check stage_pitch_mm",
            "stage": "check that row's stage position (stage_x_mm/stage_y_mm, or a table's columns and "
                     "units.position)"}[_positions_from(plan)]


def _write_sensor(handle, calibration: SensorCalibration) -> None:
    darks = calibration.darks
    write_sensor_records(handle, white_level=calibration.white_level, black_level=calibration.black_level,
                         dark_exposure_s=None if darks is None else darks.exposure_s,
                         black_maps=None if darks is None else darks.black, gain_map=calibration.gain,
                         read_noise=calibration.read_noise, electrons_per_count=calibration.electrons_per_count,
                         noise_source=calibration.noise_source)


def single_exposure_measurements(data: Ingested) -> tuple[np.ndarray, np.ndarray] | None:
    """Intensities (counts/s) and weights (0 where clipped) of captures of one exposure each; None for brackets."""
    manifest = data.plan.manifest
    k, e, h, w = data.frames.shape
    if e != 1:
        return None
    counts = data.frames[:, 0]
    intensity = counts / data.exposure_s[:, 0, None, None].astype(np.float32)
    if manifest.values == "amplitude":
        intensity = intensity * intensity
    weight = np.ones_like(counts)
    if manifest.sensor.frame_scale == "per_frame" and manifest.sensor.white_level is None:
        pass   # each frame was scaled so that its brightest pixel sits at full scale: nothing clipped there
    elif data.sensor is not None and data.sensor.white_level is not None:
        for i in range(k):
            weight[i] = counts[i] < np.float32(0.99) * data.sensor.saturation_at(float(data.exposure_s[i, 0]))
    elif data.sensor is not None:
        pass   # float values with no white level stated: no full scale, nothing clipped
    else:
        weight = (counts < np.float32(data.saturation_level * 0.99)).astype(np.float32)
    return intensity, weight


def write_raw(path: Path, data: Ingested, provenance: Provenance, *, force: bool = False) -> None:
    """Write ``raw.h5`` atomically."""
    manifest = data.plan.manifest
    with atomic_h5(path, provenance, force=force) as handle:
        frames = write_dataset(handle, "/raw/frames", data.frames)
        frames.attrs["saturation_level"] = data.saturation_level
        frames.attrs["black_level"] = manifest.sensor.black_level
        frames.attrs["values"] = manifest.values
        frames.attrs["frame_scale"] = manifest.sensor.frame_scale
        write_dataset(handle, "/raw/exposure_s", data.exposure_s)
        write_labels(handle, data.plan.labels)
        write_geometry(handle, data.geometry)
        if manifest.known_pupil.defocus_m is not None:
            handle["geometry"].attrs["defocus_m"] = float(manifest.known_pupil.defocus_m)
        led_distance = getattr(manifest.known_pupil, "led_distance_m", None)
        if led_distance is not None:
            handle["geometry"].attrs["led_distance_m"] = float(led_distance)
        if data.initial_pupil is not None:
            write_dataset(handle, "/calibration/initial_pupil", data.initial_pupil)
        if data.sensor is not None:
            _write_sensor(handle, data.sensor)
        if manifest.checkerboard is not None:
            board = handle.require_group("registration/board")
            board.attrs["pattern"] = np.asarray(manifest.checkerboard.pattern, np.int32)
            if manifest.checkerboard.square_m is not None:
                board.attrs["square_m"] = manifest.checkerboard.square_m
            if data.board_views is not None:
                write_dataset(handle, "/registration/board_views", data.board_views,
                              files=[", ".join(path.name for path, _ in views) for views in data.plan.calibration])
        measured = single_exposure_measurements(data)
        if measured is not None:
            intensity, weight = measured
            ds = write_dataset(handle, "/measurements/intensity", intensity.astype(np.float32), units="counts/s")
            ds.attrs["boundary"] = BOUNDARY_OPEN
            ds.attrs["frame_scale"] = manifest.sensor.frame_scale
            write_dataset(handle, "/measurements/weight", weight)


def run(manifest_path: Path, output: Path, *, provenance: Provenance, force: bool = False,
        progress: ProgressFn = silent) -> Ingested:
    """Ingest ``manifest_path`` and write ``output``."""
    check_output(output, force=force)
    data = ingest(Path(manifest_path), progress=progress)
    measured = single_exposure_measurements(data)
    if measured is not None and data.plan.manifest.checkerboard is None:   # a board: registration comes first
        warning = recorded_orientation_advice(*measured, data.geometry, data.plan.manifest.sensor.frame_scale)
        if warning is not None:
            _log.warning("%s: %s", manifest_path, warning)
    write_raw(output, data, provenance, force=force)
    return data
