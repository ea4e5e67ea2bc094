"""Zernike modes of a pupil's phase: which modes, their names, and their values on pupil boxes.

Modes are RMS-normalised over the unit disc (Noll): ``√(n+1) R_n(ρ)`` for
``m = 0`` and ``√(2(n+1)) R_n^|m|(ρ) cos(mθ)`` (``sin(|m|θ)`` for ``m < 0``),
so a coefficient of 1 wave is 1 wave RMS of phase. Piston and tilt are left
out: tilt only shifts the image, which the object absorbs.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ZERNIKE_MODES", "zernike_modes", "zernike_name", "zernike_basis", "zernike_phase"]

#: (radial order n, azimuthal frequency m) of the modes used, Noll order from defocus on;
#: ``m < 0`` is the sine term.
ZERNIKE_MODES: tuple[tuple[int, int], ...] = (
    (2, 0), (2, 2), (2, -2),
    (3, 1), (3, -1), (3, 3), (3, -3),
    (4, 0), (4, 2), (4, -2), (4, 4), (4, -4),
)


_MODE_NAMES = {(2, 0): "defocus", (2, 2): "astigmatism_0", (2, -2): "astigmatism_45", (3, 1): "coma_x",
               (3, -1): "coma_y", (3, 3): "trefoil_0", (3, -3): "trefoil_30", (4, 0): "spherical",
               (4, 2): "secondary_astigmatism_0", (4, -2): "secondary_astigmatism_45", (4, 4): "tetrafoil_0",
               (4, -4): "tetrafoil_22"}


def zernike_name(n: int, m: int) -> str:
    """Readable name of the Zernike mode (radial order n, azimuthal frequency m; m < 0 the sine term)."""
    return _MODE_NAMES.get((n, m), f"Z({n},{m})")


def zernike_modes(order: int) -> tuple[tuple[int, int], ...]:
    """The modes of :data:`ZERNIKE_MODES` with radial order ≤ ``order`` (2 to 4)."""
    if not 2 <= order <= 4:
        raise ValueError(f"Zernike order must be 2, 3 or 4, got {order}")
    return tuple(mode for mode in ZERNIKE_MODES if mode[0] <= order)


def _radial(n: int, m: int, rho2: np.ndarray, rho: np.ndarray) -> np.ndarray:
    m = abs(m)
    if (n, m) == (2, 0):
        return 2 * rho2 - 1
    if (n, m) == (2, 2):
        return rho2
    if (n, m) == (3, 1):
        return (3 * rho2 - 2) * rho
    if (n, m) == (3, 3):
        return rho2 * rho
    if (n, m) == (4, 0):
        return 6 * rho2 * rho2 - 6 * rho2 + 1
    if (n, m) == (4, 2):
        return (4 * rho2 - 3) * rho2
    if (n, m) == (4, 4):
        return rho2 * rho2
    raise ValueError(f"unsupported Zernike mode ({n}, {m})")


def zernike_basis(box_size: int, box_centres, radius_px: float, *, order: int = 4, modes=None) -> np.ndarray:
    """Zernike phase modes (radians per wave of coefficient) on each pupil box, RMS-normalised.

    Parameters
    ----------
    box_size : int
    box_centres : array_like, (K, 2)
        Pupil centre ``[y, x]`` inside each box (fractional pixels).
    radius_px : float
    order : int
        Highest radial order (2, 3 or 4: 3, 7 or 12 modes of :data:`ZERNIKE_MODES`).
    modes : sequence of (n, m), optional
        These modes instead of those up to ``order``.

    Returns
    -------
    ndarray, float32, (n_modes, K, box_size, box_size)
    """
    centres = np.asarray(box_centres, dtype=np.float64).reshape(-1, 2)
    grid = np.arange(box_size, dtype=np.float64)
    y = (grid[None, :, None] - centres[:, 0, None, None]) / radius_px
    x = (grid[None, None, :] - centres[:, 1, None, None]) / radius_px
    rho2 = x * x + y * y
    rho = np.sqrt(rho2)
    theta = np.arctan2(y, x)
    modes = zernike_modes(order) if modes is None else tuple(modes)
    out = np.empty((len(modes), centres.shape[0], box_size, box_size), np.float32)
    for j, (n, m) in enumerate(modes):
        norm = np.sqrt(n + 1.0) if m == 0 else np.sqrt(2.0 * (n + 1.0))
        angular = 1.0 if m == 0 else (np.cos(m * theta) if m > 0 else np.sin(-m * theta))
        out[j] = 2.0 * np.pi * norm * _radial(n, m, rho2, rho) * angular
    return out


def zernike_phase(box_size: int, box_centres, radius_px: float, coefficients) -> np.ndarray:
    """The phase (radians) of Zernike ``coefficients`` (waves, :data:`ZERNIKE_MODES` from defocus on) on each box.

    Parameters
    ----------
    box_size : int
    box_centres : array_like, (K, 2)
    radius_px : float
    coefficients : array_like, (n,)
        Waves of the first ``n`` modes of :data:`ZERNIKE_MODES` (defocus, astigmatism 0°, 45°, …).

    Returns
    -------
    ndarray, float32, (K, box_size, box_size)
    """
    coefficients = np.asarray(coefficients, np.float64).ravel()
    basis = zernike_basis(box_size, box_centres, radius_px, modes=ZERNIKE_MODES[:coefficients.size])
    return np.einsum("n,nkyx->kyx", coefficients.astype(np.float32), basis).astype(np.float32)
