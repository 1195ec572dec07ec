"""Compiled twins of the planner's geometry tests (kernels/__init__.py): triangle/box overlap,
clipping triangles to a box and polygon/cone hits, per triangle in scalars, with the numpy
code's operations in its order."""

from __future__ import annotations

import numpy as np

from ..runtime import jit


def _tri_box_overlap(tris: np.ndarray, centre: np.ndarray, h: np.ndarray,
                     out: np.ndarray) -> np.ndarray:
    """planner._tri_box_overlap of its prepared triangles (T, 3, 3) and box (centre, half
    sizes h >= 0) by ``_tri_box_kernel``, written into ``out`` (T,)."""
    _tri_box_kernel(np.ascontiguousarray(tris), centre, h, out)
    return out


def _clip_to_box(poly: np.ndarray, lo, hi):
    """planner._clip_to_box of its float64 triangles (T, 3, 3) by ``_clip_to_box_kernel``:
    polygons (T, 9, 3), the unused rows zero."""
    out, count = np.zeros((poly.shape[0], 9, 3)), np.zeros(poly.shape[0], np.int64)
    _clip_to_box_kernel(poly, np.asarray(lo, np.float64), np.asarray(hi, np.float64),
                        out, count)
    return out, count


def _cone_hits(poly: np.ndarray, count: np.ndarray, apex: np.ndarray, axis: np.ndarray,
               half: float, offset: float, u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """planner._cone_hits for half < 90 deg by ``_cone_hits_kernel``, from the planner's front
    plane ``offset`` and projection axes (u, w): the same per polygon, with no small-array
    numpy calls."""
    out = np.zeros(poly.shape[0], bool)
    _cone_hits_kernel(np.ascontiguousarray(poly, np.float64), count.astype(np.int64),
                      apex, axis, float(half), offset, u, w, float(np.tan(half) ** 2), out)
    return out


@jit.kernel
def _clip_one(src, n, dst, nx, ny, nz, offset):  # pragma: no cover - compiled
    """``_clip`` of one polygon src[:n] into dst; returns its vertex count. Same operations
    in the same order as the numpy code (the products with the normal summed x, y, z)."""
    m = 0
    for i in range(n):
        j = (i + 1) % n
        d = src[i, 0] * nx + src[i, 1] * ny + src[i, 2] * nz - offset
        dn = src[j, 0] * nx + src[j, 1] * ny + src[j, 2] * nz - offset
        if d <= 0.0:
            dst[m, 0], dst[m, 1], dst[m, 2] = src[i, 0], src[i, 1], src[i, 2]
            m += 1
        if (d <= 0.0) != (dn <= 0.0):
            f = d / (d - dn)
            for c in range(3):
                dst[m, c] = src[i, c] + f * (src[j, c] - src[i, c])
            m += 1
    return m


@jit.kernel
def _clip_to_box_kernel(tris, lo, hi, poly, count):  # pragma: no cover - compiled
    """``_clip_to_box`` per triangle: poly (T, 9, 3) and count (T,) written (a triangle
    clipped by 6 planes keeps at most 9 vertices)."""
    a = np.empty((9, 3))
    b = np.empty((9, 3))
    for t in range(tris.shape[0]):
        a[:3] = tris[t]
        n = 3
        for k in range(3):
            nx, ny, nz = (1.0 if k == 0 else 0.0), (1.0 if k == 1 else 0.0), \
                (1.0 if k == 2 else 0.0)
            n = _clip_one(a, n, b, nx, ny, nz, hi[k])
            n = _clip_one(b, n, a, -nx, -ny, -nz, -lo[k])
        poly[t, :n] = a[:n]
        count[t] = n


@jit.kernel
def _cone_hits_kernel(poly, count, apex, axis, half, offset, u, w, r2, out):  # pragma: no cover
    """``_cone_hits`` per polygon for half < 90 deg: ``offset`` the front plane's (the
    numpy code's, from the whole batch's scale), u, w the projection axes, r2 = tan^2(half)."""
    a = np.empty((poly.shape[1] + 1, 3))
    qx = np.empty(poly.shape[1] + 1)
    qy = np.empty(poly.shape[1] + 1)
    for t in range(poly.shape[0]):
        n = _clip_one(poly[t], count[t], a, -axis[0], -axis[1], -axis[2], offset)
        for i in range(n):
            rx, ry, rz = a[i, 0] - apex[0], a[i, 1] - apex[1], a[i, 2] - apex[2]
            z = rx * axis[0] + ry * axis[1] + rz * axis[2]
            qx[i] = (rx * u[0] + ry * u[1] + rz * u[2]) / z
            qy[i] = (rx * w[0] + ry * w[1] + rz * w[2]) / z
        near, pos, neg = False, False, False
        for i in range(n):
            j = (i + 1) % n
            abx, aby = qx[j] - qx[i], qy[j] - qy[i]
            len2 = abx * abx + aby * aby
            s = 0.0
            if len2 > 0:
                s = min(max(-(qx[i] * abx + qy[i] * aby) / len2, 0.0), 1.0)
            cx, cy = qx[i] + s * abx, qy[i] + s * aby
            near |= cx * cx + cy * cy <= r2
            cross = abx * (-qy[i]) - aby * (-qx[i])
            pos |= cross > 0
            neg |= cross < 0
        out[t] = n > 0 and (near or (n >= 3 and not (pos and neg)))


@jit.kernel
def _tri_box_kernel(tris, centre, h, out):  # pragma: no cover - compiled
    """``_tri_box_overlap`` per triangle: the same separating-axis tests, in scalars."""
    v = np.empty((3, 3))
    e = np.empty((3, 3))
    ax = np.empty((10, 3))
    for t in range(tris.shape[0]):
        for k in range(3):
            for c in range(3):
                v[k, c] = tris[t, k, c] - centre[c]
        aabb, vert_in = True, False
        for c in range(3):
            lo_c = min(min(v[0, c], v[1, c]), v[2, c])
            hi_c = max(max(v[0, c], v[1, c]), v[2, c])
            aabb &= (lo_c <= h[c]) & (hi_c >= -h[c])
        for k in range(3):
            vert_in |= (abs(v[k, 0]) <= h[0]) & (abs(v[k, 1]) <= h[1]) & (abs(v[k, 2]) <= h[2])
        if not aabb or vert_in:
            out[t] = aabb
            continue
        for c in range(3):
            e[0, c], e[1, c], e[2, c] = v[1, c] - v[0, c], v[2, c] - v[1, c], v[0, c] - v[2, c]
        ax[0, 0] = e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1]
        ax[0, 1] = e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2]
        ax[0, 2] = e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0]
        for j in range(3):  # unit_k x e_j, as np.cross forms it (exact: factors 0 and 1)
            ax[1 + j, 0], ax[1 + j, 1], ax[1 + j, 2] = 0.0, -e[j, 2], e[j, 1]
            ax[4 + j, 0], ax[4 + j, 1], ax[4 + j, 2] = e[j, 2], 0.0, -e[j, 0]
            ax[7 + j, 0], ax[7 + j, 1], ax[7 + j, 2] = -e[j, 1], e[j, 0], 0.0
        sep = False
        for a in range(10):
            r = abs(ax[a, 0]) * h[0] + abs(ax[a, 1]) * h[1] + abs(ax[a, 2]) * h[2]
            p0 = v[0, 0] * ax[a, 0] + v[0, 1] * ax[a, 1] + v[0, 2] * ax[a, 2]
            p1 = v[1, 0] * ax[a, 0] + v[1, 1] * ax[a, 1] + v[1, 2] * ax[a, 2]
            p2 = v[2, 0] * ax[a, 0] + v[2, 1] * ax[a, 1] + v[2, 2] * ax[a, 2]
            sep |= (min(min(p0, p1), p2) > r) | (max(max(p0, p1), p2) < -r)
        out[t] = not sep
