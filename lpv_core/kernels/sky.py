"""Compiled twin of sky.irradiance (kernels/__init__.py): the World's shadowed, normalised
sum over its directions for every receiver in one pass, each direction's visibility the same
normal-offset 2x2 percentage-closer test of its orthographic map as render/direct.py's hard
shadows (the compiled direct light's own ``_pcf``)."""

from __future__ import annotations

import numpy as np

from ..runtime import jit, pool
from .direct import _pcf


def irradiance(directions, weights, radiance, views, half, depths, positions, normals,
               pcf: bool = True, first_hit: float = 0.0) -> np.ndarray:
    """sky.irradiance (M, 3) with the directions' view matrices (K, 4, 4), window half extents
    (K,) and stacked depth maps (K, R, R) float32, on two threads; ``pcf`` False: one tap, its
    tolerance ``first_hit`` texels (sky.FIRST_HIT_TEXELS)."""
    pos = np.ascontiguousarray(positions, np.float64)
    nrm = np.ascontiguousarray(normals, np.float64)
    out = np.empty((pos.shape[0], 3), np.float64)
    args = (pos, nrm, np.ascontiguousarray(directions, np.float64),
            np.ascontiguousarray(weights, np.float64),
            np.ascontiguousarray(radiance, np.float64),
            np.ascontiguousarray(views, np.float64), np.ascontiguousarray(half, np.float64),
            depths, bool(pcf), float(first_hit), out)
    pool.in_halves(lambda sl: _sky_kernel(*args, sl.start, sl.stop), pos.shape[0])
    return out


@jit.kernel
def _sky_kernel(pos, nrm, dirs, weights, rad, views, half, depths, pcf, first_hit, out,
                m0, m1):  # pragma: no cover
    """Points m0..m1-1: den = sum_k w_k c_k, e = sum_k w_k c_k V_k L_k, out = pi e / den
    (c_k = max(0, n.w_k)); direction by direction, so that one map at a time is read (twice
    as fast as point by point through all 64 maps, docs/decisions.md)."""
    k_count, res = dirs.shape[0], depths.shape[1]
    den = np.zeros(m1 - m0)
    out[m0:m1] = 0.0
    for k in range(k_count):
        dark = rad[k, 0] == 0.0 and rad[k, 1] == 0.0 and rad[k, 2] == 0.0
        world = 2.0 * half[k] / res  # a texel; render/direct.py's offset and bias: 1.5 of them
        eps, off, lim = first_hit * world, 1.5 * world, 1.0 + 2.0 / res
        v = views[k]
        for m in range(m0, m1):
            nx, ny, nz = nrm[m, 0], nrm[m, 1], nrm[m, 2]
            c = nx * dirs[k, 0] + ny * dirs[k, 1] + nz * dirs[k, 2]
            if c <= 0.0:
                continue
            den[m - m0] += weights[k] * c
            if dark:
                continue
            if pcf:
                ox, oy, oz = (pos[m, 0] + nx * world * 1.5, pos[m, 1] + ny * world * 1.5,
                              pos[m, 2] + nz * world * 1.5)
                d = -(v[2, 0] * ox + v[2, 1] * oy + v[2, 2] * oz + v[2, 3])
                vis = _pcf(v, True, half[k], depths[k], res, ox, oy, oz, d, world * 1.5)
            else:  # sky._one_tap: the offset, biased test, then the first-hit test
                px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
                qx = px * v[0, 0] + py * v[0, 1] + pz * v[0, 2] + v[0, 3]
                qy = px * v[1, 0] + py * v[1, 1] + pz * v[1, 2] + v[1, 3]
                qz = px * v[2, 0] + py * v[2, 1] + pz * v[2, 2] + v[2, 3]
                mx = nx * v[0, 0] + ny * v[0, 1] + nz * v[0, 2]
                my = nx * v[1, 0] + ny * v[1, 1] + nz * v[1, 2]
                mz = nx * v[2, 0] + ny * v[2, 1] + nz * v[2, 2]
                u, w = (qx + off * mx) / half[k], (qy + off * my) / half[k]
                vis = 1.0
                if abs(u) <= 1.0 and abs(w) <= 1.0:
                    x = min(int((u + 1.0) * 0.5 * res), res - 1)
                    y = min(int((1.0 - w) * 0.5 * res), res - 1)
                    if -(qz + off * mz) > depths[k, y, x] + off:
                        vis = 0.0
                u, w = qx / half[k], qy / half[k]
                if vis > 0.0 and abs(u) <= lim and abs(w) <= lim:
                    x = min(max(int((u + 1.0) * 0.5 * res), 0), res - 1)
                    y = min(max(int((1.0 - w) * 0.5 * res), 0), res - 1)
                    cx = ((x + 0.5) * 2.0 / res - 1.0) * half[k]
                    cy = (1.0 - (y + 0.5) * 2.0 / res) * half[k]
                    plane = (mx * (cx - qx) + my * (cy - qy)) / max(mz, 1e-12) - qz
                    if depths[k, y, x] < plane - eps:
                        vis = 0.0
            s = weights[k] * c * vis
            out[m, 0] += s * rad[k, 0]
            out[m, 1] += s * rad[k, 1]
            out[m, 2] += s * rad[k, 2]
    for m in range(m0, m1):
        f = np.pi / den[m - m0] if den[m - m0] > 0.0 else 0.0
        out[m, 0], out[m, 1], out[m, 2] = out[m, 0] * f, out[m, 1] * f, out[m, 2] * f

