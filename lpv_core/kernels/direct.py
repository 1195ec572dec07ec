"""Compiled twin of render.direct.irradiance (kernels/__init__.py): the direct light of every
receiver point, with the 2x2 percentage-closer shadow test, in one pass per point."""

from __future__ import annotations

import numpy as np

from ..runtime import jit, pool
from ..scene.model import Light

KINDS = {"POINT": 0, "SPOT": 1, "AREA": 2, "SUN": 3}  # the light types the kernel lights


def irradiance(light: Light, positions: np.ndarray, normals: np.ndarray,
               shadow=None) -> np.ndarray:
    """direct.irradiance (M, 3) of a light of a type in KINDS (``shadow`` a direct.ShadowMap or
    None) by ``_direct_kernel``: the same float64 arithmetic as the numpy code
    (lights.intensity, then ``visibility`` for the lit points), point by point on two threads
    (it runs per light and sample over every pixel of the frame)."""
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    color = np.asarray(light.color, np.float64)
    kind = KINDS[light.type]
    cos_half = smooth = 0.0
    if kind == 1:
        cos_half = float(np.cos(0.5 * light.spot_size))
        smooth = (1.0 - cos_half) * light.spot_blend
    shadowed = shadow is not None and bool(light.cast_shadow)
    views = shadow.views if shadowed else []
    res = shadow.resolution if shadowed else 1
    mats = np.array([np.asarray(v.view, np.float64) for v in views]).reshape(-1, 4, 4)
    ortho = np.array([bool(v.ortho) for v in views], np.bool_)
    scale = np.array([v.half_extent if v.ortho else v.tan_half for v in views], np.float64)
    depths = shadow.stacked() if shadowed else np.zeros((0, 1, 1), np.float32)
    face_view = np.full(6, -1, np.int64)  # cube face -> view (point and area lights)
    single = kind == 3 or len(views) == 1
    for i, v in enumerate(views):
        if 0 <= v.face < 6:
            face_view[v.face] = i
    pos, nrm = np.ascontiguousarray(positions), np.ascontiguousarray(normals)
    out = np.empty(pos.shape[0], np.float64)
    args = (kind, np.asarray(light.position, np.float64), np.asarray(light.direction, np.float64),
            float(light.power), cos_half, smooth, mats, ortho, scale, depths, face_view, single,
            res, pos, nrm, out)
    pool.in_halves(lambda sl: _direct_kernel(*args, sl.start, sl.stop), pos.shape[0])
    return out[:, None] * color


@jit.kernel
def _direct_kernel(kind, lp, axis, power, cos_half, smooth, mats, ortho, scale, depths,
                   face_view, single, res, pos, nrm, out, m0, m1):  # pragma: no cover
    """``irradiance`` (per unit colour) of points m0..m1-1: lights.intensity and the cosine
    over d^2 (the sun: E cos), then for lit points with views the 2x2 percentage-closer
    ``visibility`` of the view the point falls in (cube face by its largest axis)."""
    four_pi, pi = 4.0 * np.pi, np.pi
    for m in range(m0, m1):
        px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
        nx, ny, nz = nrm[m, 0], nrm[m, 1], nrm[m, 2]
        if kind == 3:
            e = power * max(nx * -axis[0] + ny * -axis[1] + nz * -axis[2], 0.0)
        else:
            tx_, ty_, tz_ = lp[0] - px, lp[1] - py, lp[2] - pz
            d2 = max(tx_ * tx_ + ty_ * ty_ + tz_ * tz_, 1e-30)
            root = np.sqrt(d2)
            wx, wy, wz = tx_ / root, ty_ / root, tz_ / root
            cos_r = max(nx * wx + ny * wy + nz * wz, 0.0)
            if kind == 0:
                inten = power / four_pi
            else:
                cos_a = -wx * axis[0] + -wy * axis[1] + -wz * axis[2]
                if kind == 2:
                    inten = power / pi * max(cos_a, 0.0)
                elif smooth > 0:
                    x = min(max((cos_a - cos_half) / smooth, 0.0), 1.0)
                    inten = power / four_pi * (x * x * (3.0 - 2.0 * x))
                else:
                    inten = power / four_pi * (1.0 if cos_a > cos_half else 0.0)
            e = inten * cos_r / d2
        if e > 0 and mats.shape[0] > 0:
            view = 0
            if not single:
                rx, ry, rz = px - lp[0], py - lp[1], pz - lp[2]
                ax, big = 0, abs(rx)
                if abs(ry) > big:
                    ax, big = 1, abs(ry)
                if abs(rz) > big:
                    ax = 2
                comp = rx if ax == 0 else (ry if ax == 1 else rz)
                view = face_view[ax * 2 + (1 if comp < 0 else 0)]
            if view >= 0:
                e *= _pcf(mats[view], ortho[view], scale[view], depths[view], res, lp,
                          px, py, pz, nx, ny, nz)
        out[m] = e


@jit.kernel
def _pcf(mat, ortho, scale, depth, res, lp, px, py, pz, nx, ny, nz):  # pragma: no cover
    """``visibility`` of one point in one view: 2x2 bilinear percentage-closer filtering of the
    offset point's distance (sun: depth) against the map, 1 outside the view."""
    if ortho:
        texel = 2.0 * scale / res
        qx, qy, qz = px + nx * texel * 1.5, py + ny * texel * 1.5, pz + nz * texel * 1.5
        vx = qx * mat[0, 0] + qy * mat[0, 1] + qz * mat[0, 2] + mat[0, 3]
        vy = qx * mat[1, 0] + qy * mat[1, 1] + qz * mat[1, 2] + mat[1, 3]
        vz = qx * mat[2, 0] + qy * mat[2, 1] + qz * mat[2, 2] + mat[2, 3]
        u, v, d = vx / scale, vy / scale, -vz
        bias = texel * 1.5
    else:
        rx, ry, rz = px - lp[0], py - lp[1], pz - lp[2]
        texel = np.sqrt(rx * rx + ry * ry + rz * rz) * (2.0 * scale / res) * 1.8
        qx, qy, qz = px + nx * texel, py + ny * texel, pz + nz * texel
        vx = qx * mat[0, 0] + qy * mat[0, 1] + qz * mat[0, 2] + mat[0, 3]
        vy = qx * mat[1, 0] + qy * mat[1, 1] + qz * mat[1, 2] + mat[1, 3]
        vz = qx * mat[2, 0] + qy * mat[2, 1] + qz * mat[2, 2] + mat[2, 3]
        z = max(-vz, 1e-30)
        u, v = vx / z / scale, vy / z / scale
        ox, oy, oz = qx - lp[0], qy - lp[1], qz - lp[2]
        d = np.sqrt(ox * ox + oy * oy + oz * oz)
        bias = texel * 1.5
    if not (abs(u) <= 1.0 and abs(v) <= 1.0):
        return 1.0
    fx = (u + 1.0) * 0.5 * res - 0.5
    fy = (1.0 - v) * 0.5 * res - 0.5
    bx, by = np.floor(fx), np.floor(fy)
    tx, ty = fx - bx, fy - by
    x0, y0 = int(bx), int(by)
    acc = 0.0
    for dy in range(2):
        wy = ty if dy else 1.0 - ty
        ys = min(max(y0 + dy, 0), res - 1)
        for dx in range(2):
            wx = tx if dx else 1.0 - tx
            xs = min(max(x0 + dx, 0), res - 1)
            if d <= depth[ys, xs] + bias:
                acc += wx * wy
    return acc
