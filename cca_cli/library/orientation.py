"""Which way the captures' positions run: a short trial of the axes as given against swapped or flipped ones.

A position table whose x and y columns are swapped, or a stage or LED board whose axis runs the other way,
gives positions that place every capture in the wrong part of the spectrum. The recovery then fits the data
poorly, and its images show stripes, not the object, while nothing else looks wrong. Flipping both axes
changes nothing the intensities can tell (it conjugates the object: see the manifest's ``sign``), so four
arrangements remain: as given, x and y swapped, one axis flipped, and both (swapped, then one flipped).
:func:`orientation_trial` recovers the captures a few passes with each, on a fixed pupil, and compares how
well each fits them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cca_cli.library.data import CaptureSet
from cca_cli.sampling.capture import with_field_width
from cca_cli.sampling.geometry import CaptureGeometry

__all__ = ["ARRANGEMENTS", "OrientationTrial", "orientation_trial", "advice", "recorded_orientation_advice", "arranged",
           "trial_window"]

#: The arrangements of the positions' axes ([y, x] → [y', x']) that intensities can tell apart.
ARRANGEMENTS = {
    "as given": np.array([[1.0, 0.0], [0.0, 1.0]]),
    "x and y swapped": np.array([[0.0, 1.0], [1.0, 0.0]]),
    "x flipped": np.array([[1.0, 0.0], [0.0, -1.0]]),
    "x and y swapped, then x flipped": np.array([[0.0, 1.0], [-1.0, 0.0]]),
}
#: Passes of each trial recovery.
TRIAL_PASSES = 8
#: An arrangement must fit this much better than the positions as given to be named. On the recorded corpus's
#: eight sets (benchmarks/corpus) every other arrangement fitted at least 0.98 times the given one's residual
#: (the line-pair chart, where the trial cannot tell them apart); given their positions swapped, the right
#: arrangement fitted 0.48-0.88 times the swapped one's on five sets and 0.93-0.99 on the other three
#: (``python benchmarks/orientation_trial.py``).
CLEARLY_BETTER = 0.9
#: What to change for each arrangement that fits better.
_FIXES = {
    "x and y swapped": "exchange the x and y position columns (stage_x/stage_y, led_x/led_y, kx_norm/ky_norm, or "
                       "row/col for a board given by its indices; columns: in the manifest)",
    "x flipped": "negate the x positions or the y ones (for a board given by its indices, count the columns or "
                 "the rows the other way): one axis runs the other way; the intensities cannot tell which, and the "
                 "two differ only in the sign of the object's phase (for a camera scan, check which way the stage "
                 "moves the camera)",
    "x and y swapped, then x flipped": "exchange the x and y position columns (or row/col) and negate one of them "
                                       "(or count one index the other way)",
}


@dataclass(frozen=True)
class OrientationTrial:
    """Data residual (all images) of a short fixed-pupil recovery with each arrangement of the positions.

    Attributes
    ----------
    residuals : dict of str to float
        By arrangement (:data:`ARRANGEMENTS`).
    """

    residuals: dict[str, float]

    @property
    def best(self) -> str:
        """The arrangement that fits best."""
        return min(self.residuals, key=self.residuals.get)

    @property
    def clearly_other(self) -> str | None:
        """An arrangement other than the given one that fits far better (:data:`CLEARLY_BETTER`), or None."""
        best = self.best
        given = self.residuals["as given"]
        return best if best != "as given" and self.residuals[best] < CLEARLY_BETTER * given else None


def advice(trial: OrientationTrial) -> str | None:
    """One line for a trial in which another arrangement fits far better, or None."""
    other = trial.clearly_other
    if other is None:
        return None
    return (f"the captures fit far better with their positions' {other} (data residual "
            f"{trial.residuals[other]:.3f} against {trial.residuals['as given']:.3f} as given, in a short trial on "
            f"the nominal pupil): {_FIXES[other]}")


def arranged(captures: CaptureSet, name: str) -> CaptureSet:
    """``captures`` with the positions' axes arranged as :data:`ARRANGEMENTS` ``[name]`` says."""
    matrix = ARRANGEMENTS[name]
    g = captures.geometry
    geometry = replace(g, aperture_centres_yx_m=np.asarray(g.aperture_centres_yx_m, np.float64) @ matrix.T,
                       spectrum_centres_yx_px=np.asarray(g.spectrum_centres_yx_px, np.float64) @ matrix.T)
    return replace(captures, geometry=geometry)


#: Side of the centred window the trial recovers (px), unless the pupil would fall under :data:`TRIAL_RADIUS_PX` in it.
TRIAL_WINDOW_PX = 64
TRIAL_RADIUS_PX = 8.0


def trial_window(captures: CaptureSet) -> CaptureSet:
    """The captures' centred square window of about :data:`TRIAL_WINDOW_PX` (an open-boundary cut-out: its
    guard band is added as for any recorded frame), or the captures themselves where they are as small."""
    h, w = captures.intensity.shape[-2:]
    side = min(h, w)
    radius = captures.geometry.pupil_radius_px * side / w
    size = max(TRIAL_WINDOW_PX, int(np.ceil(side * TRIAL_RADIUS_PX / max(radius, 1e-9))))
    size = min(side, size + size % 2)
    if size == h == w:
        return captures
    y0, x0 = (h - size) // 2, (w - size) // 2
    cut = (slice(None), slice(y0, y0 + size), slice(x0, x0 + size))
    geometry = with_field_width(captures.geometry, captures.geometry.field_width_m * size / w)
    return replace(captures, intensity=np.ascontiguousarray(captures.intensity[cut]),
                   weight=None if captures.weight is None else np.ascontiguousarray(captures.weight[cut]),
                   geometry=geometry, boundary="open")


#: The trial recovers the captures whose pupils lie within this many pupil radii of the spectrum's origin (the
#: bright field and the dark field next to it, which most of the light and the misfit come from), at least
#: :data:`TRIAL_CAPTURES` of them.
TRIAL_REACH = 3.0
TRIAL_CAPTURES = 9


def _near_the_axis(captures: CaptureSet) -> CaptureSet:
    g = captures.geometry
    distance = np.hypot(*np.asarray(g.spectrum_centres_yx_px, np.float64).T)
    keep = np.flatnonzero(distance <= TRIAL_REACH * g.pupil_radius_px)
    if keep.size < TRIAL_CAPTURES:
        keep = np.sort(np.argsort(distance, kind="stable")[:TRIAL_CAPTURES])
    if keep.size == g.n_images:
        return captures
    return replace(captures, intensity=captures.intensity[keep], geometry=g.select(keep),
                   weight=None if captures.weight is None else captures.weight[keep])


def orientation_trial(captures: CaptureSet, *, passes: int = TRIAL_PASSES, threads: int | None = None
                      ) -> OrientationTrial:
    """Recover ``captures`` for ``passes`` with each arrangement of the positions and compare their fits.

    Each trial recovers the captures near the axis (:data:`TRIAL_REACH`) in their centred window
    (:func:`trial_window`) with the momentum engine on the nominal pupil (no calibration), from the same start,
    so that only the positions differ; the residual is the fit report's over all those images.

    Parameters
    ----------
    captures : CaptureSet
        As given (recorded frames not yet embedded in a guard band).
    passes : int
    threads : int, optional
        The engine's threads (default: its own).

    Returns
    -------
    OrientationTrial
    """
    from cca_cli.engines.options import MomentumOptions
    from cca_cli.library.recovery import embed_region, recover

    window = trial_window(_near_the_axis(captures))
    options = MomentumOptions(max_iterations=passes, tol=0.0, plateau=0.0, batch=24, eta=0.3, alpha=0.5,
                              pupil_recovery="none", pupil_estimate=False, threads=threads)
    residuals = {}
    for name in ARRANGEMENTS:
        padded, _ = embed_region(arranged(window, name))
        residuals[name] = float(recover(padded, "momentum", options).fit.all)
    return OrientationTrial(residuals)


def recorded_orientation_advice(intensity: np.ndarray, weight: np.ndarray | None, geometry: CaptureGeometry,
                                frame_scale: str = "shared") -> str | None:
    """:func:`advice` on recorded frames (an open boundary), their dead (constant) images left out; nothing for
    frames scaled each on its own (their brightness is unknown until a recovery fits it), under four live
    captures, or captures a recovery would refuse.

    Parameters
    ----------
    intensity : ndarray, (K, H, W)
    weight : ndarray, (K, H, W) or None
    geometry : CaptureGeometry
    frame_scale : {"shared", "per_frame"}
    """
    from cca_cli.library.data import constant_images

    if frame_scale != "shared":
        return None
    live = np.setdiff1d(np.arange(len(intensity)), constant_images(intensity))
    if live.size < 4:
        return None
    try:
        captures = CaptureSet(np.asarray(intensity[live], np.float32), geometry.select(live),
                              weight=None if weight is None else np.asarray(weight[live], np.float32),
                              boundary="open")
        return advice(orientation_trial(captures))
    except ValueError:   # captures the recovery itself would refuse (flat, no contrast): it says why, not the trial
        return None
