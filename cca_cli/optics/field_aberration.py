"""A lens whose aberration changes across the field: the interpolated-pupil model of a space-variant system.

Off-axis, a real lens adds field curvature (defocus growing with the square of
the field height ``h``), astigmatism (also ``∝ h²``, oriented along the field
direction) and coma (``∝ h``) to its on-axis aberration — the Seidel field
dependence. With ``(y, x)`` the field position over half the frame width
(``h = 1`` at the middle of an edge), the pupil phase at a field point is, in
RMS-normalised Zernike waves (modes ``(n, m)`` of :data:`MODES`, the
normalisation of :func:`cca_cli.optics.zernike.zernike_basis`)::

    defocus        = defocus_waves + field_curvature_waves · (x² + y²)
    astigmatism 0° = astigmatism_waves · (x² − y²)
    astigmatism 45°= astigmatism_waves · 2xy
    coma x, y      = coma_waves · x, coma_waves · y

The field of capture ``k`` is computed with the standard interpolated-PSF model
of a space-variant system (Nagy & O'Leary): the pupil is evaluated at ``n x n``
nodes spread over the frame, corner to corner, each node's pupil images the
whole field, and the fields are blended with bilinear hat weights ``w_j(x)``
that sum to 1 everywhere::

    ψ_k(x) = Σ_j w_j(x) · F⁻¹[ R_k S · P_j ](x)

so between nodes the point-spread function changes smoothly, and at a node it is
that node's. The intensity ``|ψ_k|²`` is what the camera records.
"""

from __future__ import annotations

import numpy as np

from cca_cli.optics.forward import ForwardModel, to_sensor_layout
from cca_cli.optics.pupil import circular_pupils
from cca_cli.optics.zernike import zernike_basis
from cca_cli.sampling.grid import BandLayout

__all__ = ["MODES", "seidel_waves", "node_positions", "hat_weights", "aberration_at", "zernike_phases",
           "field_varying_intensity"]

#: Zernike modes (n, m) of the field-dependent aberration: defocus, astigmatism 0° / 45°, coma x / y.
MODES = ((2, 0), (2, 2), (2, -2), (3, 1), (3, -1))


def seidel_waves(h_yx, *, defocus_waves: float = 0.0, field_curvature_waves: float = 0.0,
                 astigmatism_waves: float = 0.0, coma_waves: float = 0.0) -> np.ndarray:
    """Zernike coefficients (waves RMS, :data:`MODES`) at normalised field positions ``h_yx`` (..., 2)."""
    h = np.asarray(h_yx, np.float64)
    y, x = h[..., 0], h[..., 1]
    return np.stack([defocus_waves + field_curvature_waves * (x * x + y * y),
                     astigmatism_waves * (x * x - y * y), astigmatism_waves * 2.0 * x * y,
                     coma_waves * x, coma_waves * y], axis=-1)


def node_positions(nodes: int, size: int) -> np.ndarray:
    """Pixel coordinates of ``nodes`` points spread evenly from the first to the last pixel of ``size``."""
    if nodes < 2:
        raise ValueError(f"give at least 2 nodes, got {nodes}")
    return np.linspace(0.0, size - 1.0, nodes)


def hat_weights(positions: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Bilinear hat weights of nodes at ``positions`` at coordinates ``coords``: (nodes, len(coords)), sum 1.

    Coordinates outside the nodes' span take the nearest node's weight.
    """
    positions = np.asarray(positions, np.float64)
    coords = np.clip(np.asarray(coords, np.float64), positions[0], positions[-1])
    weights = np.zeros((len(positions), len(coords)))
    cell = np.clip(np.searchsorted(positions, coords, side="right") - 1, 0, len(positions) - 2)
    t = (coords - positions[cell]) / (positions[cell + 1] - positions[cell])
    columns = np.arange(len(coords))
    weights[cell, columns] = 1.0 - t
    weights[cell + 1, columns] += t
    return weights


def aberration_at(waves: np.ndarray, nodes_px: np.ndarray, yx_px) -> np.ndarray:
    """The coefficients of the node grid ``waves`` (n, n, modes) at frame pixels ``yx_px`` (P, 2), bilinearly."""
    waves = np.asarray(waves, np.float64)
    points = np.atleast_2d(np.asarray(yx_px, np.float64))
    wy = hat_weights(nodes_px, points[:, 0])
    wx = hat_weights(nodes_px, points[:, 1])
    return np.einsum("ip,jp,ijm->pm", wy, wx, waves)


def zernike_phases(layout: BandLayout) -> np.ndarray:
    """The phase (radians per wave) of each mode of :data:`MODES` on every capture's pupil box: (modes, K, b, b)."""
    return zernike_basis(layout.box_size, layout.box_centres, layout.pupil_radius_px, modes=MODES)


def field_varying_intensity(spectrum: np.ndarray, layout: BandLayout, node_waves: np.ndarray,
                            sensor_pixels: int) -> np.ndarray:
    """Noise-free captures of a lens whose aberration varies across the field (see the module notes).

    Parameters
    ----------
    spectrum : ndarray, complex64, (M, M)
        Centred object spectrum.
    layout : BandLayout
    node_waves : ndarray, (n, n, modes)
        Zernike coefficients (waves, :data:`MODES`) at the nodes, rows then columns.
    sensor_pixels : int
        Pixels across the stored frame (the nodes sit at :func:`node_positions` of it).

    Returns
    -------
    ndarray, float32, (K, m, m)
        Sensor units and centred sensor layout, as :meth:`ForwardModel.sensor_intensity`.
    """
    node_waves = np.asarray(node_waves, np.float64)
    n = node_waves.shape[0]
    m = layout.lowres_size
    disc = circular_pupils(layout.box_size, layout.box_centres, layout.pupil_radius_px)
    basis = zernike_phases(layout)
    # Band-grid pixel i covers the same field as sensor pixel (i + 0.5)·N/m − 0.5.
    coords = (np.arange(m) + 0.5) * sensor_pixels / m - 0.5
    hats = hat_weights(node_positions(n, sensor_pixels), coords).astype(np.float32)
    field = np.zeros((layout.n_images, m, m), np.complex64)
    for iy in range(n):
        rows = np.flatnonzero(hats[iy])
        for ix in range(n):
            cols = np.flatnonzero(hats[ix])
            phase = np.tensordot(node_waves[iy, ix], basis, axes=1)
            model = ForwardModel(layout, disc * np.exp(1j * phase).astype(np.complex64))
            node_field = to_sensor_layout(model.forward(spectrum))
            weight = np.outer(hats[iy, rows], hats[ix, cols])
            field[:, rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1] += (
                weight * node_field[:, rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1])
    intensity = np.square(np.abs(field))
    intensity *= np.float32(1.0 / ((layout.hires_size / m) ** 2))
    return intensity.astype(np.float32, copy=False)
