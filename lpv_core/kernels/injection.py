"""Compiled VPL injection: the twin of injection.inject (kernels/__init__.py).

Per VPL the same float64 arithmetic as the numpy reference (injection.trilinear_corners,
injection.visible_corners, sh.cosine_lobe x flux / pi), in its order, so the grid comes out
bit for bit the same; the sums are float64 per cell.
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..grid import Grid
from ..runtime import jit, pool

_C0, _C1 = sh.C0, sh.C1  # sh.cosine_lobe's constants, as plain globals for the kernel
# From SPLIT_MIN VPLs the compiled splat runs on two threads. On grids of up to SPLIT_CELLS
# cells each takes half of the VPLs into float64 sums of its own (<= 393 KiB), added at the
# end; on larger grids each adds only the corners in its own slab of one sum grid
# (split_slabs): a second 3 MiB of sums costs more than the threads save, and every cell
# still sums its VPLs in VPL order.
SPLIT_MIN = 8192
SPLIT_CELLS = 16 ** 3
SAMPLE_STEP = 16  # split_slabs histograms every 16th VPL: enough to balance the halves
MAX_SHARE = 0.85  # a cut leaving more VPLs on one side than this is not worth a thread


def inject(grid: Grid, positions: np.ndarray, normals: np.ndarray, flux: np.ndarray,
           offset_cells: float = 0.5, visibility: np.ndarray | None = None,
           index: np.ndarray | None = None) -> np.ndarray:
    """injection.inject of at least one VPL through _splat_kernel: the same arithmetic as the
    numpy reference, into float64 sums; ``index`` rows are read in place. Only the cells a VPL
    reaches are summed and converted (``touched``): on a 32^3 grid the dense float64 grid's
    zeroing and reading cost more than the splat of a few thousand VPLs."""
    pos = np.ascontiguousarray(positions, np.float64)
    nrm = np.ascontiguousarray(normals, np.float64)
    phi = np.ascontiguousarray(flux, np.float64)
    r = grid.resolution
    cells = r ** 3
    use_vis = visibility is not None
    vis = (np.ascontiguousarray(visibility).reshape(6, cells) if use_vis
           else np.ones((6, 1), np.float32))
    origin, cell_size = grid.origin_array, float(grid.cell_size)
    shift = float(offset_cells * grid.cell_size)
    rows = (np.zeros(0, np.int64) if index is None
            else np.ascontiguousarray(index, np.int64))  # empty: every row, in order
    n = pos.shape[0] if index is None else rows.shape[0]
    args = (pos, nrm, phi, rows, origin, cell_size, shift, r, vis, use_vis)
    out = np.empty(grid.shape(), np.float32)  # every cell written by _store_*_kernel
    flat = out.reshape(cells, 12)
    whole = np.array([[0, r], [0, r], [0, r]], np.int64)
    slabs = (split_slabs(pos, nrm, origin, cell_size, shift, r, rows)
             if n >= SPLIT_MIN and cells > SPLIT_CELLS else None)
    if n >= SPLIT_MIN and cells <= SPLIT_CELLS:
        _splat_halves(args, n, whole, flat)
    elif slabs is None:
        acc, touched = _sums(cells)
        _splat_box(args, n, acc, touched, cells, whole, flat)
    else:  # two slabs of one sum grid on two threads (the kernel releases the GIL)
        acc, touched = _sums(cells)
        job = pool.executor().submit(_splat_box, args, n, acc, touched, cells + 1, slabs[1], flat)
        _splat_box(args, n, acc, touched, cells, slabs[0], flat)
        job.result()
    return out


def _sums(cells: int) -> tuple[np.ndarray, np.ndarray]:
    """float64 sums (cells + 2 spare rows, 12), left unset (a row starts at its first touch),
    and their ``touched`` marks (uint8, all 0). The spare rows take corners a call skips."""
    return np.empty((cells + 2, 12), np.float64), np.zeros(cells + 2, np.uint8)


def _splat_box(args: tuple, n: int, acc, touched, spare: int, box, out) -> None:
    """All ``n`` VPLs' corners in ``box`` summed, then that box of ``out`` (R^3, 12) written."""
    _splat_kernel(*args, 0, n, acc, touched, spare, box)
    _store_box_kernel(acc, touched, box, args[7], out)


def _splat_halves(args: tuple, n: int, whole, out) -> None:
    """The VPLs in two halves on two threads (the kernel releases the GIL), each into sums of
    its own, ``out`` (R^3, 12) their sum."""
    cells = out.shape[0]
    (acc, touched), (acc2, touched2) = _sums(cells), _sums(cells)
    job = pool.executor().submit(_splat_kernel, *args, n // 2, n, acc2, touched2, cells, whole)
    _splat_kernel(*args, 0, n // 2, acc, touched, cells, whole)
    job.result()
    _store_sum_kernel(acc, touched, acc2, touched2, out)


def split_slabs(pos: np.ndarray, nrm: np.ndarray, origin: np.ndarray, cell_size: float,
                shift: float, r: int, rows: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """Two boxes of cells (3, 2) [lo, hi) per axis, halves of the grid across the axis that
    best balances the VPLs (``rows`` of pos, nrm; all if None or empty) splatting into each
    (a VPL whose corners straddle the cut is splatted by both, each adding its own corners);
    None when no cut leaves the larger side at most MAX_SHARE of the VPLs (one thread is then
    about as fast)."""
    rows = np.zeros(0, np.int64) if rows is None else np.asarray(rows, np.int64)
    axis, cut, larger = _best_cut_kernel(pos, nrm, rows, origin, cell_size, shift, r,
                                         SAMPLE_STEP)
    if cut < 1 or larger > MAX_SHARE:
        return None
    lo = np.array([[0, r], [0, r], [0, r]], np.int64)
    hi = lo.copy()
    lo[axis, 1] = cut
    hi[axis, 0] = cut
    return lo, hi


@jit.kernel
def _best_cut_kernel(pos, nrm, rows, origin, cell_size, shift, r, step):
    """(axis, cut, share): the cell plane ``cut`` across ``axis`` (0..2) that minimises the
    larger share of every ``step``-th VPL (of ``rows``; all if empty) splatting on either side
    (base cell below the cut, or its upper corner at or above it); cut 0 when no VPL lands in
    the grid."""
    counts = np.zeros((3, r + 1), np.int64)  # VPLs per base cell -1..r-1, per axis
    top = r - 1.0
    total = 0
    indexed = rows.shape[0] > 0
    for k in range(0, rows.shape[0] if indexed else pos.shape[0], step):
        i = rows[k] if indexed else k
        fx = np.floor((pos[i, 0] + nrm[i, 0] * shift - origin[0]) / cell_size - 0.5)
        fy = np.floor((pos[i, 1] + nrm[i, 1] * shift - origin[1]) / cell_size - 0.5)
        fz = np.floor((pos[i, 2] + nrm[i, 2] * shift - origin[2]) / cell_size - 0.5)
        if (fx >= -1.0) & (fx <= top) & (fy >= -1.0) & (fy <= top) & (fz >= -1.0) & (fz <= top):
            total += 1
            counts[0, np.int64(fx) + 1] += 1
            counts[1, np.int64(fy) + 1] += 1
            counts[2, np.int64(fz) + 1] += 1
    if total == 0:
        return 0, 0, 1.0
    best_axis, best_cut, best = 0, 0, total + 1
    for a in range(3):
        below = 0  # base cells up to cut - 1: corners below the cut
        for cut in range(1, r):
            below += counts[a, cut]  # base cell cut - 1 straddles the cut: counted on both
            larger = max(below, total - below + counts[a, cut])
            if larger < best:
                best_axis, best_cut, best = a, cut, larger
    return best_axis, best_cut, best / total


if jit.numba is not None:  # the 4-wide add of the splat kernel, as LLVM vector code
    from llvmlite import ir as _ir
    from numba.core import types as _types
    from numba.extending import intrinsic as _intrinsic

    @_intrinsic
    def _axpy4(typingctx, acc, at, w, a, b, c, d):
        """acc.flat[at:at + 4] += w x (a, b, c, d) as one 4-wide multiply and one add: the
        scalar products and sums bit for bit, which numba leaves scalar (its LLVM SLP
        vectoriser is off).
        ``acc``: a C-contiguous float64 array."""
        sig = _types.void(acc, at, w, a, b, c, d)

        def codegen(context, builder, signature, args):
            data = context.make_array(signature.args[0])(context, builder, args[0]).data
            vty = _ir.VectorType(_ir.DoubleType(), 4)
            ptr = builder.bitcast(builder.gep(data, [args[1]]), vty.as_pointer())
            vec = wv = _ir.Constant(vty, _ir.Undefined)
            for k in range(4):
                lane = _ir.Constant(_ir.IntType(32), k)
                vec = builder.insert_element(vec, args[3 + k], lane)
                wv = builder.insert_element(wv, args[2], lane)
            total = builder.fadd(builder.load(ptr, align=8), builder.fmul(wv, vec))
            builder.store(total, ptr, align=8)
            return context.get_dummy_value()

        return sig, codegen
else:  # pragma: no cover - without numba no kernel runs
    def _axpy4(acc, at, w, a, b, c, d):
        acc.flat[at:at + 4] += w * np.array([a, b, c, d])


@jit.kernel
def _splat_add(acc, j, wk, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11):
    """acc[j] += wk x (v0..v11): one corner's 12 sums, as three 4-wide adds."""
    at = j * 12
    _axpy4(acc, at, wk, v0, v1, v2, v3)
    _axpy4(acc, at + 4, wk, v4, v5, v6, v7)
    _axpy4(acc, at + 8, wk, v8, v9, v10, v11)


@jit.kernel
def _claim(acc, touched, j):
    """Row j of ``acc`` zeroed (its sums start at 0.0, as numpy's bincount sums do) unless
    ``touched`` says it holds sums already; marked touched."""
    if not touched[j]:
        touched[j] = 1
        for c in range(12):
            acc[j, c] = 0.0


@jit.kernel
def _store_box_kernel(acc, touched, box, r, out):
    """``out`` (R^3, 12) float32 of the cells in ``box``: their sums where touched, else 0."""
    for x in range(box[0, 0], box[0, 1]):
        for y in range(box[1, 0], box[1, 1]):
            row = (x * r + y) * r
            for j in range(row + box[2, 0], row + box[2, 1]):
                if touched[j]:
                    for c in range(12):
                        out[j, c] = np.float32(acc[j, c])
                else:
                    for c in range(12):
                        out[j, c] = np.float32(0.0)


@jit.kernel
def _store_sum_kernel(acc, touched, acc2, touched2, out):
    """``out`` (R^3, 12) float32: the two threads' sums of each cell added (0 where neither
    touched it)."""
    for j in range(out.shape[0]):
        if touched[j] and touched2[j]:
            for c in range(12):
                out[j, c] = np.float32(acc[j, c] + acc2[j, c])
        elif touched[j]:
            for c in range(12):
                out[j, c] = np.float32(acc[j, c])
        elif touched2[j]:
            for c in range(12):
                out[j, c] = np.float32(acc2[j, c])
        else:
            for c in range(12):
                out[j, c] = np.float32(0.0)


@jit.kernel
def _splat_kernel(pos, nrm, flux, rows, origin, cell_size, shift, r, vis, use_vis, lo, hi,
                  acc, touched, spare, box):
    """The corners inside ``box`` (3, 2) [lo, hi) cells per axis of VPLs lo..hi-1 (of ``rows``
    of pos, nrm, flux, in order; of all if empty) summed in ``acc`` (R^3 + spare rows, 12)
    float64: trilinear_corners, visible_corners (same tie tolerance, clip and all-hidden rule)
    and the cosine lobe x flux / pi, per VPL.
    ``touched`` (uint8 per row of ``acc``) marks the rows summed so far; the others hold
    garbage. Rows are claimed (_claim) once per base cell of the VPLs, so the adds themselves
    stay branch-free.

    A VPL with all 8 corners outside the grid (or a non-finite position) adds nothing, as its
    zero weights do in numpy; it is skipped before its cell index is made an integer. Corners
    outside go to the row ``spare`` of ``acc`` (numpy adds 0 x value to cell 0: the same
    unless flux is inf/NaN), so the 8 adds need no branches. Everything per VPL is a scalar
    (corner k = 4 dx + 2 dy + dz), so it stays in registers; each product and sum is the
    numpy path's, in its order (the same float64 bits)."""
    c0 = _C0
    c1 = _C1
    top = r - 1.0
    rr = r * r
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    xlo, xhi, ylo, yhi, zlo, zhi = box[0, 0], box[0, 1], box[1, 0], box[1, 1], box[2, 0], box[2, 1]
    ready = np.zeros((r + 1) ** 3, np.uint8)  # per base cell -1..r-1: its corners claimed
    indexed = rows.shape[0] > 0
    for k in range(lo, hi):
        i = rows[k] if indexed else k
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
        # Corners this call adds, per axis and side: inside ``box`` (which lies in the grid).
        ex0 = (bx >= xlo) & (bx < xhi)
        ex1 = (bx + 1 >= xlo) & (bx + 1 < xhi)
        ey0 = (by >= ylo) & (by < yhi)
        ey1 = (by + 1 >= ylo) & (by + 1 < yhi)
        ez0 = (bz >= zlo) & (bz < zhi)
        ez1 = (bz + 1 >= zlo) & (bz + 1 < zhi)
        if not ((ex0 | ex1) & (ey0 | ey1) & (ez0 | ez1)):
            continue
        fx = cx - fbx
        fy = cy - fby
        fz = cz - fbz
        gx = 1.0 - fx
        gy = 1.0 - fy
        gz = 1.0 - fz
        # Corner inside the grid per axis and side (b >= -1 and b <= r - 1 hold here).
        x0 = bx >= 0
        x1 = bx < r - 1
        y0 = by >= 0
        y1 = by < r - 1
        z0 = bz >= 0
        z1 = bz < r - 1
        w00 = gx * gy
        w01 = gx * fy
        w10 = fx * gy
        w11 = fx * fy
        w0 = w00 * gz if x0 & y0 & z0 else 0.0
        w1 = w00 * fz if x0 & y0 & z1 else 0.0
        w2 = w01 * gz if x0 & y1 & z0 else 0.0
        w3 = w01 * fz if x0 & y1 & z1 else 0.0
        w4 = w10 * gz if x1 & y0 & z0 else 0.0
        w5 = w10 * fz if x1 & y0 & z1 else 0.0
        w6 = w11 * gz if x1 & y1 & z0 else 0.0
        w7 = w11 * fz if x1 & y1 & z1 else 0.0
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
        # Corner k's row when inside the grid and ``box``, else the spare row.
        j = (bx * r + by) * r + bz
        t0 = j if ex0 & ey0 & ez0 else spare
        t1 = j + 1 if ex0 & ey0 & ez1 else spare
        t2 = j + r if ex0 & ey1 & ez0 else spare
        t3 = j + r + 1 if ex0 & ey1 & ez1 else spare
        t4 = j + rr if ex1 & ey0 & ez0 else spare
        t5 = j + rr + 1 if ex1 & ey0 & ez1 else spare
        t6 = j + rr + r if ex1 & ey1 & ez0 else spare
        t7 = j + rr + r + 1 if ex1 & ey1 & ez1 else spare
        base = ((bx + 1) * (r + 1) + by + 1) * (r + 1) + bz + 1
        if not ready[base]:  # the first VPL on this base cell: start its corners' sums
            ready[base] = 1
            _claim(acc, touched, t0)
            _claim(acc, touched, t1)
            _claim(acc, touched, t2)
            _claim(acc, touched, t3)
            _claim(acc, touched, t4)
            _claim(acc, touched, t5)
            _claim(acc, touched, t6)
            _claim(acc, touched, t7)
        _splat_add(acc, t0, w0, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        _splat_add(acc, t1, w1, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        _splat_add(acc, t2, w2, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        _splat_add(acc, t3, w3, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        _splat_add(acc, t4, w4, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        _splat_add(acc, t5, w5, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        _splat_add(acc, t6, w6, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
        _splat_add(acc, t7, w7, v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
