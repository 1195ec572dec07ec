"""Compiled contact-light gather: the twin of render.contact.gather_at, receiver by receiver
with the numpy reference's float64 arithmetic, the receivers split over the pool's threads."""

from __future__ import annotations

import numpy as np

from ..runtime import jit, pool
from .direct import _polygon


def gather_at(positions, normals, reach, size, region, centre, source, own_view: bool,
              taps: int, front: float) -> np.ndarray:
    """render.contact.gather_at by ``_gather_kernel``, ``taps`` its TAP_RADIUS, ``front`` its
    FRONT_TOLERANCE."""
    m = len(positions)
    out = np.zeros((m, 3), np.float64)

    def f64(a):
        return np.ascontiguousarray(a, np.float64)

    args = (f64(positions), f64(normals), f64(reach), f64(size),
            np.ascontiguousarray(region, np.int64), np.ascontiguousarray(centre, np.int64),
            f64(source.position), f64(source.normal),
            np.ascontiguousarray(source.covered, np.bool_), f64(source.radiosity),
            f64(source.area), np.ascontiguousarray(source.region, np.int64),
            f64(source.edges), bool(own_view), int(taps), 0.0 if own_view else float(front))
    pool.in_parts(lambda sl: _gather_kernel(*args, out, sl.start, sl.stop), m, smallest=256)
    return out


@jit.kernel
def _gather_kernel(pos, nrm, reach, size, region, centre, spos, snrm, covered, radiosity,
                   area, sregion, edges, own, t, front, out, i0, i1):  # pragma: no cover
    """gather_at's taps for receivers i0..i1-1: the same window, stride, tests, form factors
    and sum in tap order."""
    h, w = covered.shape
    poly = np.empty((4, 3))
    for i in range(i0, i1):
        rho = reach[i]
        px = rho / size[i] if size[i] > 0.0 else 0.0
        if px < 1.0:
            continue
        st = max(1, int(np.ceil(px / t)))
        inv_far = 1.0 / (np.pi * rho * rho)
        y, x = centre[i, 0], centre[i, 1]
        for dy in range(-t, t + 1):
            for dx in range(-t, t + 1):
                if (own and dx == 0 and dy == 0) or dx * dx + dy * dy > t * t:
                    continue
                yy, xx = y + dy * st, x + dx * st
                if yy < 0 or yy >= h or xx < 0 or xx >= w:
                    continue
                if not covered[yy, xx] or sregion[yy, xx] != region[i]:
                    continue
                v0 = spos[yy, xx, 0] - pos[i, 0]
                v1 = spos[yy, xx, 1] - pos[i, 1]
                v2 = spos[yy, xx, 2] - pos[i, 2]
                r2 = v0 * v0 + v1 * v1 + v2 * v2
                if not (r2 < rho * rho) or r2 <= 0.0:
                    continue
                ci = nrm[i, 0] * v0 + nrm[i, 1] * v1 + nrm[i, 2] * v2
                cj = -(snrm[yy, xx, 0] * v0 + snrm[yy, xx, 1] * v1 + snrm[yy, xx, 2] * v2)
                if not cj > front * rho:
                    continue
                if not own and not ci > front * rho:
                    continue
                a = (st * st) * area[yy, xx]
                cc = max(ci, 0.0) * cj / r2
                f = cc * a / (np.pi * r2 + a)  # the disk form factor
                span = 0.0  # 0: no footprint (patch_edges)
                for k in range(3):
                    span += abs(edges[yy, xx, 0, k]) + abs(edges[yy, xx, 1, k])
                if span > 0.0:
                    for k in range(3):
                        q = spos[yy, xx, k]  # the patch's centre
                        du, dv = st * edges[yy, xx, 0, k], st * edges[yy, xx, 1, k]
                        poly[0, k], poly[1, k] = q - du - dv, q + du - dv
                        poly[2, k], poly[3, k] = q + du + dv, q - du + dv
                    f = _polygon(poly, pos[i, 0], pos[i, 1], pos[i, 2],
                                 nrm[i, 0], nrm[i, 1], nrm[i, 2]) / np.pi
                elif ci <= 0.0:
                    continue
                g = max(0.0, f - cc * a * inv_far)
                for c in range(3):
                    out[i, c] += radiosity[yy, xx, c] * g
