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

from . import sh
from .geometry_volume import GAP_COVERAGE
from .grid import Grid
from .injection import trilinear_corners, visible_corners
from .kernels import lookup as _compiled
from .runtime import jit

REPROJECTION_GAIN = np.pi / (sh.C0**2 + sh.C1**2)  # = 12/7
OFFSET_CELLS = 0.5  # receivers read half a cell along their normal [KD10 sec. 4.4]
PLANE_TOLERANCE = 1e-3  # cells: a corner centred on the receiver's plane stays (scale-stable)
# A face whose surface covers over GAP_COVERAGE of it stands for that surface (its gap, where
# lookups do not sample): lookups read it as closed (lookup_visibility), propagation as it is
OPEN_FOR_LOOKUP = 1.0 - GAP_COVERAGE


def sample(grid: Grid, values: np.ndarray, positions: np.ndarray,
           visibility: np.ndarray | None = None,
           normals: np.ndarray | None = None) -> np.ndarray:
    """Trilinear SH samples (M, 3, K) at world positions (M, 3), K = values.shape[-1] (4, or 9
    for a discrete-ordinates grid); zero outside the grid. With ``visibility``, corners behind
    occluders are left out (injection.visible_corners); with the receivers' ``normals``, the
    corners behind their own planes too (front_corners)."""
    m = positions.shape[0]
    k_coeffs = values.shape[-1]
    if m == 0:
        return np.zeros((0, 3, k_coeffs), np.float32)
    coords = grid.cell_coords(positions)
    idx, wts = trilinear_corners(coords, grid.resolution)
    if normals is not None:
        wts = front_corners(coords, wts, np.asarray(normals, np.float64))
    wts = visible_corners(coords, idx, wts, visibility, grid.resolution)
    flat = values.reshape(-1, 3 * k_coeffs)
    out = np.zeros((m, 3 * k_coeffs), np.float64)
    for k in range(8):
        out += wts[k][:, None] * flat[idx[k]]
    return out.reshape(m, 3, k_coeffs)


def lookup_visibility(visibility: np.ndarray | None) -> np.ndarray | None:
    """The face transmittances a lookup reads (6, R, R, R): those below OPEN_FOR_LOOKUP, faces
    mostly covered by a surface, closed. A room's wall in a cell its corner cuts leaves the
    face part-open (the part outside the room); read as open, the receivers in the room by
    that wall read the cell beyond it, the sunlit outside's light."""
    if visibility is None:
        return None
    v = np.asarray(visibility, np.float32)
    return np.where(v < OPEN_FOR_LOOKUP, np.float32(0.0), v)


def front_corners(coords: np.ndarray, wts: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Trilinear weights (8, N) without the corners whose centre lies behind the receiver's own
    plane (OFFSET_CELLS behind the sample point ``coords`` along ``normals``; PLANE_TOLERANCE),
    the rest renormalised (all behind: unchanged). Such a cell's light is the far side's: a
    wall of single faces crosses the cell whose centre is outside, and its inner side read the
    sunlit outer side's light there."""
    base = np.floor(coords)
    out = wts.copy()
    k = 0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                ahead = ((base[:, 0] + dx - coords[:, 0]) * normals[:, 0]
                         + (base[:, 1] + dy - coords[:, 1]) * normals[:, 1]
                         + (base[:, 2] + dz - coords[:, 2]) * normals[:, 2])
                out[k] = np.where(ahead > -(OFFSET_CELLS + PLANE_TOLERANCE), out[k], 0.0)
                k += 1
    total, original = out.sum(axis=0), wts.sum(axis=0)
    scale = np.divide(original, total, out=np.zeros_like(total), where=total > 0)
    return np.where(total > 0, out * scale, wts)


def gap_corrected(grid: Grid, positions: np.ndarray, gaps: np.ndarray | None) -> np.ndarray:
    """Sample points (M, 3) moved out of the slabs geometry_volume.cell_gaps describes: a
    point in a cell's slab behind a blocked face (room air the face's plane cut off) goes to
    the centre of the neighbour across that face, along that axis only, so it reads the
    light on its own side of the surface."""
    p = np.asarray(positions, np.float64)
    if gaps is None or p.shape[0] == 0:
        return p
    if jit.enabled():
        return _compiled.gap_corrected(grid, p, gaps)
    r = grid.resolution
    rel = (p - grid.origin_array) / grid.cell_size  # face planes at integers
    cell = np.floor(rel).astype(np.int64)
    inside = np.all((cell >= 0) & (cell < r), axis=1)
    out = rel.copy()
    idx = tuple(np.clip(cell, 0, r - 1).T)
    for axis in range(3):
        frac = rel[:, axis] - cell[:, axis]
        below = inside & (frac < gaps[2 * axis + 1][idx])  # in the slab above the lower face
        above = inside & ~below & (1.0 - frac < gaps[2 * axis][idx])
        out[below, axis] = cell[below, axis] - 0.5
        out[above, axis] = cell[above, axis] + 1.5
    return grid.origin_array + out * grid.cell_size


def sample_points(grid: Grid, positions: np.ndarray, normals: np.ndarray,
                  gaps: np.ndarray | None) -> np.ndarray:
    """Where receivers (M, 3) read ``grid``: OFFSET_CELLS along the normal [KD10 sec. 4.4],
    out of the slabs an occluder's plane cut off (gap_corrected). Pass the result to
    ``irradiance`` with ``offset_cells=0``."""
    at = np.asarray(positions, np.float64) + np.asarray(normals, np.float64) * (
        OFFSET_CELLS * grid.cell_size)
    return gap_corrected(grid, at, gaps)


def irradiance(
    grid: Grid,
    values: np.ndarray,
    positions: np.ndarray,
    normals: np.ndarray,
    offset_cells: float = OFFSET_CELLS,
    angular: str = "dom",
    visibility: np.ndarray | None = None,
) -> np.ndarray:
    """Indirect irradiance (M, 3) in W/m^2 at receivers; samples half a cell along the normal.

    A 9-coefficient grid (``angular="dom"``: the flux per direction folded into bands 0-2) is
    read with the irradiance kernel of sh.irradiance_weights, exact for the clamped cosine up to
    band 2 (Ramamoorthi & Hanrahan 2001): a beam, an isotropic field and a uniform hemisphere
    (light leaving a lit floor: a floor receives none of it) all come out right to within the
    kernel's band 4. It leaves out the corners behind the receiver's own plane
    (front_corners), which lies OFFSET_CELLS behind the sample point, and reads faces a
    surface mostly covers as closed (lookup_visibility): with ``offset_cells=0`` the
    ``positions`` are sample points (sample_points). ``angular="sh"`` (KD10's grid, 4
    coefficients): the clamped cosine lobe of the module docstring, times KD10's gradient
    damping (``gradient_damping``).
    """
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    if jit.enabled() and values.shape[-1] == sh.BANDS2 and positions.shape[0]:
        return _compiled.irradiance(grid, values, positions, normals, offset_cells,
                                    OFFSET_CELLS + PLANE_TOLERANCE, OPEN_FOR_LOOKUP, visibility)
    at = positions + normals * (offset_cells * grid.cell_size)
    dom = values.shape[-1] == sh.BANDS2  # KD10's baseline reads all 8, through open faces
    coeffs = sample(grid, values, at, lookup_visibility(visibility) if dom else visibility,
                    normals if dom else None)
    if dom:
        e = np.einsum("mcs,ms->mc", coeffs, sh.irradiance_weights(normals))
        return np.maximum(e / (grid.cell_size**2), 0.0)
    if angular != "sh":
        raise ValueError(f"a {coeffs.shape[-1]}-coefficient grid is KD10's (angular='sh'), "
                         f"not {angular!r}: dom grids hold {sh.BANDS2} coefficients")
    lobe = sh.cosine_lobe(-normals)  # light arriving at the receiver travels along -n
    e = np.einsum("mcs,ms->mc", coeffs, lobe)
    e *= gradient_damping(grid, values, at, normals, e, visibility)
    e *= REPROJECTION_GAIN / (grid.cell_size**2)
    return np.maximum(e, 0.0)


def gradient_damping(grid: Grid, values: np.ndarray, at: np.ndarray, normals: np.ndarray,
                     read: np.ndarray, visibility: np.ndarray | None = None) -> np.ndarray:
    """KD10's damping of self-illumination at lookup (KD10 sec. 6, "Improving the quality",
    light bleeding): the factor (M, 3) in [0, 1] by which a receiver's read of a 4-coefficient
    grid is scaled.

    A receiver reads E = <I, lobe(-n)>, the light travelling along -n, at the sample point
    x_s = x + n s/2 (``at``; ``read`` = E(x_s) per colour). Light that really arrives from in
    front of the surface comes from the +n side, so along +n it grows towards its source:
    dE/dn >= 0. Where E instead falls along +n, the light read moves away from the surface's
    back: it is the light of cells behind the surface that the trilinear read (and the
    diffusive transport) smeared across it, the leak through a wall thinner than a cell.
    With the one-cell central difference s dE/dn ~ E(x_s + n s/2) - E(x_s - n s/2), the
    factor is 1 + s (dE/dn) / E clamped to [0, 1]: 1 where E does not fall along n, 0 where
    it falls by all of E within one cell (light that a cell's length further from the
    surface is gone came from behind it), linear between. Only the "sh" lookup uses it."""
    lobe = sh.cosine_lobe(-np.asarray(normals, np.float64))
    half = np.asarray(normals, np.float64) * (0.5 * grid.cell_size)
    ahead = np.einsum("mcs,ms->mc", sample(grid, values, at + half, visibility), lobe)
    behind = np.einsum("mcs,ms->mc", sample(grid, values, at - half, visibility), lobe)
    with np.errstate(divide="ignore", invalid="ignore"):
        factor = np.where(read > 0, 1.0 + (ahead - behind) / read, 1.0)
    return np.clip(factor, 0.0, 1.0)
