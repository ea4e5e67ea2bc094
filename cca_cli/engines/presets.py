"""Which engine, with which options, ``engine: auto`` runs for each kind of data.

Simulations have a perfect model: the paper's alternating minimization
reproduces its numbers. Recorded captures do not: the pupil is aberrated and
the light varies, so they get the sequential engine with calibration.

- LED-array microscopes (a fixed objective, tilted illumination): one pupil
  recovered as Zernike phase (and amplitude) modes plus a smooth remainder
  (``pupil_model: smooth``), with its tilt pinned (``pupil_tilt: pinned``) so
  the object stays registered to the centre capture. A full per-pixel map
  fitted the data it was given more closely but absorbed object detail on
  recorded sets: ring halos, bright spots at the LED-grid frequencies and an
  object that drifted by up to 2 px over the run.
- Camera scans and camera arrays (apertures on a regular lattice): the pupil
  phase in Zernike modes, one pupil per camera when the captures name their
  cameras. A lattice leaves pupil patterns with its own period undetermined
  (the raster-grid ambiguity of ptychography); smooth modes cannot take them.

Both stop when the data misfit falls by less than 2% over 10 passes (a few
seconds on the sets in the README), or after 150 passes (300 for LED arrays,
below). Momentum is moderate (η = 0.3): on recorded data a larger η makes the
low spatial frequencies oscillate, on simulations η = 0.3 converges as fast as
0.7. Batches are 24 captures, not 12: averaging each step over more captures
fitted both real LED-array sets better and sooner (blood smear: residual
0.076 / 0.070 over all / bright-field images after 30 passes, against
0.078 / 0.076 after 60 with 12).

LED arrays also take batches that double at each plateau until a batch may
hold every capture: fixed small batches end in a cycle between the captures'
constraints, which recorded data never satisfy all at once (so the cap is 300
passes). rPIE's α is 0.3 and 5% of the captures are held back from the
updates, spread over bright and dark field: the run ends when their misfit
has stayed more than 1% above its best for 10 passes, and returns to the best
state, so it stops where the recovery predicts unseen data best rather than
where it fits its own data closest.

These were chosen on the tuning half of the recorded-set corpus
(``benchmarks/real_corpus.py``: a blood smear, two USAF targets) and judged on
its validation half; benchmarks/README.md has both tables. Against the
previous full pupil map (residual all / bright field, common reading) the
blood smear went from 0.069 / 0.060 to 0.069 / 0.059, the 32² USAF tile from
0.140 / 0.084 to 0.127 / 0.065 and the 8-bit USAF set from 0.105 / 0.053 to
0.099 / 0.044; the finest resolved element is G9E1 on the tile (G9E2 before)
and G9E2 on the 8-bit set (G9E1 before).
α = 0.1 kept a little more contrast in the tile's finest bars but fitted all
three sets worse; α = 0.5 lost G9E1 on the tile.

The engine the preset picks keeps these settings when a user names it outright
on recorded captures (:func:`engine_defaults`): ``engine: momentum`` on an
LED-array set recovers the pupil, as PtyLab's mPIE and fpm-rs's EPRY do by
default.
"""

from __future__ import annotations

__all__ = ["DATA_KINDS", "preset", "engine_defaults", "starting_options", "summary"]

_REAL_DATA = dict(max_iterations=150, tol=1e-7, plateau=0.02, plateau_window=10, eta=0.3, batch=24)

_PRESETS = {
    "simulation": ("altmin", {}),
    "led_array": ("momentum", dict(_REAL_DATA, max_iterations=300, batch_growth=2, alpha=0.3, hold_back=0.05,
                                   pupil_recovery="shared", pupil_model="smooth", pupil_tilt="pinned")),
    "camera_scan": ("momentum", dict(_REAL_DATA, pupil_recovery="per_camera", pupil_model="zernike")),
}

#: The kinds of data ``engine: auto`` tells apart.
DATA_KINDS = tuple(_PRESETS)


def preset(kind: str) -> tuple[str, dict]:
    """Engine name and options (``max_iterations``, ``tol`` included) for a kind of data.

    Parameters
    ----------
    kind : {"simulation", "led_array", "camera_scan"}

    Returns
    -------
    engine : str
    options : dict
        A fresh copy; the simulation preset leaves every option at the engine's default.
    """
    try:
        engine, options = _PRESETS[kind]
    except KeyError:
        raise ValueError(f"unknown kind of data {kind!r}; choose one of {', '.join(DATA_KINDS)}") from None
    return engine, dict(options)


def engine_defaults(engine: str, kind: str) -> dict:
    """Options an engine named outright takes on a kind of data, where the user sets none.

    The engine that ``engine: auto`` picks for recorded captures keeps the
    preset's settings when named outright (``engine: momentum`` on an
    LED-array set recovers the pupil, as mPIE and EPRY do by default); any
    other engine, and every engine on simulations, keeps its own defaults.

    Parameters
    ----------
    engine : str
        A registered engine name.
    kind : {"simulation", "led_array", "camera_scan"}

    Returns
    -------
    dict
        A fresh copy (``max_iterations`` and ``tol`` included where the preset sets them).
    """
    chosen, options = preset(kind)
    return options if kind != "simulation" and chosen == engine else {}


def starting_options(engine: str, kind: str) -> tuple[str, dict]:
    """The engine ``engine`` names (``auto`` resolved for ``kind``) and the options it starts from.

    What the user sets goes on top of these options.
    """
    if engine == "auto":
        return preset(kind)
    return engine, engine_defaults(engine, kind)


def summary() -> str:
    """What ``auto`` picks, in a few words (for help texts)."""
    return "altmin for simulations, momentum with calibration for recorded captures"
