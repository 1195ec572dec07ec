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

This module is the numpy reference. Where numba is installed (runtime.jit), _subdivide,
face_coverage, face_offsets and occluder_volume run their compiled twins in
kernels/geometry_volume.py, which give the same bits.
"""

from __future__ import annotations

import numpy as np

from .grid import Grid
from .kernels import geometry_volume as _compiled
from .runtime import jit

# Sample points per face edge: 8, a quarter of a sub-triangle's length (SURFEL_SPACING), so that
# even a sub-triangle's thin projection (a surface nearly edge-on to the plane) is sampled
# across and a face's blocking is resolved in steps of 1/64. Measured on the two-room leak test
# (tests/test_lpv_core.py, a 0.2 m wall, 1/3 of a cell): 2 and 4 samples per edge let
# 0.95 % and 1.02 % through (coarse coverage of the faces where the wall meets floor and
# roof), 8 lets 0.76 % through. The samples sit at odd multiples of 1/16 cell, off the cell and
# half-cell lines where fitted scene bounds and walls usually lie. Sub-triangles are half a
# cell long (SURFEL_SPACING, in cells). Both are defined with the compiled twins, which share
# them.
COVERAGE_SAMPLES = _compiled.COVERAGE_SAMPLES
SURFEL_SPACING = _compiled.SURFEL_SPACING
GAP_COVERAGE = _compiled.GAP_COVERAGE  # (3/8: over half of a face, to within its sampling)


MAX_SPLITS = 64  # sub-triangles along a triangle's edge at most (kernels' _splits_kernel too)


def _subdivide(positions: np.ndarray, spacing: float):
    """Sub-triangles (N, 3, 3) of triangles (T, 3, 3), each at most ``spacing`` long (up to a
    64 x 64 split per triangle), and the triangle each came from (N,), its unit normal (N, 3)
    and its area (N,). A triangle gets k^2 equal sub-triangles (k from its longest edge): exact
    area, even coverage, no randomness."""
    p = np.asarray(positions, np.float64).reshape(-1, 3, 3)
    if p.shape[0] == 0:
        return np.zeros((0, 3, 3)), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    if jit.enabled():
        return _compiled._subdivide(p, spacing)
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
    the sub-triangles along each edge (_subdivide)."""
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    cross = np.cross(e1, e2)
    area2 = np.linalg.norm(cross, axis=1)
    normal = cross / np.where(area2 > 0, area2, 1.0)[:, None]
    longest = np.max(np.linalg.norm(np.stack([e1, e2, p[:, 2] - p[:, 1]], 1), axis=2), axis=1)
    # (an edge that is an exact multiple of the spacing must not get one more split by rounding)
    k = np.clip(np.ceil(longest / max(spacing, 1e-30) - 1e-6), 1, MAX_SPLITS).astype(np.int64)
    return normal, area2, k


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
    # mean(axis=1)'s bits without its reduction machinery (dearer than the sum itself)
    result = ((sub[:, 0] + sub[:, 1] + sub[:, 2]) / 3.0, normal, area)
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
        return _compiled.face_coverage(grid, tri, m, out)
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
        return _compiled.face_offsets(grid, tri, normals, areas, out)
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
    lookup.gap_corrected moves sample points out of these slabs. A face counts as blocked when
    its sampled coverage exceeds GAP_COVERAGE: over half of it, to within the sampling (the
    wall of a cell a room's corner cuts, whose far part is outside the room, is then one)."""
    r = grid.resolution
    gaps = np.zeros((6, r, r, r), np.float32)
    blocked = coverage > GAP_COVERAGE  # mostly covered: the face stands for the surface
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
        return _compiled.occluder_volume(grid, triangles)
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
