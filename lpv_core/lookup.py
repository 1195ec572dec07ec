"""Irradiance lookup from the LPV [KD10 sec. 4.4].

The receiver samples the grid trilinearly and convolves the intensity with the cosine lobe
around its normal: E = k <I, lobe(-n)> / s^2, clamped at zero. Intensity passing through a cell
of cross-section s^2 becomes irradiance by dividing by s^2. The factor
k = pi / (c0^2 + c1^2) = 12/7 undoes the smoothing of re-projection: flux Phi crossing a face
is stored as (Phi/pi) lobe(d), and a receiver facing it reads back
(Phi/pi) <lobe(d), lobe(d)> / s^2 = (7/12) Phi / s^2 instead of Phi / s^2.
"""

from __future__ import annotations

import numpy as np

from . import closure, sh
from .grid import Grid
from .injection import trilinear_corners, visible_corners

REPROJECTION_GAIN = np.pi / (sh.C0**2 + sh.C1**2)  # = 12/7


def sample(grid: Grid, values: np.ndarray, positions: np.ndarray,
           visibility: np.ndarray | None = None) -> np.ndarray:
    """Trilinear SH samples (M, 3, 4) at world positions (M, 3); zero outside the grid.
    With ``visibility``, corners behind occluders are left out (injection.visible_corners)."""
    m = positions.shape[0]
    if m == 0:
        return np.zeros((0, 3, 4), np.float32)
    coords = grid.cell_coords(positions)
    idx, wts = trilinear_corners(coords, grid.resolution)
    wts = visible_corners(coords, idx, wts, visibility, grid.resolution)
    flat = values.reshape(-1, 12)
    out = np.zeros((m, 12), np.float64)
    for k in range(8):
        out += wts[k][:, None] * flat[idx[k]]
    return out.reshape(m, 3, 4)


def irradiance(
    grid: Grid,
    values: np.ndarray,
    positions: np.ndarray,
    normals: np.ndarray,
    offset_cells: float = 0.5,
    angular: str = "sh",
    visibility: np.ndarray | None = None,
) -> np.ndarray:
    """Indirect irradiance (M, 3) in W/m^2 at receivers; samples half a cell along the normal.

    ``angular="m1"``: the cell is read as its maximum-entropy lobe (closure.py), and the flux
    that passed through it becomes irradiance Phi E[max(0, <-n, w>)] / s^2, exact for a beam
    (Phi / s^2 head-on) and for an isotropic field (Phi / (4 s^2) = pi L).
    """
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    coeffs = sample(grid, values, positions + normals * (offset_cells * grid.cell_size),
                    visibility)
    if angular in closure.LOBE_MODELS:
        held, r, d = closure.moments(coeffs)  # (M, 3), (M, 3), (M, 3, 3)
        t = -np.einsum("mcx,mx->mc", d, normals)
        e = held * closure.cosine_expectation(r, t) / (grid.cell_size**2)
        return np.maximum(e, 0.0)
    lobe = sh.cosine_lobe(-normals)  # light arriving at the receiver travels along -n
    e = np.einsum("mcs,ms->mc", coeffs, lobe)
    e *= REPROJECTION_GAIN / (grid.cell_size**2)
    return np.maximum(e, 0.0)
