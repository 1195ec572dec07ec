"""VPL injection into the LPV [KD10 sec. 4.2].

Each VPL of flux Phi and normal n adds (Phi / pi) x lobe(n) to the grid, which integrates back
to exactly Phi. The VPL is first moved half a cell along its normal (against self-illumination)
and then splatted trilinearly to its 8 nearest cells (less flicker than snapping to one).
Accumulation is a float64 sum per cell: never an average, which would lose flux.
"""

from __future__ import annotations

import numpy as np

from . import sh
from .grid import Grid
from .kernels import injection as _compiled
from .runtime import jit


def trilinear_corners(coords: np.ndarray, resolution: int):
    """For continuous cell coords (N, 3): 8 flat cell indices (8, N) and weights (8, N).

    Weights of corners outside the grid are zero (their share of the flux leaves the volume).
    """
    base = np.floor(coords).astype(np.int64)
    frac = coords - base
    idx = np.empty((8, coords.shape[0]), np.int64)
    wts = np.empty((8, coords.shape[0]), np.float64)
    r = resolution
    k = 0
    for dx in (0, 1):
        wx = frac[:, 0] if dx else 1.0 - frac[:, 0]
        ix = base[:, 0] + dx
        for dy in (0, 1):
            wy = frac[:, 1] if dy else 1.0 - frac[:, 1]
            iy = base[:, 1] + dy
            for dz in (0, 1):
                wz = frac[:, 2] if dz else 1.0 - frac[:, 2]
                iz = base[:, 2] + dz
                inside = (ix >= 0) & (ix < r) & (iy >= 0) & (iy < r) & (iz >= 0) & (iz < r)
                idx[k] = np.where(inside, (ix * r + iy) * r + iz, 0)
                wts[k] = np.where(inside, wx * wy * wz, 0.0)
                k += 1
    return idx, wts


def visible_corners(coords: np.ndarray, idx: np.ndarray, wts: np.ndarray,
                    visibility: np.ndarray | None, resolution: int) -> np.ndarray:
    """Trilinear weights (8, N) with corners behind occluders removed and the rest renormalised.

    A corner counts as far as light gets to it from the cell nearest the point: the product of
    the face transmittances (``visibility`` (6, R, R, R), propagation.AXES order) the step from
    that cell to the corner crosses. So a splat or a lookup never reaches through a wall
    thinner than a cell, and a receiver next to a wall is not darkened by the wall's cells.
    """
    if visibility is None or coords.shape[0] == 0:
        return wts
    r = resolution
    base = np.floor(coords).astype(np.int64)
    # (N, 3) nearest corner's offsets. Points exactly half-way are common by construction (a
    # VPL half a cell off a surface on a half-cell plane): a tolerance keeps the choice from
    # flipping with rounding when the scene is scaled or moved (RSM positions come back from a
    # float32 target: ~1e-5 cells of noise at 128^3).
    near = (coords - base > 0.5 + 1e-3).astype(np.int64)
    cell = np.clip(base + near, 0, r - 1)
    vis = visibility.reshape(6, -1)
    flat_cell = (cell[:, 0] * r + cell[:, 1]) * r + cell[:, 2]
    out = wts.copy()
    k = 0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                factor = np.ones(coords.shape[0])
                for axis, d in enumerate((dx, dy, dz)):
                    step = d - near[:, axis]  # -1, 0 or +1 along this axis
                    plus = vis[2 * axis][flat_cell]
                    minus = vis[2 * axis + 1][flat_cell]
                    factor *= np.where(step > 0, plus, np.where(step < 0, minus, 1.0))
                out[k] *= factor
                k += 1
    total = out.sum(axis=0)
    original = wts.sum(axis=0)
    scale = np.divide(original, total, out=np.zeros_like(total), where=total > 0)
    # Every corner hidden (a point boxed in by occluders at this resolution): keep the plain
    # trilinear weights rather than lose the sample.
    return np.where(total > 0, out * scale, wts)


def inject(grid: Grid, positions: np.ndarray, normals: np.ndarray, flux: np.ndarray,
           offset_cells: float = 0.5, visibility: np.ndarray | None = None,
           index: np.ndarray | None = None) -> np.ndarray:
    """SH intensity grid (R, R, R, 3, 4) float32 from VPLs (N, 3) position, normal, flux (W).

    With ``visibility`` the splat does not reach cells behind occluders (visible_corners).
    ``index`` (int): inject only these rows of the three arrays, in this order, as if given
    ``positions[index]`` etc.; the compiled twin reads them in place (gathering three
    (36k, 3) arrays costs ~1.5 ms in numpy).
    With jit.enabled() the compiled twin (kernels.injection) does the same float64 arithmetic
    per VPL; the numpy code below is the reference."""
    n = positions.shape[0] if index is None else len(index)
    if jit.enabled() and n:
        return _compiled.inject(grid, positions, normals, flux, offset_cells, visibility, index)
    out = grid.zeros()
    if n == 0:
        return out
    if index is not None:
        positions, normals, flux = (np.asarray(a)[index] for a in (positions, normals, flux))
    normals = np.asarray(normals, np.float64)
    shifted = np.asarray(positions, np.float64) + normals * (offset_cells * grid.cell_size)
    coords = grid.cell_coords(shifted)
    idx, wts = trilinear_corners(coords, grid.resolution)
    wts = visible_corners(coords, idx, wts, visibility, grid.resolution)
    coeffs = (np.asarray(flux, np.float64) / np.pi)[:, :, None] * sh.cosine_lobe(normals)[:, None, :]
    flat_idx = idx.ravel()
    cells = grid.resolution ** 3
    flat = out.reshape(cells, 12)
    values = coeffs.reshape(n, 12)
    for ch in range(12):
        flat[:, ch] = np.bincount(
            flat_idx, weights=(wts * values[:, ch]).ravel(), minlength=cells
        )
    return out

