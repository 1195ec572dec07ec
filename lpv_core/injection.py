"""VPL injection into the LPV [KD10 sec. 4.2].

Each VPL of flux Phi and normal n adds (Phi / pi) x lobe(n) to the grid, which integrates back
to exactly Phi. The VPL is first moved half a cell along its normal (against self-illumination)
and then splatted trilinearly to its 8 nearest cells (less flicker than snapping to one).
Accumulation is a float64 sum per cell: never an average, which would lose flux.
"""

from __future__ import annotations

import numpy as np

from . import jit, sh
from .grid import Grid


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
           offset_cells: float = 0.5, visibility: np.ndarray | None = None) -> np.ndarray:
    """SH intensity grid (R, R, R, 3, 4) float32 from VPLs (N, 3) position, normal, flux (W).

    With ``visibility`` the splat does not reach cells behind occluders (visible_corners).
    With jit.enabled() a compiled kernel does the same per VPL (~10x faster); the numpy code
    below is the reference."""
    out = grid.zeros()
    n = positions.shape[0]
    if n == 0:
        return out
    if jit.enabled():
        return _inject_compiled(grid, positions, normals, flux, offset_cells, visibility, out)
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


_C0, _C1 = sh.C0, sh.C1  # sh.cosine_lobe's constants, as plain globals for the kernel
# The compiled splat runs as two halves on two threads, each into its own float64 sums, from
# SPLIT_MIN VPLs on grids of at most SPLIT_CELLS cells (sums of <= 384 KiB, cheap to zero and
# add). Measured on this 2-core machine, R=16, 65k VPLs with visibility: 8.0 -> 5.9 ms; at R=32
# the second 3 MiB of sums made it slower (random VPL order: 11 -> 29 ms).
SPLIT_MIN = 8192
SPLIT_CELLS = 16 ** 3


def _inject_compiled(grid: Grid, positions, normals, flux, offset_cells, visibility,
                     out: np.ndarray) -> np.ndarray:
    """inject() through _splat_kernel: same arithmetic as the numpy path, into float64 sums."""
    pos = np.ascontiguousarray(positions, np.float64)
    nrm = np.ascontiguousarray(normals, np.float64)
    phi = np.ascontiguousarray(flux, np.float64)
    r = grid.resolution
    cells = r ** 3
    use_vis = visibility is not None
    vis = (np.ascontiguousarray(visibility).reshape(6, cells) if use_vis
           else np.ones((6, 1), np.float32))
    args = (pos, nrm, phi, grid.origin_array, float(grid.cell_size),
            float(offset_cells * grid.cell_size), r, vis, use_vis)
    n = pos.shape[0]
    acc = np.zeros((cells, 12), np.float64)
    if n < SPLIT_MIN or cells > SPLIT_CELLS:
        _splat_kernel(*args, acc, 0, n)
    else:  # two halves on two threads (the kernel releases the GIL)
        from .ordinates import _pool

        other = np.zeros_like(acc)
        half = n // 2
        job = _pool().submit(_splat_kernel, *args, other, half, n)
        _splat_kernel(*args, acc, 0, half)
        job.result()
        acc += other
    out.reshape(cells, 12)[...] = acc
    return out


@jit.kernel
def _splat_kernel(pos, nrm, flux, origin, cell_size, shift, r, vis, use_vis, acc, lo, hi):
    """VPLs lo..hi-1 added to ``acc`` (R^3, 12) float64: trilinear_corners, visible_corners
    (same tie tolerance, clip and all-hidden rule) and the cosine lobe x flux / pi, per VPL.

    A VPL with all 8 corners outside the grid (or a non-finite position) adds nothing, as its
    zero weights do in numpy; it is skipped before its cell index is made an integer. Corners
    outside are skipped too (numpy adds 0 x value to cell 0: the same unless flux is inf/NaN)."""
    c0 = _C0
    c1 = _C1
    base = np.empty(3, np.int64)
    frac = np.empty(3, np.float64)
    fac = np.ones((3, 2), np.float64)  # per axis: visibility factor of the corner at +0, +1
    near = np.empty(3, np.int64)
    w = np.empty(8, np.float64)
    seen = np.empty(8, np.float64)
    idx = np.empty(8, np.int64)
    vals = np.empty(12, np.float64)
    for i in range(lo, hi):
        skip = False
        for a in range(3):
            c = (pos[i, a] + nrm[i, a] * shift - origin[a]) / cell_size - 0.5
            b = np.floor(c)
            if not (b >= -1.0 and b <= r - 1.0):  # both corners outside (or NaN)
                skip = True
                break
            base[a] = np.int64(b)
            frac[a] = c - b
        if skip:
            continue
        total_w = 0.0
        k = 0
        for dx in range(2):
            ix = base[0] + dx
            wx = frac[0] if dx else 1.0 - frac[0]
            for dy in range(2):
                iy = base[1] + dy
                wy = frac[1] if dy else 1.0 - frac[1]
                for dz in range(2):
                    iz = base[2] + dz
                    wz = frac[2] if dz else 1.0 - frac[2]
                    if 0 <= ix < r and 0 <= iy < r and 0 <= iz < r:
                        idx[k] = (ix * r + iy) * r + iz
                        w[k] = wx * wy * wz
                    else:
                        idx[k] = -1
                        w[k] = 0.0
                    total_w += w[k]
                    k += 1
        if use_vis:
            flat_cell = 0
            for a in range(3):
                near[a] = 1 if frac[a] > 0.5 + 1e-3 else 0
                flat_cell = flat_cell * r + min(max(base[a] + near[a], 0), r - 1)
            for a in range(3):  # step from the nearest cell to the corner at +0 / +1: -1, 0, +1
                fac[a, 0] = np.float64(vis[2 * a + 1, flat_cell]) if near[a] else 1.0
                fac[a, 1] = 1.0 if near[a] else np.float64(vis[2 * a, flat_cell])
            total = 0.0
            k = 0
            for dx in range(2):
                for dy in range(2):
                    for dz in range(2):
                        seen[k] = w[k] * (fac[0, dx] * fac[1, dy] * fac[2, dz])
                        total += seen[k]
                        k += 1
            if total > 0.0:  # else every corner is hidden: plain trilinear weights
                scale = total_w / total
                for k in range(8):
                    w[k] = seen[k] * scale
        for ch in range(3):
            f = flux[i, ch] / np.pi
            vals[4 * ch] = f * c0
            vals[4 * ch + 1] = f * (c1 * -nrm[i, 1])
            vals[4 * ch + 2] = f * (c1 * nrm[i, 2])
            vals[4 * ch + 3] = f * (c1 * -nrm[i, 0])
        for k in range(8):
            j = idx[k]
            if j >= 0:
                wk = w[k]
                for m in range(12):
                    acc[j, m] += wk * vals[m]
