"""Geometry volume: how much of each LPV cell face is covered by occluders [KD10 sec. 5].

KD10 stores a blocking potential B(w) = A_s <n_s, w>_+ / s^2 per cell of a grid offset by half
a cell, injected from RSM and camera-depth surfels. We build it from the occluding triangles
themselves (complete, not limited to what a light or the camera sees) and keep it where
propagation needs it: on the faces between cells. The triangles are cut into sub-triangles at
most half a cell long; each belongs to the face plane nearest its centroid along each axis (the
slab of the surface that plane stands for) and is projected onto it (surfaces block from both
sides). A face's blocking is the fraction of it covered by the *union* of those projections,
measured at M x M sample points per face (COVERAGE_SAMPLES). A union, not a sum: a surface
duplicated in place, or two coplanar overlapping ones (a decal, z-fighting copies), block
once, as Cycles renders them once; the two sides of a thin wall, both near one plane, cover the
face once. And the coverage ends where the occluder ends: a wall whose edge lies on a face
boundary leaves the next face open and closes its own completely (a bilinear splat of surfel
areas smeared ~12 % of a wall's edge faces' blocking onto the faces beside them, and let light
out of a closed crate at its edges). The transmittance 1 - B per face becomes the propagation
``visibility`` (6, R, R, R).

Where numba is installed (jit.py), _subdivide, face_coverage, face_offsets and occluder_volume
run compiled kernels that repeat the numpy arithmetic and give the same bits (occluder_volume
on the Cornell box, on 2 shared cores: about 40 -> 3 ms at R = 16, 150 -> 7 ms at R = 32).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from . import jit
from .grid import Grid

# Sample points per face edge: 8, a quarter of a sub-triangle's length (SURFEL_SPACING), so that
# even a sub-triangle's thin projection (a surface nearly edge-on to the plane) is sampled
# across and a face's blocking is resolved in steps of 1/64. Measured on the two-room leak test
# (tests/test_lpv_core.py, a 0.2 m wall, 1/3 of a cell): 2 and 4 samples per edge let
# 0.95 % and 1.02 % through (coarse coverage of the faces where the wall meets floor and
# roof), 8 lets 0.76 % through. The samples sit at odd multiples of 1/16 cell, off the cell and
# half-cell lines where fitted scene bounds and walls usually lie.
COVERAGE_SAMPLES = 8
SURFEL_SPACING = 0.5  # sub-triangle length, in cells


def _subdivide(positions: np.ndarray, spacing: float):
    """Sub-triangles (N, 3, 3) of triangles (T, 3, 3), each at most ``spacing`` long (up to a
    64 x 64 split per triangle), and the triangle each came from (N,), its unit normal (N, 3)
    and its area (N,). A triangle gets k^2 equal sub-triangles (k from its longest edge): exact
    area, even coverage, no randomness."""
    p = np.asarray(positions, np.float64).reshape(-1, 3, 3)
    if p.shape[0] == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    if jit.enabled():
        return _subdivide_compiled(p, *_splits_compiled(p, spacing))
    normal, area2, k = _splits(p, spacing)
    out_t, out_i, out_n, out_a = [], [], [], []
    for kk in np.unique(k):
        sel = np.nonzero(k == kk)[0]
        corners = _sub_corners(int(kk))  # (kk^2, 3 corners, 3 barycentric)
        out_t.append(np.einsum("scb,tbx->tscx", corners, p[sel]).reshape(-1, 3, 3))
        n_sub = corners.shape[0]
        out_i.append(np.repeat(sel, n_sub))
        out_n.append(np.repeat(normal[sel], n_sub, axis=0))
        out_a.append(np.repeat(0.5 * area2[sel] / n_sub, n_sub))
    return (np.concatenate(out_t), np.concatenate(out_i), np.concatenate(out_n),
            np.concatenate(out_a))


def _splits(p: np.ndarray, spacing: float):
    """Per triangle of ``p`` (T, 3, 3): unit normal (T, 3), twice the area (T,) and k (T,),
    the sub-triangles along each edge (_subdivide, both paths)."""
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    cross = np.cross(e1, e2)
    area2 = np.linalg.norm(cross, axis=1)
    normal = cross / np.where(area2 > 0, area2, 1.0)[:, None]
    longest = np.max(np.linalg.norm(np.stack([e1, e2, p[:, 2] - p[:, 1]], 1), axis=2), axis=1)
    # (an edge that is an exact multiple of the spacing must not get one more split by rounding)
    k = np.clip(np.ceil(longest / max(spacing, 1e-30) - 1e-6), 1, 64).astype(np.int64)
    return normal, area2, k


def _splits_compiled(p: np.ndarray, spacing: float):
    """_splits by _splits_kernel: the same normals, areas and k (0 where numpy's is no count:
    a non-finite triangle), without numpy's dozen small calls (0.2 ms)."""
    t = p.shape[0]
    normal = np.empty((t, 3))
    area2 = np.empty(t)
    k = np.empty(t, np.int64)
    _splits_kernel(np.ascontiguousarray(p), max(spacing, 1e-30), normal, area2, k)
    return normal, area2, k


def _subdivide_compiled(p: np.ndarray, normal: np.ndarray, area2: np.ndarray, k: np.ndarray):
    """_subdivide through _subdivide_kernel: the same sub-triangles in the same order (grouped
    by k, ascending, then by triangle), written straight into the output arrays (no per-k
    einsum and repeats: 12 -> 0.4 ms on the Cornell box at R = 16)."""
    k = np.where(k >= 1, k, 0)  # (a non-finite triangle: none, where numpy's path would fail)
    order = np.argsort(k, kind="stable")  # np.unique's groups, each in triangle order
    count = k[order] ** 2
    start = np.cumsum(count) - count
    n = int(count.sum())
    sub = np.empty((n, 3, 3))
    index = np.empty(n, np.int64)
    nrm = np.empty((n, 3))
    area = np.empty(n)
    _subdivide_kernel(p, order, k, start, np.ascontiguousarray(normal), area2, sub, index, nrm,
                      area)
    return sub, index, nrm, area


def _sub_corners(k: int) -> np.ndarray:
    """Barycentric corners (k^2, 3, 3) of the k^2 equal sub-triangles of a triangle, in the
    order of their centroids in the original surfel sampling (upright, then its inverted
    neighbour)."""
    tris = []
    for i in range(k):
        for j in range(k - i):
            a, b, c = (i, j), (i + 1, j), (i, j + 1)
            tris.append((a, b, c))  # upright: centroid ((i + 1/3) / k, (j + 1/3) / k)
            if i + j < k - 1:
                tris.append((b, (i + 1, j + 1), c))  # inverted: centroid (i + 2/3, j + 2/3)/k
    uv = np.array(tris, np.float64) / k  # (k^2, 3, 2)
    return np.concatenate([1.0 - uv.sum(-1, keepdims=True), uv], axis=-1)


def surfels(positions: np.ndarray, spacing: float, with_index: bool = False):
    """Sample triangles (T, 3, 3) into surfels at most ``spacing`` apart.

    Returns centres (N, 3), unit normals (N, 3) and areas (N,) that add up to each triangle's
    area (and, ``with_index``, each surfel's triangle (N,)): the centroids of _subdivide's
    sub-triangles.
    """
    sub, index, normal, area = _subdivide(positions, spacing)
    result = (sub.mean(axis=1), normal, area)
    return result + (index,) if with_index else result


def face_coverage(grid: Grid, sub_triangles: np.ndarray, samples: int = COVERAGE_SAMPLES):
    """(3, R + 1, R, R) fraction of each face plane's faces [axis, plane, u cell, v cell]
    covered by the union of the projections of the sub-triangles (N, 3, 3) nearest to it.

    A sample point counts as covered when it lies in (or on the edge of: no cracks between
    the triangles of a mesh) the projection of a sub-triangle assigned to that plane.
    """
    r = grid.resolution
    m = int(samples)
    out = np.zeros((3, r + 1, r, r))
    tri = np.asarray(sub_triangles, np.float64).reshape(-1, 3, 3)
    if tri.shape[0] == 0:
        return out
    if jit.enabled():
        return _coverage_compiled(grid, tri, m, out)
    rel = (tri - grid.origin_array) / grid.cell_size  # cell units
    centroid = (rel[:, 0] + rel[:, 1] + rel[:, 2]) / 3.0
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        # Nearest plane; a sub-triangle half-way between two (common by construction) goes to
        # the lower one whatever the rounding, so scaling or moving the scene changes nothing.
        plane = np.floor(centroid[:, axis] + 0.5 - 1e-6).astype(np.int64)
        # Projected corners in sample units: sample j of the plane sits at (j + 0.5) / m cells.
        pu = rel[:, :, u] * m - 0.5
        pv = rel[:, :, v] * m - 0.5
        area2 = ((pu[:, 1] - pu[:, 0]) * (pv[:, 2] - pv[:, 0])
                 - (pv[:, 1] - pv[:, 0]) * (pu[:, 2] - pu[:, 0]))
        lo_u, hi_u = _min3(pu), _max3(pu)
        lo_v, hi_v = _min3(pv), _max3(pv)
        span = np.maximum(hi_u - lo_u, hi_v - lo_v)
        # Edge-on to this plane (no projected area) or outside the grid's planes: no cover.
        keep = ((np.abs(area2) > 1e-9 * np.maximum(span, 1.0) ** 2)
                & (plane >= 0) & (plane <= r))
        if not keep.any():
            continue
        pu, pv, area2, plane = pu[keep], pv[keep], area2[keep], plane[keep]
        lo_u, hi_u, lo_v, hi_v = lo_u[keep], hi_u[keep], lo_v[keep], hi_v[keep]
        sign = np.sign(area2)
        # Edge functions (inside >= 0) of edge i (corner i -> i + 1), times the orientation so
        # the test holds for either winding; the tolerance, relative to each edge's length,
        # puts points on a shared edge in both triangles (no cracks).
        edges = []
        for i in range(3):
            a_u, a_v = pu[:, i], pv[:, i]
            d_u = (pu[:, (i + 1) % 3] - a_u) * sign
            d_v = (pv[:, (i + 1) % 3] - a_v) * sign
            edges.append((a_u, a_v, d_u, d_v, -1e-9 * np.hypot(d_u, d_v)))
        j0 = np.ceil(lo_u - 1e-9).astype(np.int64)
        l0 = np.ceil(lo_v - 1e-9).astype(np.int64)
        width = int(np.max(np.floor(hi_u + 1e-9) - j0, initial=0)) + 1
        height = int(np.max(np.floor(hi_v + 1e-9) - l0, initial=0)) + 1
        hit = np.zeros((r + 1, r * m, r * m), bool)
        for dj in range(width):
            ju = j0 + dj
            for dl in range(height):
                lv = l0 + dl
                inside = (ju >= 0) & (ju < r * m) & (lv >= 0) & (lv < r * m)
                for a_u, a_v, d_u, d_v, tol in edges:
                    inside &= d_u * (lv - a_v) - d_v * (ju - a_u) >= tol
                hit[plane[inside], ju[inside], lv[inside]] = True
        out[axis] = hit.reshape(r + 1, r, m, r, m).mean(axis=(2, 4))
    return out


def _min3(a: np.ndarray) -> np.ndarray:
    return np.minimum(np.minimum(a[:, 0], a[:, 1]), a[:, 2])


def _max3(a: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])


def _transmittance(grid: Grid, coverage: np.ndarray) -> np.ndarray:
    """(6, R, R, R) per-cell transmittance (AXES order) from face_coverage (3, R + 1, R, R)."""
    r = grid.resolution
    trans = 1.0 - coverage
    vis = np.empty((6, r, r, r), np.float32)
    for axis in range(3):
        t = np.moveaxis(trans[axis], 0, axis)  # plane index along the grid axis
        hi = [slice(None)] * 3
        lo = [slice(None)] * 3
        hi[axis] = slice(1, None)  # +axis from cell i crosses plane i + 1
        lo[axis] = slice(0, -1)  # -axis from cell i crosses plane i
        vis[2 * axis] = t[tuple(hi)]
        vis[2 * axis + 1] = t[tuple(lo)]
    return vis


def face_offsets(grid: Grid, sub_triangles: np.ndarray, normals: np.ndarray,
                 areas: np.ndarray) -> np.ndarray:
    """(3, R + 1, R, R) mean signed distance, in cells, from each face plane to the occluding
    surface face_coverage put on it (weighted by projected area; 0 where none): where the
    surface really is, in [-1/2, 1/2] of a cell around the plane that stands for it."""
    r = grid.resolution
    out = np.zeros((3, r + 1, r, r))
    tri = np.asarray(sub_triangles, np.float64).reshape(-1, 3, 3)
    if tri.shape[0] == 0:
        return out
    if jit.enabled():
        total = np.zeros((3, r + 1, r, r))
        moment = np.zeros((3, r + 1, r, r))
        _offsets_kernel(np.ascontiguousarray(tri), np.ascontiguousarray(normals, np.float64),
                        np.ascontiguousarray(areas, np.float64), grid.origin_array,
                        float(grid.cell_size), r, total, moment)
        return np.divide(moment, total, out=out, where=total > 0)
    centroid = ((tri - grid.origin_array) / grid.cell_size).mean(axis=1)
    cells = (r + 1) * r * r
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        plane = np.floor(centroid[:, axis] + 0.5 - 1e-6).astype(np.int64)  # as face_coverage
        iu = np.floor(centroid[:, u]).astype(np.int64)
        iv = np.floor(centroid[:, v]).astype(np.int64)
        w = areas * np.abs(normals[:, axis])
        ok = ((plane >= 0) & (plane <= r) & (iu >= 0) & (iu < r) & (iv >= 0) & (iv < r)
              & (w > 0))
        flat = (plane[ok] * r + iu[ok]) * r + iv[ok]
        total = np.bincount(flat, weights=w[ok], minlength=cells)
        moment = np.bincount(flat, weights=(w * (centroid[:, axis] - plane))[ok],
                             minlength=cells)
        out[axis] = np.divide(moment, total, out=np.zeros(cells), where=total > 0).reshape(
            r + 1, r, r)
    return out


def cell_gaps(grid: Grid, coverage: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(6, R, R, R) per cell and face (AXES order): how deep, in cells, the slab between a
    blocked face and the surface it stands for reaches into the cell (0: none).

    A surface is put on its nearest face plane, up to half a cell from where it is. When a
    ceiling 0.3 cells above a plane is put on it, the 0.3 cells of the cell above the plane,
    below the real ceiling, are room air on the wrong side of the LPV's ceiling: a receiver on
    a wall there would read the dark cell above (a black seam along every such edge).
    lookup.gap_corrected moves sample points out of these slabs."""
    r = grid.resolution
    gaps = np.zeros((6, r, r, r), np.float32)
    blocked = coverage > 0.5  # mostly covered: the face stands for the surface there
    for axis in range(3):
        d = np.where(blocked[axis], offsets[axis], 0.0)
        up = np.moveaxis(np.maximum(d, 0.0), 0, axis)  # surface above plane i: cell i's slab
        down = np.moveaxis(np.maximum(-d, 0.0), 0, axis)  # below plane i + 1: cell i's slab
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis] = slice(0, -1)
        hi[axis] = slice(1, None)
        gaps[2 * axis + 1] = up[tuple(lo)]  # from cell i's lower face (plane i) upwards
        gaps[2 * axis] = down[tuple(hi)]  # from cell i's upper face (plane i + 1) down
    return gaps


def occluder_volume(grid: Grid, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(propagation visibility (6, R, R, R), cell_gaps (6, R, R, R)) of occluding triangles
    (T, 3, 3), cut into half-cell sub-triangles."""
    if jit.enabled():
        return _occluder_compiled(grid, np.ascontiguousarray(
            np.asarray(triangles, np.float64).reshape(-1, 3, 3)))
    sub, _, normal, area = _subdivide(triangles, SURFEL_SPACING * grid.cell_size)
    coverage = face_coverage(grid, sub)
    return (_transmittance(grid, coverage),
            cell_gaps(grid, coverage, face_offsets(grid, sub, normal, area)))


def face_transmittance(grid: Grid, triangles: np.ndarray) -> np.ndarray:
    """(6, R, R, R) fraction of light a cell sends across each of its faces (AXES order):
    1 - face_coverage of the occluding triangles (T, 3, 3), cut into half-cell sub-triangles."""
    sub = _subdivide(triangles, SURFEL_SPACING * grid.cell_size)[0]
    return _transmittance(grid, face_coverage(grid, sub))


def occluder_visibility(grid: Grid, triangles: np.ndarray) -> np.ndarray:
    """Propagation visibility (6, R, R, R) from occluding triangles (T, 3, 3)."""
    return face_transmittance(grid, triangles)


# Compiled kernels (jit.py): the numpy code above is the reference; these repeat its arithmetic
# operation for operation, one sub-triangle at a time, so the results are the same bits.
#
# Coverage in two passes. The first (_project_run) projects every sub-triangle onto its
# nearest plane across each axis and keeps those that cover something as records (plane,
# corners' u, v in sample units, twice the signed area), finding the largest sample window on
# the way. Then the planes, split into parts of about equal work (_parts), are scanned from the
# records on ordinates' pool threads (_cover_part: each part writes only its own planes' bits)
# and counted (_finish_coverage, or _finish_volume straight into the visibility and gaps).
# occluder_volume runs the first pass on the triangles themselves, in runs on the pool threads
# (_occluder_kernel): each one's sub-triangle corners computed once per lattice point, as
# _subdivide_kernel computes them, face_offsets' sums added on the way (no sub-triangle arrays,
# no second conversion to cell units, each projection computed once).
#
# Hot loops call no compiled function with array arguments (each such call counts references
# to its arrays: atomic operations that cost more than the work per sub-triangle).
# Against the kernels before (cell units and _projected computed twice, a serial window pass,
# one pool thread per axis, numpy glue), one process A/B on the Cornell box, 2 shared cores:
# occluder_volume 5.3 -> 2.7 ms at R = 16, 16 -> 7 ms at R = 32.

_RECORD = 8  # (plane, u0, u1, u2, v0, v1, v2, area2) per kept sub-triangle and axis


def _occluder_compiled(grid: Grid, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """occluder_volume by the compiled kernels: _occluder_kernel on runs of the triangles (in
    _subdivide's order) on the pool, then the planes' coverage, visibility and gaps in parts.

    face_offsets' sums add the sub-triangles' terms in their order: the first run adds its
    own; each later run logs them (face, weight, weighted distance), and each part adds the
    logged terms of its own planes after the first run's, run by run, in order."""
    from .ordinates import _pool, pool_workers

    r = grid.resolution
    m = COVERAGE_SAMPLES
    if p.shape[0] == 0:
        return np.ones((6, r, r, r), np.float32), np.zeros((6, r, r, r), np.float32)
    normal, area2, k = _splits_compiled(p, SURFEL_SPACING * grid.cell_size)
    pool = _pool()
    order, o, first, n = _runs(k, max(1, min(pool_workers(), p.shape[0])))
    runs = first.size
    rec = np.empty((3, n, _RECORD))
    nrec = np.zeros((runs, 3), np.int64)
    windows = np.zeros((runs, 3, 2))
    work = np.zeros((runs, 3 * (r + 1)), np.int64)
    total = np.zeros((3, r + 1, r, r))
    moment = np.zeros((3, r + 1, r, r))
    # runs i > 0 log up to 3 terms per sub-triangle, from column at[i]
    at = np.maximum(3 * (first - first[min(1, runs - 1)]), 0)
    logged = np.empty((3, 3 * (n - first[1]) if runs > 1 else 0))
    nlog = np.zeros(runs, np.int64)
    origin = grid.origin_array
    cell = float(grid.cell_size)

    def run(i):
        _occluder_kernel(p, order, k, o[i], o[i + 1], normal, area2, origin, cell, r, m, rec,
                         first[i], nrec[i], windows[i], work[i], total, moment, i > 0,
                         logged[:, at[i]:], nlog[i:i + 1])

    _in_parallel(pool, run, range(runs))
    hit = np.zeros((3, r + 1, r, r, (m * m + 63) // 64), np.int64)
    vis = np.empty((6, r, r, r), np.float32)  # (every cell face is written: _finish_volume)
    gaps = np.empty((6, r, r, r), np.float32)
    window = np.zeros((3, 2))

    def part(b):
        for i in range(1, runs):
            _add_logged(logged[:, at[i]:], nlog[i], r, b[0], b[1], total, moment)
        _cover_part(rec, first, nrec, r, m, window, b[0], b[1], hit)
        _finish_volume(hit, m, r, total, moment, b[0], b[1], vis, gaps)

    _run_parts(pool, part, work, windows, r, window)
    return vis, gaps


def _coverage_compiled(grid: Grid, tri: np.ndarray, m: int, out: np.ndarray) -> np.ndarray:
    """face_coverage by the compiled kernels: _project_subs' records and window, then the
    planes' coverage in parts on the pool."""
    from .ordinates import _pool

    r = grid.resolution
    rec = np.empty((3, tri.shape[0], _RECORD))
    nrec = np.zeros((1, 3), np.int64)
    windows = np.zeros((1, 3, 2))
    work = np.zeros((1, 3 * (r + 1)), np.int64)
    _project_subs(np.ascontiguousarray(tri), grid.origin_array, float(grid.cell_size), r, m,
                  rec, nrec[0], windows[0], work[0])
    hit = np.zeros((3, r + 1, r, r, (m * m + 63) // 64), np.int64)
    first = np.zeros(1, np.int64)
    window = np.zeros((3, 2))

    def part(b):
        _cover_part(rec, first, nrec, r, m, window, b[0], b[1], hit)
        _finish_coverage(hit, m, r, b[0], b[1], out)

    _run_parts(_pool(), part, work, windows, r, window)
    return out


def _run_parts(pool, part, work: np.ndarray, windows: np.ndarray, r: int,
               window: np.ndarray) -> None:
    """part((b0, b1)) for the planes' parts (_parts, which also merges the runs' windows into
    ``window``), one per pool thread."""
    from .ordinates import pool_workers

    bounds = np.empty(pool_workers() + 1, np.int64)
    _parts(work, windows, r, bounds, window)
    _in_parallel(pool, part, list(itertools.pairwise(bounds)))


def _in_parallel(pool, fn, items) -> None:
    """fn(item) for each of items at once: the first on this thread (one thread handoff
    less, and this one works instead of waiting), the others on the pool's."""
    items = list(items)
    futures = [pool.submit(fn, item) for item in items[1:]]
    try:
        fn(items[0])
    finally:
        for future in futures:  # (all done before their arrays are let go)
            future.result()


@jit.kernel
def _runs(k, runs):
    """_subdivide's order of the triangles (by k, stable) cut into ``runs`` runs of about
    equal numbers of sub-triangles: (order, the runs' first triangles in it (runs + 1), their
    first sub-triangles (runs), the number of sub-triangles)."""
    order = np.argsort(k, kind="mergesort")
    end = np.cumsum(k[order] ** 2)  # sub-triangles up to each triangle's
    n = end[-1]
    o = np.empty(runs + 1, np.int64)
    first = np.zeros(runs, np.int64)
    o[0] = 0
    o[runs] = order.size
    for i in range(1, runs):
        o[i] = np.searchsorted(end, i * (n / runs), side="right")
        first[i] = end[o[i] - 1] if o[i] > 0 else 0
    return order, o, first, n


@jit.kernel
def _parts(work, windows, r, bounds, window):
    """Split the planes (3 (R + 1), axis-major: b = axis (R + 1) + plane) into len(bounds) - 1
    parts of about equal work, bounds[i] .. bounds[i + 1]: each plane's records (work, per
    run) times its axis's window, plus its faces' count. window: the largest of the runs'
    windows."""
    for i in range(windows.shape[0]):
        for axis in range(3):
            for d in range(2):
                window[axis, d] = max(window[axis, d], windows[i, axis, d])
    nb = work.shape[1]
    cost = np.empty(nb)
    for b in range(nb):
        axis = b // (r + 1)
        count = 0
        for i in range(work.shape[0]):
            count += work[i, b]
        cost[b] = count * (window[axis, 0] + 1.0) * (window[axis, 1] + 1.0) + 0.25 * r * r
    whole = cost.sum()
    parts = bounds.shape[0] - 1
    bounds[0] = 0
    b = 0
    acc = 0.0
    for i in range(1, parts):
        while b < nb and acc + 0.5 * cost[b] < whole * i / parts:
            acc += cost[b]
            b += 1
        bounds[i] = b
    bounds[parts] = nb


@jit.kernel
def _project_subs(tri, origin, cell, r, m, rec, nrec, window, work):
    """_project_run over the sub-triangles tri (N, 3, 3), their corners in cell units as
    face_coverage computes them: (tri - origin) / cell."""
    n = tri.shape[0]
    rel = np.empty((3 * n, 3))
    smp = np.empty((3 * n, 3))
    corners = np.empty((n, 3), np.int64)
    for s in range(n):
        for c in range(3):
            corners[s, c] = 3 * s + c
            for x in range(3):
                rel[3 * s + c, x] = (tri[s, c, x] - origin[x]) / cell
                smp[3 * s + c, x] = rel[3 * s + c, x] * m - 0.5
    none = np.zeros(0)
    _project_run(rel, smp, corners, n, r, rec, 0, nrec, window, work, none, none, none, False,
                 False, np.zeros((3, 0)), np.zeros(1, np.int64))


@jit.kernel
def _occluder_kernel(p, order, k, o0, o1, normal, area2, origin, cell, r, m, rec, first,
                     nrec_out, window_out, work_out, total, moment, log, logged, nlog_out):
    """occluder_volume's first pass over the triangles p[order[o0:o1]] (_subdivide's order,
    records from row first): _project_run over each one's k^2 sub-triangles as
    _subdivide_kernel cuts it, corners computed once per lattice point (i, j) / k, in cell
    units as face_coverage computes them, with their face_offsets terms (added to total and
    moment, or with ``log`` logged). Counts and window are kept here and written out at the
    end (runs on pool threads write next to each other)."""
    nrec = np.zeros(3, np.int64)
    window = np.zeros((3, 2))
    work = np.zeros(work_out.shape[0], np.int64)
    nlog = np.zeros(1, np.int64)
    kmax = 1
    for o in range(o0, o1):
        kmax = max(kmax, k[order[o]])
    rel = np.empty(((kmax + 1) * (kmax + 1), 3))
    smp = np.empty(((kmax + 1) * (kmax + 1), 3))
    corners = np.empty((kmax * kmax, 3), np.int64)
    wgt = np.empty(3)
    total_flat = total.reshape(-1)
    moment_flat = moment.reshape(-1)
    for o in range(o0, o1):
        t = order[o]
        kk = k[t]
        if kk < 1:
            continue
        for i in range(kk + 1):
            for j in range(kk + 1 - i):
                u = i / kk
                v = j / kk
                w = 1.0 - (u + v)
                q = i * (kk + 1) + j
                for x in range(3):
                    rel[q, x] = (w * p[t, 0, x] + u * p[t, 1, x] + v * p[t, 2, x]
                                 - origin[x]) / cell
                    smp[q, x] = rel[q, x] * m - 0.5
        s = 0
        for i in range(kk):
            for j in range(kk - i):
                q = i * (kk + 1) + j
                corners[s, 0] = q  # upright
                corners[s, 1] = q + kk + 1
                corners[s, 2] = q + 1
                s += 1
                if i + j < kk - 1:  # its inverted neighbour
                    corners[s, 0] = q + kk + 1
                    corners[s, 1] = q + kk + 2
                    corners[s, 2] = q + 1
                    s += 1
        a = 0.5 * area2[t] / (kk * kk)
        for x in range(3):
            wgt[x] = a * abs(normal[t, x])
        _project_run(rel, smp, corners, s, r, rec, first, nrec, window, work, wgt, total_flat,
                     moment_flat, True, log, logged, nlog)
    nrec_out[:] = nrec
    window_out[:] = window
    work_out[:] = work
    nlog_out[0] = nlog[0]


@jit.kernel
def _project_run(rel, smp, corners, count, r, rec, row, nrec, window, work, wgt, total, moment,
                 offsets, log, logged, nlog):
    """Sub-triangles corners[:count] (indices into rel: cell units, and smp: the same times m,
    minus 1/2: sample units) projected onto their nearest face planes across each axis, as
    face_coverage computes them: where one covers something (not edge-on, plane inside the
    grid), its record appended to rec[axis] (from row ``row``: nrec[axis] so far), the largest
    sample window (width, height) any needs grown in window[axis], its plane's record count in
    work. With ``offsets``, their face_offsets terms too (weight wgt[axis], centroid and plane
    as face_offsets computes them), added to total and moment (flat), or with ``log`` appended
    to logged ((face, weight, weighted distance), nlog[0] so far)."""
    cen = np.empty(3)
    for s in range(count):
        a = corners[s, 0]
        b = corners[s, 1]
        c = corners[s, 2]
        for x in range(3):
            cen[x] = (rel[a, x] + rel[b, x] + rel[c, x]) / 3.0
        for axis in range(3):
            plane = math.floor(cen[axis] + 0.5 - 1e-6)
            if not (plane >= 0.0 and plane <= r):
                continue
            u = 1 if axis == 0 else 0
            v = 1 if axis == 2 else 2
            u0 = smp[a, u]
            u1 = smp[b, u]
            u2 = smp[c, u]
            v0 = smp[a, v]
            v1 = smp[b, v]
            v2 = smp[c, v]
            area2, width, height = _projection(u0, u1, u2, v0, v1, v2)
            if area2 != 0.0:
                window[axis, 0] = max(window[axis, 0], width)
                window[axis, 1] = max(window[axis, 1], height)
                i = row + nrec[axis]
                nrec[axis] += 1
                rec[axis, i, 0] = plane
                rec[axis, i, 1] = u0
                rec[axis, i, 2] = u1
                rec[axis, i, 3] = u2
                rec[axis, i, 4] = v0
                rec[axis, i, 5] = v1
                rec[axis, i, 6] = v2
                rec[axis, i, 7] = area2
                work[axis * (r + 1) + np.int64(plane)] += 1
            if not (offsets and wgt[axis] > 0.0):  # (none across 2 axes from an aligned wall)
                continue
            w = wgt[axis]
            iu = math.floor(cen[u])
            iv = math.floor(cen[v])
            if iu >= 0.0 and iu < r and iv >= 0.0 and iv < r:
                face = ((axis * (r + 1) + np.int64(plane)) * r + np.int64(iu)) * r + np.int64(iv)
                d = w * (cen[axis] - plane)
                if log:
                    j = nlog[0]
                    nlog[0] = j + 1
                    logged[0, j] = face
                    logged[1, j] = w
                    logged[2, j] = d
                else:
                    total[face] += w
                    moment[face] += d


@jit.kernel
def _projection(u0, u1, u2, v0, v1, v2):
    """A sub-triangle's projection, corners (u, v) in sample units, onto a face plane inside
    the grid, as face_coverage tests it: (twice its signed area, 0.0 where it covers nothing
    (edge-on); the sample window (width, height) it needs)."""
    area2 = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    if area2 == 0.0:  # (most sub-triangles of an axis-aligned wall, across 2 of the 3 axes)
        return 0.0, 0.0, 0.0
    lo_u = min(u0, u1, u2)
    hi_u = max(u0, u1, u2)
    lo_v = min(v0, v1, v2)
    hi_v = max(v0, v1, v2)
    span = max(hi_u - lo_u, hi_v - lo_v)
    s = max(span, 1.0)
    if not abs(area2) > 1e-9 * (s * s):
        return 0.0, 0.0, 0.0
    return (area2, math.floor(hi_u + 1e-9) - math.ceil(lo_u - 1e-9),
            math.floor(hi_v + 1e-9) - math.ceil(lo_v - 1e-9))


@jit.kernel
def _add_logged(logged, n, r, b0, b1, total, moment):
    """The first n logged face_offsets terms (_project_run) of planes b0 <= b < b1 added to
    total and moment, in order."""
    total_flat = total.reshape(-1)
    moment_flat = moment.reshape(-1)
    for j in range(n):
        face = np.int64(logged[0, j])
        b = face // (r * r)
        if b >= b0 and b < b1:
            total_flat[face] += logged[1, j]
            moment_flat[face] += logged[2, j]


@jit.kernel
def _cover_part(rec, first, nrec, r, m, window, b0, b1, hit):
    """The samples covered on planes b0 <= b < b1 (_parts' numbering) by their records
    (_project_run; run h's from row first[h], nrec[h, axis] of them) as bits in hit (3, R + 1,
    R, R, words): face by face, its m x m samples in words of 64 (the union; 8x less memory
    than numpy's booleans, no pass over them).

    Each record's projection covers a sample inside its three edges (same edge functions and
    tolerances as face_coverage). Numpy scans every sub-triangle over the largest sample
    window any of them needs (window[axis]), from its own first sample; so does this, so that
    a sample just past a sliver's tip, inside all three edges' tolerance, counts there too.
    The edge functions' terms are the same products and differences, each computed once per
    window column (col: du (v - a_v)) or row (dv (u - a_u))."""
    rm = r * m
    col = np.empty((3, rm))
    col_word = np.empty(rm, np.int64)
    col_bit = np.empty(rm, np.int64)
    words = hit.shape[4]
    flat = hit.reshape(-1)
    runs = first.shape[0]
    for ah in range(3 * runs):
        axis = ah // runs
        h = ah - axis * runs
        lo = max(b0 - axis * (r + 1), 0)
        hi = min(b1 - axis * (r + 1), r + 1)
        if lo >= hi:
            continue
        width = window[axis, 0]
        height = window[axis, 1]
        for n in range(first[h], first[h] + nrec[h, axis]):
            plane = np.int64(rec[axis, n, 0])
            if plane < lo or plane >= hi:
                continue
            u0 = rec[axis, n, 1]
            u1 = rec[axis, n, 2]
            u2 = rec[axis, n, 3]
            v0 = rec[axis, n, 4]
            v1 = rec[axis, n, 5]
            v2 = rec[axis, n, 6]
            j0 = math.ceil(min(u0, u1, u2) - 1e-9)
            l0 = math.ceil(min(v0, v1, v2) - 1e-9)
            ja = max(j0, 0.0)
            jb = min(j0 + width, rm - 1.0)
            la = max(l0, 0.0)
            lb = min(l0 + height, rm - 1.0)
            if ja > jb or la > lb:
                continue
            sign = 1.0 if rec[axis, n, 7] > 0.0 else -1.0
            # edge i: corner i -> i + 1, oriented inside >= tolerance (relative to its length)
            du0, dv0 = (u1 - u0) * sign, (v1 - v0) * sign
            du1, dv1 = (u2 - u1) * sign, (v2 - v1) * sign
            du2, dv2 = (u0 - u2) * sign, (v0 - v2) * sign
            # The tolerances (-1e-9 x each edge's length) only decide a sample within their
            # reach of an edge (at most twice 1e-9 (|du| + |dv|)): computed (hypot) only then.
            reach0 = 2e-9 * (abs(du0) + abs(dv0))
            reach1 = 2e-9 * (abs(du1) + abs(dv1))
            reach2 = 2e-9 * (abs(du2) + abs(dv2))
            tol0 = tol1 = tol2 = 0.0
            exact = False
            lv = np.int64(la)
            cols = np.int64(lb) - lv + 1
            iv = lv // m  # (faces and samples in them counted on, not divided for)
            sv = lv - iv * m
            for q in range(cols):
                fv = float(lv + q)
                col[0, q] = du0 * (fv - v0)
                col[1, q] = du1 * (fv - v1)
                col[2, q] = du2 * (fv - v2)
                col_word[q] = iv * words  # (its face's first word in a row of faces)
                col_bit[q] = sv
                sv += 1
                if sv == m:
                    sv = 0
                    iv += 1
            start = np.int64(ja)
            iu = start // m
            su = start - iu * m
            for ju in range(start, np.int64(jb) + 1):
                fu = float(ju)
                row0 = dv0 * (fu - u0)
                row1 = dv1 * (fu - u1)
                row2 = dv2 * (fu - u2)
                row = su * m
                base = ((axis * (r + 1) + plane) * r + iu) * r * words
                su += 1
                if su == m:
                    su = 0
                    iu += 1
                # The row's bits gathered word by word in a register, each word written
                # once. The samples in are one run (each edge's test is monotonic along the
                # row, as rounding is): the row ends at the first one out after it.
                word = -1
                bits = 0
                entered = False
                for q in range(cols):
                    e0 = col[0, q] - row0
                    e1 = col[1, q] - row1
                    e2 = col[2, q] - row2
                    if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                        inside = True
                    elif e0 < -reach0 or e1 < -reach1 or e2 < -reach2:
                        inside = False
                    else:
                        if not exact:
                            tol0 = -1e-9 * math.hypot(du0, dv0)
                            tol1 = -1e-9 * math.hypot(du1, dv1)
                            tol2 = -1e-9 * math.hypot(du2, dv2)
                            exact = True
                        inside = e0 >= tol0 and e1 >= tol1 and e2 >= tol2
                    if inside:
                        bit = row + col_bit[q]
                        at = base + col_word[q] + (bit >> 6)
                        if at != word:
                            if bits:
                                flat[word] |= bits
                            word = at
                            bits = 0
                        bits |= np.int64(1) << (bit & 63)
                        entered = True
                    elif entered:
                        break
                if bits:
                    flat[word] |= bits


@jit.kernel
def _popcount(x):
    """Set bits of the int64 x (the arithmetic shifts' sign bits are masked off)."""
    x = x - ((x >> 1) & 0x5555555555555555)
    x = (x & 0x3333333333333333) + ((x >> 2) & 0x3333333333333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0F
    return (x * 0x0101010101010101) >> 56


@jit.kernel
def _finish_coverage(hit, m, r, b0, b1, out):
    """face_coverage (3, R + 1, R, R) of planes b0 <= b < b1: the mean over each face's m x m
    samples."""
    for b in range(b0, b1):
        axis = b // (r + 1)
        plane = b - axis * (r + 1)
        for iu in range(r):
            for iv in range(r):
                count = 0
                for word in range(hit.shape[4]):
                    count += _popcount(hit[axis, plane, iu, iv, word])
                out[axis, plane, iu, iv] = count / (m * m)


@jit.kernel
def _finish_volume(hit, m, r, total, moment, b0, b1, vis, gaps):
    """occluder_volume's visibility and gaps (6, R, R, R) across planes b0 <= b < b1, from
    their coverage and face_offsets' sums, as face_coverage, face_offsets, _transmittance and
    cell_gaps compute them (np.maximum(x, 0.0): x where x > 0 or NaN, else +0.0). Each plane
    is crossed by +axis from the cell below it (axis index plane - 1) and -axis from the cell
    above (plane)."""
    for b in range(b0, b1):
        axis = b // (r + 1)
        plane = b - axis * (r + 1)
        for iu in range(r):
            for iv in range(r):
                count = 0
                for word in range(hit.shape[4]):
                    count += _popcount(hit[axis, plane, iu, iv, word])
                w = total[axis, plane, iu, iv]
                if count == 0 and not w > 0.0:  # (most faces: nothing there)
                    trans = np.float32(1.0)
                    up = down = np.float32(0.0)
                else:
                    cover = count / (m * m)
                    trans = np.float32(1.0 - cover)
                    offset = moment[axis, plane, iu, iv] / w if w > 0.0 else 0.0
                    d = offset if cover > 0.5 else 0.0
                    up = np.float32(d if (d > 0.0 or math.isnan(d)) else 0.0)
                    down = np.float32(-d if (-d > 0.0 or math.isnan(d)) else 0.0)
                if plane >= 1:
                    if axis == 0:
                        vis[0, plane - 1, iu, iv] = trans
                        gaps[0, plane - 1, iu, iv] = down
                    elif axis == 1:
                        vis[2, iu, plane - 1, iv] = trans
                        gaps[2, iu, plane - 1, iv] = down
                    else:
                        vis[4, iu, iv, plane - 1] = trans
                        gaps[4, iu, iv, plane - 1] = down
                if plane < r:
                    if axis == 0:
                        vis[1, plane, iu, iv] = trans
                        gaps[1, plane, iu, iv] = up
                    elif axis == 1:
                        vis[3, iu, plane, iv] = trans
                        gaps[3, iu, plane, iv] = up
                    else:
                        vis[5, iu, iv, plane] = trans
                        gaps[5, iu, iv, plane] = up


@jit.kernel
def _splits_kernel(p, step, normal, area2, k):
    """_splits' outputs: the same differences, products and sums, in numpy's order (np.cross;
    np.linalg.norm adds the squares first to last), and roundings; step: max(spacing, 1e-30)."""
    e = np.empty((3, 3))  # edges p1 - p0, p2 - p0, p2 - p1
    for t in range(p.shape[0]):
        for x in range(3):
            e[0, x] = p[t, 1, x] - p[t, 0, x]
            e[1, x] = p[t, 2, x] - p[t, 0, x]
            e[2, x] = p[t, 2, x] - p[t, 1, x]
        c0 = e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1]
        c1 = e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2]
        c2 = e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0]
        a = math.sqrt((c0 * c0 + c1 * c1) + c2 * c2)
        area2[t] = a
        d = a if a > 0 else 1.0
        normal[t, 0] = c0 / d
        normal[t, 1] = c1 / d
        normal[t, 2] = c2 / d
        longest = 0.0
        nan = False
        for i in range(3):
            length = math.sqrt((e[i, 0] * e[i, 0] + e[i, 1] * e[i, 1]) + e[i, 2] * e[i, 2])
            nan = nan or math.isnan(length)
            longest = max(longest, length)
        # (an edge that is an exact multiple of the spacing must not get one more split)
        split = np.ceil(longest / step - 1e-6) if not nan else math.nan
        k[t] = 0 if math.isnan(split) else np.int64(min(max(split, 1.0), 64.0))


@jit.kernel
def _subdivide_kernel(p, order, k, start, normal, area2, sub, index, nrm, area):
    """_subdivide's outputs for triangles p[order] (the i-th from row start[i]): its k^2
    sub-triangles in _sub_corners' order, each with its triangle, normal and area."""
    for o in range(order.shape[0]):
        t = order[o]
        kk = k[t]
        a = 0.5 * area2[t] / (kk * kk)
        n = start[o]
        for i in range(kk):
            for j in range(kk - i):
                for inverted in range(2 if i + j < kk - 1 else 1):  # upright, its neighbour
                    for c in range(3):
                        # lattice corner (ci, cj): upright (i, j), (i + 1, j), (i, j + 1),
                        # inverted (i + 1, j), (i + 1, j + 1), (i, j + 1)
                        ci = i + (1 if c == 1 or (c == 0 and inverted == 1) else 0)
                        cj = j + (1 if c == 2 or (c == 1 and inverted == 1) else 0)
                        u = ci / kk
                        v = cj / kk
                        w = 1.0 - (u + v)
                        for x in range(3):
                            sub[n, c, x] = w * p[t, 0, x] + u * p[t, 1, x] + v * p[t, 2, x]
                    n += 1
        for row in range(start[o], n):
            index[row] = t
            for x in range(3):
                nrm[row, x] = normal[t, x]
            area[row] = a


@jit.kernel
def _offsets_kernel(tri, normals, areas, origin, cell, r, total, moment):
    """face_offsets' sums (3, R + 1, R, R): weight and weighted distance per face, added in
    sub-triangle order as its bincounts add them."""
    c = np.empty(3)
    for n in range(tri.shape[0]):
        for x in range(3):
            c[x] = ((tri[n, 0, x] - origin[x]) / cell + (tri[n, 1, x] - origin[x]) / cell
                    + (tri[n, 2, x] - origin[x]) / cell) / 3.0
        for axis in range(3):
            u = 1 if axis == 0 else 0
            v = 1 if axis == 2 else 2
            plane = math.floor(c[axis] + 0.5 - 1e-6)
            iu = math.floor(c[u])
            iv = math.floor(c[v])
            w = areas[n] * abs(normals[n, axis])
            if (plane >= 0.0 and plane <= r and iu >= 0.0 and iu < r and iv >= 0.0 and iv < r
                    and w > 0.0):
                face = (axis, np.int64(plane), np.int64(iu), np.int64(iv))
                total[face] += w
                moment[face] += w * (c[axis] - plane)
