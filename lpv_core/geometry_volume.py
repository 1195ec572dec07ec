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

Where numba is installed (jit.py), _subdivide, face_coverage and face_offsets run compiled
kernels that repeat the numpy arithmetic and give the same bits (occluder_volume on the Cornell
box, on 2 shared cores: about 40 -> 5 ms at R = 16, 150 -> 20 ms at R = 32).
"""

from __future__ import annotations

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
    normal, area2, k = _splits(p, spacing)
    if jit.enabled():
        return _subdivide_compiled(p, normal, area2, k)
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

def _coverage_compiled(grid: Grid, tri: np.ndarray, m: int, out: np.ndarray) -> np.ndarray:
    """face_coverage by the compiled kernels, on the corners in cell units computed once
    (_cell_units): the sample windows (_coverage_windows), then each axis's planes
    (_cover_axis) on ordinates' pool threads."""
    from .ordinates import _pool

    rel = np.empty(tri.shape)
    _cell_units(tri, grid.origin_array, float(grid.cell_size), rel)
    r = grid.resolution
    width, height = _coverage_windows(rel, r, m)
    for _ in _pool().map(lambda a: _cover_axis(rel, r, m, a, width[a], height[a], out[a]),
                         range(3)):
        pass
    return out


@jit.kernel
def _cell_units(tri, origin, cell, rel):
    """rel = (tri - origin) / cell, without numpy's temporaries (3.3 -> 1.1 ms for 66 000
    sub-triangles)."""
    for n in range(tri.shape[0]):
        for c in range(3):
            for x in range(3):
                rel[n, c, x] = (tri[n, c, x] - origin[x]) / cell


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
                _sub_triangle(p, t, kk, i, j, i + 1, j, i, j + 1, sub, n)  # upright
                n += 1
                if i + j < kk - 1:  # its inverted neighbour
                    _sub_triangle(p, t, kk, i + 1, j, i + 1, j + 1, i, j + 1, sub, n)
                    n += 1
        for row in range(start[o], n):
            index[row] = t
            for x in range(3):
                nrm[row, x] = normal[t, x]
            area[row] = a


@jit.kernel
def _sub_triangle(p, t, k, i0, j0, i1, j1, i2, j2, sub, n):
    """sub[n] = the sub-triangle of p[t] with lattice corners (i, j) / k: barycentric
    (1 - (u + v), u, v) as _sub_corners makes them, summed as the einsum sums them."""
    for c in range(3):
        ci = i0 if c == 0 else (i1 if c == 1 else i2)
        cj = j0 if c == 0 else (j1 if c == 1 else j2)
        u = ci / k
        v = cj / k
        w = 1.0 - (u + v)
        for x in range(3):
            sub[n, c, x] = w * p[t, 0, x] + u * p[t, 1, x] + v * p[t, 2, x]


@jit.kernel
def _projected(rel, n, r, m, axis, u, v):
    """Sub-triangle n of rel (corners in cell units) projected onto its nearest face plane
    across ``axis``, as face_coverage computes it: (plane, -1 when it covers nothing (edge-on,
    or outside the grid's planes); corners' u, v in sample units; twice the signed projected
    area)."""
    plane = math.floor((rel[n, 0, axis] + rel[n, 1, axis] + rel[n, 2, axis]) / 3.0 + 0.5 - 1e-6)
    u0 = rel[n, 0, u] * m - 0.5
    u1 = rel[n, 1, u] * m - 0.5
    u2 = rel[n, 2, u] * m - 0.5
    v0 = rel[n, 0, v] * m - 0.5
    v1 = rel[n, 1, v] * m - 0.5
    v2 = rel[n, 2, v] * m - 0.5
    area2 = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    span = max(max(u0, u1, u2) - min(u0, u1, u2), max(v0, v1, v2) - min(v0, v1, v2))
    s = max(span, 1.0)
    keep = abs(area2) > 1e-9 * (s * s) and plane >= 0.0 and plane <= r
    return (np.int64(plane) if keep else -1), u0, u1, u2, v0, v1, v2, area2


@jit.kernel
def _coverage_windows(rel, r, m):
    """Per axis the largest sample window (width, height) any sub-triangle rel (N, 3, 3) in
    cell units needs. face_coverage's planes across each axis (_cover_axis) mark the samples
    each kept sub-triangle's projection covers (same edge functions and tolerances) in a bit
    per sample (the union), and count them per face.

    Numpy scans every sub-triangle over the largest sample window any of them needs, from its
    own first sample; so does _cover_axis (this pass finds that window), so that a sample just
    past a sliver's tip, inside all three edges' tolerance, counts there too."""
    width = np.zeros(3)
    height = np.zeros(3)
    for n in range(rel.shape[0]):
        for axis in range(3):
            u = 1 if axis == 0 else 0
            v = 1 if axis == 2 else 2
            plane, u0, u1, u2, v0, v1, v2, _ = _projected(rel, n, r, m, axis, u, v)
            if plane >= 0:
                width[axis] = max(width[axis], math.floor(max(u0, u1, u2) + 1e-9)
                                  - math.ceil(min(u0, u1, u2) - 1e-9))
                height[axis] = max(height[axis], math.floor(max(v0, v1, v2) + 1e-9)
                                   - math.ceil(min(v0, v1, v2) - 1e-9))
    return width, height


@jit.kernel
def _cover_axis(rel, r, m, axis, width, height, out):
    """face_coverage's planes across ``axis`` into out (R + 1, R, R)."""
    u = 1 if axis == 0 else 0
    v = 1 if axis == 2 else 2
    rm = r * m
    # The union: one bit per sample (face by face, its m x m samples in words of 64), a face's
    # count going up when one of its bits is first set (8x less memory than numpy's booleans,
    # and no pass over them afterwards).
    words = (m * m + 63) // 64
    hit = np.zeros((r + 1, r, r, words), np.int64)
    count = np.zeros((r + 1, r, r), np.int64)
    pu = np.empty(4)
    pv = np.empty(4)
    for n in range(rel.shape[0]):
        plane, pu[0], pu[1], pu[2], pv[0], pv[1], pv[2], area2 = _projected(rel, n, r, m,
                                                                            axis, u, v)
        if plane < 0:
            continue
        pu[3] = pu[0]
        pv[3] = pv[0]
        sign = 1.0 if area2 > 0.0 else -1.0
        # edge i: corner i -> i + 1, oriented inside >= tolerance (relative to its length)
        au0, av0 = pu[0], pv[0]
        du0, dv0 = (pu[1] - pu[0]) * sign, (pv[1] - pv[0]) * sign
        au1, av1 = pu[1], pv[1]
        du1, dv1 = (pu[2] - pu[1]) * sign, (pv[2] - pv[1]) * sign
        au2, av2 = pu[2], pv[2]
        du2, dv2 = (pu[3] - pu[2]) * sign, (pv[3] - pv[2]) * sign
        tol0 = -1e-9 * math.hypot(du0, dv0)
        tol1 = -1e-9 * math.hypot(du1, dv1)
        tol2 = -1e-9 * math.hypot(du2, dv2)
        j0 = math.ceil(min(pu[0], pu[1], pu[2]) - 1e-9)
        l0 = math.ceil(min(pv[0], pv[1], pv[2]) - 1e-9)
        ja = max(j0, 0.0)
        jb = min(j0 + width, rm - 1.0)
        la = max(l0, 0.0)
        lb = min(l0 + height, rm - 1.0)
        if ja > jb or la > lb:
            continue
        for ju in range(np.int64(ja), np.int64(jb) + 1):
            fu = float(ju)
            iu = ju // m
            row = (ju - iu * m) * m
            for lv in range(np.int64(la), np.int64(lb) + 1):
                fv = float(lv)
                if (du0 * (fv - av0) - dv0 * (fu - au0) >= tol0
                        and du1 * (fv - av1) - dv1 * (fu - au1) >= tol1
                        and du2 * (fv - av2) - dv2 * (fu - au2) >= tol2):
                    iv = lv // m
                    bit = row + lv - iv * m
                    mask = np.int64(1) << (bit & 63)
                    word = hit[plane, iu, iv, bit >> 6]
                    if not word & mask:
                        hit[plane, iu, iv, bit >> 6] = word | mask
                        count[plane, iu, iv] += 1
    for p in range(r + 1):  # the mean over each face's m x m samples
        for iu in range(r):
            for iv in range(r):
                out[p, iu, iv] = count[p, iu, iv] / (m * m)


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
