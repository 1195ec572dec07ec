"""Geometry volume: how much of each LPV cell face is covered by occluders [KD10 sec. 5].

KD10 stores a blocking potential B(w) = A_s <n_s, w>_+ / s^2 per cell of a grid offset by half
a cell, injected from RSM and camera-depth surfels. We build it from the occluding triangles
themselves (complete, not limited to what a light or the camera sees), sampled into surfels,
and keep it where propagation needs it: on the faces between cells. Light crossing a face along
axis a is blocked by the occluders' projected area onto that face, sum A_s |n_s . a| / s^2
(surfaces block from both sides), clamped to 1. The transmittance 1 - B per face becomes the
propagation ``visibility`` (6, R, R, R).
"""

from __future__ import annotations

import numpy as np

from .grid import Grid


def surfels(positions: np.ndarray, spacing: float, with_index: bool = False):
    """Sample triangles (T, 3, 3) into surfels at most ``spacing`` apart.

    Returns centres (N, 3), unit normals (N, 3) and areas (N,) that add up to each triangle's
    area (and, ``with_index``, each surfel's triangle (N,)). A triangle gets k^2 sub-triangles
    (k from its longest edge), whose centroids are the surfels: exact area, even coverage, no
    randomness.
    """
    p = np.asarray(positions, np.float64).reshape(-1, 3, 3)
    if p.shape[0] == 0:
        empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        return empty + (np.zeros(0, np.int64),) if with_index else empty
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    cross = np.cross(e1, e2)
    area2 = np.linalg.norm(cross, axis=1)
    normal = cross / np.where(area2 > 0, area2, 1.0)[:, None]
    longest = np.max(np.linalg.norm(np.stack([e1, e2, p[:, 2] - p[:, 1]], 1), axis=2), axis=1)
    # (an edge that is an exact multiple of the spacing must not get one more split by rounding)
    k = np.clip(np.ceil(longest / max(spacing, 1e-30) - 1e-6), 1, 64).astype(np.int64)
    out_p, out_n, out_a, out_i = [], [], [], []
    for kk in np.unique(k):
        sel = np.nonzero(k == kk)[0]
        bary = _sub_centroids(int(kk))  # (kk^2, 3)
        pts = np.einsum("sb,tbc->tsc", bary, p[sel]).reshape(-1, 3)
        out_p.append(pts)
        out_n.append(np.repeat(normal[sel], len(bary), axis=0))
        out_a.append(np.repeat(0.5 * area2[sel] / len(bary), len(bary)))
        out_i.append(np.repeat(sel, len(bary)))
    result = (np.concatenate(out_p), np.concatenate(out_n), np.concatenate(out_a))
    return result + (np.concatenate(out_i),) if with_index else result


def _sub_centroids(k: int) -> np.ndarray:
    """Barycentric centroids of the k^2 equal sub-triangles of a triangle."""
    pts = []
    for i in range(k):
        for j in range(k - i):
            pts.append(((i + 1 / 3) / k, (j + 1 / 3) / k))  # upright sub-triangle
            if i + j < k - 1:
                pts.append(((i + 2 / 3) / k, (j + 2 / 3) / k))  # inverted neighbour
    uv = np.array(pts)
    return np.c_[1.0 - uv.sum(1), uv]


def face_transmittance(grid: Grid, positions, normals, areas) -> np.ndarray:
    """(6, R, R, R) fraction of light a cell sends across each of its faces (AXES order).

    A surfel blocks the face plane nearest to it along each axis, spread bilinearly over the
    faces of that plane around it.
    """
    r = grid.resolution
    s = grid.cell_size
    blocking = np.zeros((3, r + 1, r, r))  # [axis, plane index, two in-plane cell indices]
    if len(areas):
        rel = (np.asarray(positions, np.float64) - grid.origin_array) / s
        for axis in range(3):
            u, v = [a for a in range(3) if a != axis]
            weight = np.abs(normals[:, axis]) * areas / (s * s)
            # Nearest plane; a surfel half-way between two (common by construction) goes to the
            # lower one whatever the rounding, so scaling or moving the scene changes nothing.
            plane = np.floor(rel[:, axis] + 0.5 - 1e-6).astype(np.int64)
            fu = rel[:, u] - 0.5
            fv = rel[:, v] - 0.5
            iu0 = np.floor(fu).astype(np.int64)
            iv0 = np.floor(fv).astype(np.int64)
            tu, tv = fu - iu0, fv - iv0
            flat = blocking[axis].reshape(-1)
            for du, wu in ((0, 1 - tu), (1, tu)):
                for dv, wv in ((0, 1 - tv), (1, tv)):
                    iu, iv = iu0 + du, iv0 + dv
                    ok = ((plane >= 0) & (plane <= r) & (iu >= 0) & (iu < r)
                          & (iv >= 0) & (iv < r))
                    idx = (plane[ok] * r + iu[ok]) * r + iv[ok]
                    flat += np.bincount(idx, weights=(weight * wu * wv)[ok], minlength=flat.size)
    trans = 1.0 - np.minimum(blocking, 1.0)  # (3, R+1, R, R)
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


def occluder_visibility(grid: Grid, triangles: np.ndarray) -> np.ndarray:
    """Propagation visibility (6, R, R, R) from occluding triangles (T, 3, 3)."""
    p, n, a = surfels(triangles, 0.5 * grid.cell_size)
    return face_transmittance(grid, p, n, a)
