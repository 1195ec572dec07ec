"""Compiled irradiance lookup: the twins of lookup.irradiance (9-coefficient grids) and
lookup.gap_corrected (kernels/__init__.py), point by point with the float64 arithmetic of the
numpy reference, the points split over two threads (the kernels release the GIL).
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..grid import Grid
from ..runtime import jit, pool


def gap_corrected(grid: Grid, positions: np.ndarray, gaps: np.ndarray) -> np.ndarray:
    """lookup.gap_corrected of float64 points (M >= 1, 3) and ``gaps`` by ``_gap_kernel``."""
    out = np.empty_like(positions)
    g, q = np.ascontiguousarray(gaps), np.ascontiguousarray(positions)
    pool.in_parts(lambda sl: _gap_kernel(grid.origin_array, float(grid.cell_size),
                                         grid.resolution, g, q, out, sl.start, sl.stop),
                  q.shape[0])
    return out


def irradiance(grid: Grid, values: np.ndarray, positions: np.ndarray, normals: np.ndarray,
               offset_cells: float, plane: float, open_for_lookup: float,
               visibility: np.ndarray | None = None) -> np.ndarray:
    """lookup.irradiance of a 9-coefficient grid at float64 points (M >= 1, 3) by
    ``_irradiance_kernel``: the same float64 arithmetic as lookup.sample (trilinear,
    front_corners behind ``plane`` cells, visible_corners through lookup_visibility's
    ``open_for_lookup``) and sh.irradiance_weights, point by point (1280x720 points at 32^3:
    numpy ~1.6 s)."""
    r = grid.resolution
    flat = np.ascontiguousarray(values, np.float32).reshape(r**3, 3 * sh.BANDS2)
    vis = (np.zeros((0, 0), np.float32) if visibility is None
           else np.ascontiguousarray(visibility, np.float32).reshape(6, -1))
    kernel = np.array([sh.IRRADIANCE_KERNEL[0]] + [sh.IRRADIANCE_KERNEL[1]] * 3
                      + [sh.IRRADIANCE_KERNEL[2]] * 5)
    pos, nrm = np.ascontiguousarray(positions), np.ascontiguousarray(normals)
    out = np.empty((pos.shape[0], 3), np.float64)
    pool.in_parts(lambda sl: _irradiance_kernel(
        grid.origin_array, float(grid.cell_size), r, flat, vis, kernel, pos, nrm,
        float(offset_cells), float(plane), float(open_for_lookup), out, sl.start, sl.stop),
        pos.shape[0])
    return out


@jit.kernel
def _irradiance_kernel(origin, cell, r, flat, vis, kernel, pos, nrm, offset, plane, open_,
                       out, m0, m1):  # pragma: no cover - compiled
    """``irradiance`` (9 coefficients) of points m0..m1-1: the sample point ``offset`` cells
    along the normal, grid.cell_coords, injection.trilinear_corners (corners outside get
    weight 0), lookup.front_corners behind ``plane``, injection.visible_corners with ``vis``
    (6, R^3) read as lookup.lookup_visibility does with ``open_`` (none when empty), the
    trilinear sum in corner order, the band 0-2 irradiance weights of -n, / s^2, >= 0."""
    has_vis = vis.shape[0] > 0
    s2 = cell * cell
    w = np.empty(8)
    seen = np.empty(8)
    idx = np.empty(8, np.int64)
    acc = np.empty(3 * 9)
    y = np.empty(9)
    for m in range(m0, m1):
        nx, ny, nz = nrm[m, 0], nrm[m, 1], nrm[m, 2]
        px = pos[m, 0] + nx * (offset * cell)
        py = pos[m, 1] + ny * (offset * cell)
        pz = pos[m, 2] + nz * (offset * cell)
        cx = (px - origin[0]) / cell - 0.5
        cy = (py - origin[1]) / cell - 0.5
        cz = (pz - origin[2]) / cell - 0.5
        bx, by, bz = np.floor(cx), np.floor(cy), np.floor(cz)
        fx, fy, fz = cx - bx, cy - by, cz - bz
        ix0, iy0, iz0 = int(bx), int(by), int(bz)
        k = 0
        for dx in range(2):
            wx = fx if dx else 1.0 - fx
            ix = ix0 + dx
            for dy in range(2):
                wy = fy if dy else 1.0 - fy
                iy = iy0 + dy
                for dz in range(2):
                    wz = fz if dz else 1.0 - fz
                    iz = iz0 + dz
                    if 0 <= ix < r and 0 <= iy < r and 0 <= iz < r:
                        idx[k] = (ix * r + iy) * r + iz
                        w[k] = wx * wy * wz
                    else:
                        idx[k] = 0
                        w[k] = 0.0
                    k += 1
        # front_corners: corners behind the receiver's plane out, the rest renormalised
        total = 0.0
        original = 0.0
        k = 0
        for dx in range(2):
            for dy in range(2):
                for dz in range(2):
                    ahead = ((bx + dx - cx) * nx + (by + dy - cy) * ny + (bz + dz - cz) * nz)
                    original += w[k]
                    if ahead > -plane:
                        seen[k] = w[k]
                    else:
                        seen[k] = 0.0
                    total += seen[k]
                    k += 1
        if total > 0:
            scale = original / total
            for k in range(8):
                w[k] = seen[k] * scale
        if has_vis:  # visible_corners: corners behind occluders out, the rest renormalised
            near = (1 if fx > 0.5 + 1e-3 else 0, 1 if fy > 0.5 + 1e-3 else 0,
                    1 if fz > 0.5 + 1e-3 else 0)
            c = ((min(max(ix0 + near[0], 0), r - 1) * r + min(max(iy0 + near[1], 0), r - 1))
                 * r + min(max(iz0 + near[2], 0), r - 1))
            total = 0.0
            original = 0.0
            k = 0
            for dx in range(2):
                for dy in range(2):
                    for dz in range(2):
                        factor = 1.0
                        for axis, d in enumerate((dx, dy, dz)):
                            step = d - near[axis]
                            t = 1.0
                            if step > 0:
                                t = vis[2 * axis, c]
                            elif step < 0:
                                t = vis[2 * axis + 1, c]
                            factor *= t if t >= open_ else 0.0  # lookup_visibility
                        seen[k] = w[k] * factor
                        total += seen[k]
                        original += w[k]
                        k += 1
            if total > 0:
                scale = original / total
                for k in range(8):
                    w[k] = seen[k] * scale
        for t in range(27):
            acc[t] = 0.0
        for k in range(8):
            wk = w[k]
            row = idx[k]
            for t in range(27):
                acc[t] += wk * flat[row, t]
        x, yy, z = -nx, -ny, -nz
        y[0] = 0.28209479177387814
        y[1], y[2], y[3] = -0.4886025119029199 * yy, 0.4886025119029199 * z, \
            -0.4886025119029199 * x
        y[4] = 1.0925484305920792 * x * yy
        y[5] = 1.0925484305920792 * yy * z
        y[6] = 0.31539156525252005 * (3.0 * z * z - 1.0)
        y[7] = 1.0925484305920792 * x * z
        y[8] = 0.5462742152960396 * (x * x - yy * yy)
        for col in range(3):
            e = 0.0
            for t in range(9):
                e += acc[col * 9 + t] * (y[t] * kernel[t])
            e = e / s2
            out[m, col] = max(0.0, e)


@jit.kernel
def _gap_kernel(origin, cell, r, gaps, pos, out, m0, m1):  # pragma: no cover - compiled
    """``gap_corrected`` of points m0..m1-1 (the same float64 operations): a point in the
    slab behind a blocked face of its cell (gaps (6, R, R, R)) goes to the centre of the
    neighbour across it, along that axis only."""
    for m in range(m0, m1):
        rx = (pos[m, 0] - origin[0]) / cell
        ry = (pos[m, 1] - origin[1]) / cell
        rz = (pos[m, 2] - origin[2]) / cell
        ci, cj, ck = int(np.floor(rx)), int(np.floor(ry)), int(np.floor(rz))
        inside = 0 <= ci < r and 0 <= cj < r and 0 <= ck < r
        i, j, k = min(max(ci, 0), r - 1), min(max(cj, 0), r - 1), min(max(ck, 0), r - 1)
        for a, rel, base in ((0, rx, ci), (1, ry, cj), (2, rz, ck)):
            moved = rel
            if inside:
                frac = rel - base
                if frac < gaps[2 * a + 1, i, j, k]:
                    moved = base - 0.5
                elif 1.0 - frac < gaps[2 * a, i, j, k]:
                    moved = base + 1.5
            out[m, a] = origin[a] + moved * cell
