"""Compiled twin of sky.irradiance (kernels/__init__.py): the World's shadowed, normalised
sum over its directions for every receiver in one pass, each direction's visibility the same
normal-offset 2x2 percentage-closer test of its orthographic map as render/direct.py's hard
shadows (the compiled direct light's own ``_pcf``)."""

from __future__ import annotations

import numpy as np

from ..runtime import jit, pool
from .direct import _pcf


def irradiance(directions, weights, radiance, views, half, depths, positions,
               normals) -> np.ndarray:
    """sky.irradiance (M, 3) with the directions' view matrices (K, 4, 4), window half extents
    (K,) and stacked depth maps (K, R, R) float32, on two threads."""
    pos = np.ascontiguousarray(positions, np.float64)
    nrm = np.ascontiguousarray(normals, np.float64)
    out = np.empty((pos.shape[0], 3), np.float64)
    args = (pos, nrm, np.ascontiguousarray(directions, np.float64),
            np.ascontiguousarray(weights, np.float64),
            np.ascontiguousarray(radiance, np.float64),
            np.ascontiguousarray(views, np.float64), np.ascontiguousarray(half, np.float64),
            depths, out)
    pool.in_halves(lambda sl: _sky_kernel(*args, sl.start, sl.stop), pos.shape[0])
    return out


@jit.kernel
def _sky_kernel(pos, nrm, dirs, weights, rad, views, half, depths, out, m0,
                m1):  # pragma: no cover
    """Points m0..m1-1: den = sum_k w_k c_k, e = sum_k w_k c_k V_k L_k, out = pi e / den
    (c_k = max(0, n.w_k))."""
    k_count, res = dirs.shape[0], depths.shape[1]
    for m in range(m0, m1):
        px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
        nx, ny, nz = nrm[m, 0], nrm[m, 1], nrm[m, 2]
        den = e0 = e1 = e2 = 0.0
        for k in range(k_count):
            c = nx * dirs[k, 0] + ny * dirs[k, 1] + nz * dirs[k, 2]
            if c <= 0.0:
                continue
            den += weights[k] * c
            if rad[k, 0] == 0.0 and rad[k, 1] == 0.0 and rad[k, 2] == 0.0:
                continue
            world = 2.0 * half[k] / res
            ox, oy, oz = px + nx * world * 1.5, py + ny * world * 1.5, pz + nz * world * 1.5
            v = views[k]
            d = -(v[2, 0] * ox + v[2, 1] * oy + v[2, 2] * oz + v[2, 3])
            vis = _pcf(v, True, half[k], depths[k], res, ox, oy, oz, d, world * 1.5)
            s = weights[k] * c * vis
            e0 += s * rad[k, 0]
            e1 += s * rad[k, 1]
            e2 += s * rad[k, 2]
        f = np.pi / den if den > 0.0 else 0.0
        out[m, 0], out[m, 1], out[m, 2] = e0 * f, e1 * f, e2 * f
