"""Compiled contact-light gather: the twin of render.contact.gather, pixel by pixel with the
numpy reference's float64 arithmetic, the rows split over the pool's threads."""

from __future__ import annotations

import numpy as np

from ..runtime import jit, pool
from .direct import _polygon


def gather(positions, normals, covered, radiosity, area, size, reach, region, edges,
           taps: int) -> np.ndarray:
    """render.contact.gather by ``_gather_kernel``, ``taps`` its TAP_RADIUS."""
    h, w = covered.shape
    out = np.zeros((h, w, 3), np.float64)
    args = (np.ascontiguousarray(positions, np.float64), np.ascontiguousarray(normals, np.float64),
            np.ascontiguousarray(covered, np.bool_),
            np.ascontiguousarray(radiosity, np.float64), np.ascontiguousarray(area, np.float64),
            np.ascontiguousarray(size, np.float64), np.ascontiguousarray(reach, np.float64),
            np.ascontiguousarray(region, np.int64), np.ascontiguousarray(edges, np.float64))
    pool.in_parts(lambda sl: _gather_kernel(*args, int(taps), out, sl.start, sl.stop), h,
                  smallest=16)
    return out


@jit.kernel
def _gather_kernel(pos, nrm, covered, radiosity, area, size, reach, region, edges, t, out,
                   y0, y1):  # pragma: no cover - compiled
    """gather's taps for rows y0..y1-1: the same window, stride, tests, form factors and sum
    in tap order."""
    h, w = covered.shape
    poly = np.empty((4, 3))
    for y in range(y0, y1):
        for x in range(w):
            if not covered[y, x]:
                continue
            rho = reach[y, x]
            px = rho / size[y, x] if size[y, x] > 0.0 else 0.0
            if px < 1.0:
                continue
            st = max(1, int(np.ceil(px / t)))
            inv_far = 1.0 / (np.pi * rho * rho)
            for dy in range(-t, t + 1):
                for dx in range(-t, t + 1):
                    if (dx == 0 and dy == 0) or dx * dx + dy * dy > t * t:
                        continue
                    yy, xx = y + dy * st, x + dx * st
                    if yy < 0 or yy >= h or xx < 0 or xx >= w:
                        continue
                    if not covered[yy, xx] or region[yy, xx] != region[y, x]:
                        continue
                    v0 = pos[yy, xx, 0] - pos[y, x, 0]
                    v1 = pos[yy, xx, 1] - pos[y, x, 1]
                    v2 = pos[yy, xx, 2] - pos[y, x, 2]
                    r2 = v0 * v0 + v1 * v1 + v2 * v2
                    if not (r2 < rho * rho) or r2 <= 0.0:
                        continue
                    ci = nrm[y, x, 0] * v0 + nrm[y, x, 1] * v1 + nrm[y, x, 2] * v2
                    cj = -(nrm[yy, xx, 0] * v0 + nrm[yy, xx, 1] * v1 + nrm[yy, xx, 2] * v2)
                    if cj <= 0.0:
                        continue
                    a = (st * st) * area[yy, xx]
                    cc = max(ci, 0.0) * cj / r2
                    f = cc * a / (np.pi * r2 + a)  # the disk form factor
                    span = 0.0  # 0: no footprint (patch_edges)
                    for k in range(3):
                        span += abs(edges[yy, xx, 0, k]) + abs(edges[yy, xx, 1, k])
                    if span > 0.0:
                        for k in range(3):
                            q = pos[yy, xx, k]  # the patch's centre
                            du, dv = st * edges[yy, xx, 0, k], st * edges[yy, xx, 1, k]
                            poly[0, k], poly[1, k] = q - du - dv, q + du - dv
                            poly[2, k], poly[3, k] = q + du + dv, q - du + dv
                        f = _polygon(poly, pos[y, x, 0], pos[y, x, 1], pos[y, x, 2],
                                     nrm[y, x, 0], nrm[y, x, 1], nrm[y, x, 2]) / np.pi
                    elif ci <= 0.0:
                        continue
                    g = max(0.0, f - cc * a * inv_far)
                    for c in range(3):
                        out[y, x, c] += radiosity[yy, xx, c] * g
