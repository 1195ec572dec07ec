"""Compiled twin of sky.irradiance (kernels/__init__.py): the World's shadowed, normalised
sum over its directions for every receiver in one pass, each direction's visibility the same
normal-offset 2x2 percentage-closer test of its orthographic map as render/direct.py's hard
shadows (the compiled direct light's own ``_pcf``)."""

from __future__ import annotations

import numpy as np

from ..runtime import jit, pool
from .direct import BIAS_TEXELS, OFFSET_TEXELS, _pcf


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
    pool.in_parts(lambda sl: _sky_kernel(*args, sl.start, sl.stop), pos.shape[0])
    return out


@jit.kernel
def _sky_kernel(pos, nrm, dirs, weights, rad, views, half, depths, pcf, first_hit, out,
                m0, m1):  # pragma: no cover
    """Points m0..m1-1: den = sum_k w_k c_k, e = sum_k w_k c_k V_k L_k, out = pi e / den
    (c_k = max(0, n.w_k)); direction by direction, so that one map at a time is read (twice
    as fast as point by point through all 64 maps, docs/decisions.md), over runs of points
    with one normal (a surface's surfels): c_k, the normal's view terms and den once a run."""
    k_count, res = dirs.shape[0], depths.shape[1]
    starts = _normal_runs(nrm, m0, m1)
    runs = starts.size - 1
    den = np.zeros(runs)
    out[m0:m1] = 0.0
    for k in range(k_count):
        dark = rad[k, 0] == 0.0 and rad[k, 1] == 0.0 and rad[k, 2] == 0.0
        hk = half[k]
        world = 2.0 * hk / res  # a texel; the surfels' one tap: offset and bias 1.5 of them
        eps, off, lim = first_hit * world, 1.5 * world, 1.0 + 2.0 / res
        o, bias = world * OFFSET_TEXELS, world * BIAS_TEXELS  # the pixels' 2x2 test
        v, dep = views[k], depths[k]
        v00, v01, v02, v03 = v[0, 0], v[0, 1], v[0, 2], v[0, 3]
        v10, v11, v12, v13 = v[1, 0], v[1, 1], v[1, 2], v[1, 3]
        v20, v21, v22, v23 = v[2, 0], v[2, 1], v[2, 2], v[2, 3]
        for r in range(runs):
            a = starts[r]
            nx, ny, nz = nrm[a, 0], nrm[a, 1], nrm[a, 2]
            c = nx * dirs[k, 0] + ny * dirs[k, 1] + nz * dirs[k, 2]
            if c <= 0.0:
                continue
            den[r] += weights[k] * c
            if dark:
                continue
            if pcf:
                for m in range(a, starts[r + 1]):
                    ox, oy, oz = pos[m, 0] + nx * o, pos[m, 1] + ny * o, pos[m, 2] + nz * o
                    d = -(v20 * ox + v21 * oy + v22 * oz + v23)
                    vis = _pcf(v, True, hk, dep, res, ox, oy, oz, d, bias, False)
                    s = weights[k] * c * vis
                    out[m, 0] += s * rad[k, 0]
                    out[m, 1] += s * rad[k, 1]
                    out[m, 2] += s * rad[k, 2]
                continue
            # sky._one_tap: the offset, biased test, then the first-hit test
            mx = nx * v00 + ny * v01 + nz * v02
            my = nx * v10 + ny * v11 + nz * v12
            mz = nx * v20 + ny * v21 + nz * v22
            s = weights[k] * c
            s0, s1, s2 = s * rad[k, 0], s * rad[k, 1], s * rad[k, 2]
            for m in range(a, starts[r + 1]):
                px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
                qx = px * v00 + py * v01 + pz * v02 + v03
                qy = px * v10 + py * v11 + pz * v12 + v13
                qz = px * v20 + py * v21 + pz * v22 + v23
                u, w = (qx + off * mx) / hk, (qy + off * my) / hk
                if abs(u) <= 1.0 and abs(w) <= 1.0:
                    x = min(int((u + 1.0) * 0.5 * res), res - 1)
                    y = min(int((1.0 - w) * 0.5 * res), res - 1)
                    if -(qz + off * mz) > dep[y, x] + off:
                        continue
                u, w = qx / hk, qy / hk
                if abs(u) <= lim and abs(w) <= lim:
                    x = min(max(int((u + 1.0) * 0.5 * res), 0), res - 1)
                    y = min(max(int((1.0 - w) * 0.5 * res), 0), res - 1)
                    cx = ((x + 0.5) * 2.0 / res - 1.0) * hk
                    cy = (1.0 - (y + 0.5) * 2.0 / res) * hk
                    plane = (mx * (cx - qx) + my * (cy - qy)) / max(mz, 1e-12) - qz
                    if dep[y, x] < plane - eps:
                        continue
                out[m, 0] += s0
                out[m, 1] += s1
                out[m, 2] += s2
    for r in range(runs):
        f = np.pi / den[r] if den[r] > 0.0 else 0.0
        for m in range(starts[r], starts[r + 1]):
            out[m, 0], out[m, 1], out[m, 2] = out[m, 0] * f, out[m, 1] * f, out[m, 2] * f


@jit.kernel
def _normal_runs(nrm, m0, m1):  # pragma: no cover
    """Where each run of equal normals among points m0..m1-1 starts, then m1 (runs + 1,)."""
    starts = np.empty(m1 - m0 + 1, np.int64)
    n = 0
    for m in range(m0, m1):
        if (m == m0 or nrm[m, 0] != nrm[m - 1, 0] or nrm[m, 1] != nrm[m - 1, 1]
                or nrm[m, 2] != nrm[m - 1, 2]):
            starts[n] = m
            n += 1
    starts[n] = m1
    return starts[:n + 1].copy()
