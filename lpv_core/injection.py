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
def _splat_add(acc, j, wk, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11):
    """acc[j] += wk x (v0..v11): one corner's 12 sums, each value kept in a register."""
    acc[j, 0] += wk * v0
    acc[j, 1] += wk * v1
    acc[j, 2] += wk * v2
    acc[j, 3] += wk * v3
    acc[j, 4] += wk * v4
    acc[j, 5] += wk * v5
    acc[j, 6] += wk * v6
    acc[j, 7] += wk * v7
    acc[j, 8] += wk * v8
    acc[j, 9] += wk * v9
    acc[j, 10] += wk * v10
    acc[j, 11] += wk * v11


@jit.kernel
def _splat_kernel(pos, nrm, flux, origin, cell_size, shift, r, vis, use_vis, acc, lo, hi):
    """VPLs lo..hi-1 added to ``acc`` (R^3, 12) float64: trilinear_corners, visible_corners
    (same tie tolerance, clip and all-hidden rule) and the cosine lobe x flux / pi, per VPL.

    A VPL with all 8 corners outside the grid (or a non-finite position) adds nothing, as its
    zero weights do in numpy; it is skipped before its cell index is made an integer. Corners
    outside are skipped too (numpy adds 0 x value to cell 0: the same unless flux is inf/NaN).
    Everything per VPL is a scalar (corner k = 4 dx + 2 dy + dz), so it stays in registers;
    each product and sum is the numpy path's, in its order (the same float64 bits)."""
    c0 = _C0
    c1 = _C1
    top = r - 1.0
    rr = r * r
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    for i in range(lo, hi):
        nx = nrm[i, 0]
        ny = nrm[i, 1]
        nz = nrm[i, 2]
        cx = (pos[i, 0] + nx * shift - ox) / cell_size - 0.5
        cy = (pos[i, 1] + ny * shift - oy) / cell_size - 0.5
        cz = (pos[i, 2] + nz * shift - oz) / cell_size - 0.5
        fbx = np.floor(cx)
        fby = np.floor(cy)
        fbz = np.floor(cz)
        # Both corners of an axis outside (or NaN): nothing of this VPL lands in the grid.
        if not (fbx >= -1.0 and fbx <= top and fby >= -1.0 and fby <= top
                and fbz >= -1.0 and fbz <= top):
            continue
        bx = np.int64(fbx)
        by = np.int64(fby)
        bz = np.int64(fbz)
        fx = cx - fbx
        fy = cy - fby
        fz = cz - fbz
        gx = 1.0 - fx
        gy = 1.0 - fy
        gz = 1.0 - fz
        # Corner inside per axis and side (b >= -1 and b <= r - 1 hold here).
        x0 = bx >= 0
        x1 = bx < r - 1
        y0 = by >= 0
        y1 = by < r - 1
        z0 = bz >= 0
        z1 = bz < r - 1
        i0 = x0 and y0 and z0
        i1 = x0 and y0 and z1
        i2 = x0 and y1 and z0
        i3 = x0 and y1 and z1
        i4 = x1 and y0 and z0
        i5 = x1 and y0 and z1
        i6 = x1 and y1 and z0
        i7 = x1 and y1 and z1
        w00 = gx * gy
        w01 = gx * fy
        w10 = fx * gy
        w11 = fx * fy
        w0 = w00 * gz if i0 else 0.0
        w1 = w00 * fz if i1 else 0.0
        w2 = w01 * gz if i2 else 0.0
        w3 = w01 * fz if i3 else 0.0
        w4 = w10 * gz if i4 else 0.0
        w5 = w10 * fz if i5 else 0.0
        w6 = w11 * gz if i6 else 0.0
        w7 = w11 * fz if i7 else 0.0
        if use_vis:
            total_w = 0.0 + w0 + w1 + w2 + w3 + w4 + w5 + w6 + w7
            nearx = fx > 0.5 + 1e-3
            neary = fy > 0.5 + 1e-3
            nearz = fz > 0.5 + 1e-3
            cell = ((min(max(bx + nearx, 0), r - 1) * r + min(max(by + neary, 0), r - 1)) * r
                    + min(max(bz + nearz, 0), r - 1))
            # Visibility factor per axis of the corner at +0 / +1: the step from the nearest
            # cell to it is -1, 0 or +1.
            ax0 = np.float64(vis[1, cell]) if nearx else 1.0
            ax1 = 1.0 if nearx else np.float64(vis[0, cell])
            ay0 = np.float64(vis[3, cell]) if neary else 1.0
            ay1 = 1.0 if neary else np.float64(vis[2, cell])
            az0 = np.float64(vis[5, cell]) if nearz else 1.0
            az1 = 1.0 if nearz else np.float64(vis[4, cell])
            a00 = ax0 * ay0
            a01 = ax0 * ay1
            a10 = ax1 * ay0
            a11 = ax1 * ay1
            s0 = w0 * (a00 * az0)
            s1 = w1 * (a00 * az1)
            s2 = w2 * (a01 * az0)
            s3 = w3 * (a01 * az1)
            s4 = w4 * (a10 * az0)
            s5 = w5 * (a10 * az1)
            s6 = w6 * (a11 * az0)
            s7 = w7 * (a11 * az1)
            total = 0.0 + s0 + s1 + s2 + s3 + s4 + s5 + s6 + s7
            if total > 0.0:  # else every corner is hidden: plain trilinear weights
                scale = total_w / total
                w0 = s0 * scale
                w1 = s1 * scale
                w2 = s2 * scale
                w3 = s3 * scale
                w4 = s4 * scale
                w5 = s5 * scale
                w6 = s6 * scale
                w7 = s7 * scale
        # Cosine lobe x flux / pi: per colour (c0, -c1 y, c1 z, -c1 x).
        l1 = c1 * -ny
        l2 = c1 * nz
        l3 = c1 * -nx
        fr = flux[i, 0] / np.pi
        fg = flux[i, 1] / np.pi
        fb = flux[i, 2] / np.pi
        v0 = fr * c0
        v1 = fr * l1
        v2 = fr * l2
        v3 = fr * l3
        v4 = fg * c0
        v5 = fg * l1
        v6 = fg * l2
        v7 = fg * l3
        v8 = fb * c0
        v9 = fb * l1
        v10 = fb * l2
        v11 = fb * l3
        j = np.uint64((bx * r + by) * r + bz)  # corner 0 (only used for corners inside)
        if i0:
            _splat_add(acc, j, w0, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        if i1:
            _splat_add(acc, j + 1, w1, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        if i2:
            _splat_add(acc, j + r, w2, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        if i3:
            _splat_add(acc, j + r + 1, w3, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        if i4:
            _splat_add(acc, j + rr, w4, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        if i5:
            _splat_add(acc, j + rr + 1, w5, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        if i6:
            _splat_add(acc, j + rr + r, w6, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        if i7:
            _splat_add(acc, j + rr + r + 1, w7, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10,
                       v11)
