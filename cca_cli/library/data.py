"""What the library takes and gives: captured images with their geometry, and a reconstruction.

:class:`CaptureSet` is the one type for captured intensities (simulated or
recorded, read from a file or given as arrays), and :class:`Reconstruction` the
one type for a recovered object with everything about how it was obtained.
The command line's files hold exactly these (``captures.h5`` and
``recon.h5``, read and written by :mod:`cca_cli.io`).

The checks here keep a recovery from running on nothing: an intensity stack
must hold finite, real numbers, no image may have a mean below zero beyond its noise (noise may
dip below zero, a signal may not), and not every image may be flat. Weights
must match the images, lie in [0, 1] and not be zero everywhere. An image that
holds one value is a dead capture (:func:`constant_images`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cca_cli.engines.base import History
from cca_cli.engines.calibrator import Calibration
from cca_cli.engines.fit import FitReport
from cca_cli.engines.presets import FRAME_SCALES
from cca_cli.sampling.geometry import CaptureGeometry
from cca_cli.sampling.region import RegionEmbedding

__all__ = ["BOUNDARIES", "FRAME_SCALES", "CaptureSet", "data_kind", "Reconstruction", "TiledReconstruction", "check_intensity", "check_weight",
           "constant_images"]

#: ``periodic``: simulated images that wrap; ``open``: windows on a larger scene (recorded frames).
BOUNDARIES = ("periodic", "open")


def data_kind(has_truth: bool, geometry_kind: str) -> str:
    """What captures are, as the engine presets read it: ``simulation`` when a ground truth is known, else the
    geometry's kind (``led_array``, ``camera_scan``)."""
    return "simulation" if has_truth else geometry_kind


@dataclass(frozen=True)
class CaptureSet:
    """Captured intensities with their geometry.

    Attributes
    ----------
    intensity : ndarray, float32, (K, N, N) or (K, H, W)
        Images, centred on the optical axis, linear.
    geometry : CaptureGeometry
    weight : ndarray, float32, shaped as ``intensity``, or None
        Per-pixel confidence in [0, 1] (0: ignored by the recovery).
    truth : dict
        Ground truth of simulations (``object`` and the chart layout tables), else empty.
    units : str or None
        Units of ``intensity`` when not the simulation's irradiance (``counts/s`` for recorded data).
    boundary : {"periodic", "open"}
        ``open``: the images are windows on a larger scene (recorded frames); a
        reconstruction places them on a larger grid with a guard band.
        ``periodic``: simulated, wrapping images.
    initial_pupil : ndarray, complex64, (P, P) or None
        A known pupil on the NA disc (from the manifest's pupil file), the start of pupil recovery.
    dropped : tuple of int
        Images of the source left out as dead (constant) captures.
    frame_scale : {"shared", "per_frame"}
        ``per_frame``: each image was scaled on its own (to its own maximum, by an automatic exposure);
        an engine that can fit each capture's brightness (``momentum``, which ``auto`` picks for recorded
        captures) then does (``brightness: true``, on the CPU).
    """

    intensity: np.ndarray
    geometry: CaptureGeometry
    weight: np.ndarray | None = None
    truth: dict = field(default_factory=dict)
    units: str | None = None
    boundary: str = "periodic"
    initial_pupil: np.ndarray | None = None
    dropped: tuple[int, ...] = ()
    frame_scale: str = "shared"

    def __post_init__(self):
        if self.boundary not in BOUNDARIES:
            raise ValueError(f"boundary must be 'periodic' or 'open', got {self.boundary!r}")
        if self.frame_scale not in FRAME_SCALES:
            raise ValueError(f"frame_scale must be 'shared' or 'per_frame', got {self.frame_scale!r}")

    @property
    def kind(self) -> str:
        """``simulation`` (a ground truth is known), else the geometry's kind (``led_array``, ``camera_scan``)."""
        return data_kind(bool(self.truth), self.geometry.kind)

    @property
    def centre_image(self) -> np.ndarray:
        """The capture nearest the optical axis: what a single camera sees."""
        return self.intensity[self.geometry.centre_index]


@dataclass(frozen=True)
class Reconstruction:
    """A recovered object and how it was obtained.

    Attributes
    ----------
    object : ndarray, complex64, (M, M) or (H, W)
        Recovered complex field at the object (``√`` of the intensity units):
        the whole recovery grid, or the region the captures covered when they
        were placed on a larger square grid (see ``region``).
    spectrum : ndarray, complex64, (M, M)
        Centred spectrum (orthonormal FFT) of the whole recovery grid.
    history : History
        ``history["residual"]`` (relative data misfit of each iteration's
        model, before the final fit report: see ``fit``), ``["change"]``
        (relative spectrum change) and ``["seconds"]`` (wall time since the
        iterations began, at the end of each) per iteration (a mapping of
        those arrays is read as a History).
    geometry : CaptureGeometry
        The captures' geometry on the whole recovery grid.
    engine : str
    options : dict
        The engine's options as run.
    seconds : float
        Time of the engine's iterations (``history["seconds"][-1]``): the problem's set-up and the final
        fit report, which a whole call also spends, are not in it.
    stopped_by : str
        ``tol`` (the change fell below ``tol``), ``plateau`` (the data misfit
        stopped falling) or ``cap`` (the iteration cap came first).
    observed : ndarray or None
        The capture nearest the optical axis (what one camera sees), over the region.
    truth : dict
        Ground truth, when known.
    units : str or None
        Intensity units when not irradiance (``counts/s``).
    band_grid_px : int
        Side of the per-capture grid the engine worked on.
    pupil : ndarray, complex64, (P, b, b) or None
        Recovered pupil of each camera (NA disc × aberration, spectrum grid), for
        engines that recover it; None otherwise.
    positions_px : ndarray, (K, 2) or None
        Pupil centres (spectrum px) a calibrating engine arrived at; None otherwise.
    calibration : Calibration or None
        Everything a calibrating engine found (pupils per capture, Zernike
        coefficients, brightness, global position parameters).
    fit : FitReport or None
        Residuals of the final model: per capture and over all / bright-field / dark-field captures.
    region : RegionEmbedding or None
        Where ``object`` sits when it is a region of the recovery grid (non-square
        or recorded captures placed on a square grid with a guard band); None
        when ``object`` is the whole grid.
    dropped : tuple of int
        Captures left out as dead (constant images).
    held_back : tuple of int
        Captures (of those recovered) the engine held back from its updates to judge when to stop;
        ``history["held_back"]`` is their misfit.
    device : str
        Where the engine ran: ``cpu``, or ``cuda`` (a GPU through CuPy).
    """

    object: np.ndarray
    spectrum: np.ndarray
    history: History
    geometry: CaptureGeometry
    engine: str
    options: dict
    seconds: float
    stopped_by: str
    observed: np.ndarray | None = None
    truth: dict = field(default_factory=dict)
    units: str | None = None
    band_grid_px: int = 0
    pupil: np.ndarray | None = None
    positions_px: np.ndarray | None = None
    calibration: Calibration | None = None
    fit: FitReport | None = None
    region: RegionEmbedding | None = None
    dropped: tuple[int, ...] = ()
    held_back: tuple[int, ...] = ()
    device: str = "cpu"

    def __post_init__(self):
        if not isinstance(self.history, History):  # columns by name, as a user may write them
            object.__setattr__(self, "history", History.from_columns(self.history))

    @property
    def intensity(self) -> np.ndarray:
        """``|object|²`` (float32)."""
        return (np.abs(self.object) ** 2).astype(np.float32)

    @property
    def amplitude(self) -> np.ndarray:
        """``|object|`` (float32)."""
        return np.abs(self.object).astype(np.float32)

    @property
    def phase(self) -> np.ndarray:
        """``angle(object)`` in radians (float32)."""
        return np.angle(self.object).astype(np.float32)

    @property
    def iterations(self) -> int:
        """Iterations run."""
        return self.history.iterations

    @property
    def hires_size(self) -> int:
        """Side M of the recovery grid."""
        return int(self.spectrum.shape[-1])

    @property
    def pixel_size_m(self) -> float:
        """Object-plane pixel size of the recovery grid (m)."""
        return self.geometry.field_width_m / self.hires_size

    @property
    def field_m(self) -> tuple[float, float]:
        """``(height, width)`` of ``object`` at the object plane (m)."""
        rows, cols = self.object.shape[-2:]
        return rows * self.pixel_size_m, cols * self.pixel_size_m


@dataclass(frozen=True)
class TiledReconstruction:
    """A wide frame recovered in overlapping tiles, each with its own pupil, and blended.

    Attributes
    ----------
    object : ndarray, complex64, (q·H, q·W)
        The blended field, ``q`` samples per frame pixel (``upsampling``).
    upsampling : int
    pixel_size_m : float
        Object-plane size of one sample of ``object`` (m).
    boxes_px : ndarray, int, (T, 4)
        Each tile's ``[y0, x0, height, width]`` in frame pixels, row by row.
    zernike_waves : ndarray, (T, P, n_modes) or None
        Each tile's pupil phase in Zernike modes (waves RMS).
    zernike_modes : list of (n, m)
    pupils : ndarray, complex64, (T, P, b, b) or None
        Each tile's recovered pupil(s), NA disc included.
    residual : ndarray, (T, 3)
        Each tile's amplitude residual over all, bright-field and dark-field captures.
    seconds : float
    engine : str
    options : dict
    """

    object: np.ndarray
    upsampling: int
    pixel_size_m: float
    boxes_px: np.ndarray
    zernike_waves: np.ndarray | None
    zernike_modes: list
    pupils: np.ndarray | None
    residual: np.ndarray
    seconds: float
    engine: str
    options: dict

    @property
    def intensity(self) -> np.ndarray:
        """``|object|²`` (float32)."""
        return (np.abs(self.object) ** 2).astype(np.float32)


def _prefix(source) -> str:
    return f"{source}: " if source else ""


def check_intensity(intensity: np.ndarray, name: str = "intensities", *, source=None, error=ValueError,
                    labels=None) -> None:
    """Refuse an intensity stack (K, H, W) that no recovery can use (see the module notes).

    Parameters
    ----------
    intensity : ndarray, (K, H, W)
        Real images.
    name : str
        What the images are called in messages (an argument, or a file's dataset).
    source : str or Path, optional
        The file they come from, which the messages begin with.
    error : type
        The exception raised (``ValueError`` for arrays; files raise :class:`~cca_cli.errors.InputError`).
    labels : sequence of str, optional
        Each image's name (its position and file), added to the messages.
    """
    where = _prefix(source)
    k = intensity.shape[0]
    if k == 0 or intensity.size == 0:
        raise error(f"{where}{name} holds no images")
    flat = intensity.reshape(k, -1)
    finite = np.isfinite(flat).all(axis=1)
    if not finite.all():
        bad = int(np.argmin(finite))
        raise error(f"{where}image {bad} of {name} contains NaN or Inf; fix or mask it")
    if not flat.any():
        raise error(f"{where}every image of {name} is zero; nothing was recorded")
    live = flat.max(axis=1) != flat.min(axis=1)
    if not live.any():
        raise error(f"{where}every image of {name} is flat (one value each), so there is no contrast "
                    "to recover an object from")
    # A constant image (a dead capture, black level subtracted) is judged by constant_images, not here.
    means = np.where(live, flat.mean(axis=1, dtype=np.float64), 0.0)
    # An image that recorded (nearly) no light has a mean of zero up to its noise: only a mean below zero by more
    # than its noise allows (five standard errors) says the black level or the sign is wrong.
    spread = np.where(live, flat.std(axis=1, dtype=np.float64), 0.0) / np.sqrt(flat.shape[1])
    below = means < -5.0 * spread
    if below.any():
        bad = int(np.argmin(np.where(below, means, np.inf)))
        which = f"image {bad}" if labels is None else f"image {bad} ({labels[bad]})"
        more = f" (and {int(below.sum()) - 1} more)" if below.sum() > 1 else ""
        raise error(f"{where}{which}{more} of {name} has a negative mean ({means[bad]:.3g}, {-means[bad] / spread[bad]:.3g} "
                    "times its noise); intensities are ≥ 0 (noise may dip below zero, the signal may not): check "
                    "the black level or the sign")


def constant_images(intensity: np.ndarray) -> np.ndarray:
    """Indices of the images (K, H, W) whose pixels all hold one value: a dead capture records nothing."""
    flat = intensity.reshape(intensity.shape[0], -1)
    return np.flatnonzero(flat.max(axis=1) == flat.min(axis=1))


def check_weight(weight: np.ndarray, shape: tuple[int, ...], name: str = "weight", *, source=None,
                 error=ValueError) -> None:
    """Refuse weights that do not match the images' ``shape``, leave [0, 1] or are 0 everywhere.

    ``name``, ``source`` and ``error`` are as in :func:`check_intensity`.
    """
    where = _prefix(source)
    if weight.shape != tuple(shape):
        raise error(f"{where}{name} has shape {weight.shape}, expected {tuple(shape)}")
    if not np.isfinite(weight).all():
        raise error(f"{where}{name} contains NaN or Inf; weights are in [0, 1]")
    low, high = float(weight.min()), float(weight.max())
    if low < 0 or high > 1:
        raise error(f"{where}{name} spans [{low:.3g}, {high:.3g}]; weights are in [0, 1] (0 ignores a pixel)")
    if high == 0:
        raise error(f"{where}{name} is 0 everywhere, so every pixel would be ignored; "
                    "give weights in (0, 1] where the data are valid")
