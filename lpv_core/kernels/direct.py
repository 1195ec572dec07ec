"""Compiled twin of render.direct.irradiance and render.direct.visibility
(kernels/__init__.py): the direct light of every receiver point, with its shadow test (2x2
percentage-closer for hard lights, percentage-closer soft shadows for lights with a size), in
one pass per point, in the same float64 arithmetic as the numpy code."""

from __future__ import annotations

import numpy as np

from ..runtime import jit, pool
from ..scene import lights as lights_mod
from ..scene.model import Light

KINDS = {"POINT": 0, "SPOT": 1, "AREA": 2, "SUN": 3}  # the light types the kernel lights
# render.direct's constants (the stage owns them; a kernel never imports its stage)
SEARCH_SIDE, FILTER_SIDE, SEARCH_AT, PYRAMID_FROM = 6, 6, 0.5, 2  # REFINE 2: _sub_blocks
HARD, SPHERE, RECTANGLE, ELLIPSE, CONE = 0, 1, 2, 3, 4
OFFSET_TEXELS, BIAS_TEXELS, BESIDE_TEXELS = 1.5, 0.001, 0.02
HASH_A = (12.9898, 78.233, 37.719, 43758.5453)
HASH_B = (39.3468, 11.135, 83.155, 24634.6345)


def _shadow_args(shadow, src, light: Light) -> tuple:
    """The map's arrays and the source's numbers as the kernels take them."""
    shadowed = shadow is not None and bool(light.cast_shadow)
    views = shadow.views if shadowed else []
    res = shadow.resolution if shadowed else 1
    mats = np.array([np.asarray(v.view, np.float64) for v in views]).reshape(-1, 4, 4)
    ortho = np.array([bool(v.ortho) for v in views], np.bool_)
    scale = np.array([v.half_extent if v.ortho else v.tan_half for v in views], np.float64)
    depths = shadow.stacked() if shadowed else np.zeros((0, 1, 1), np.float32)
    face_view = np.full(6, -1, np.int64)  # cube face -> view (point and area lights)
    single = light.type == "SUN" or len(views) == 1
    for i, v in enumerate(views):
        if 0 <= v.face < 6:
            face_view[v.face] = i
    near = 0.0
    if shadowed and views[0].ortho:
        proj = np.asarray(views[0].projection, np.float64)
        near = float((proj[2, 3] + 1.0) / proj[2, 2])
    kind = HARD if src is None else int(src.kind)
    su = np.zeros(3) if src is None else np.asarray(src.u, np.float64)
    sv = np.zeros(3) if src is None else np.asarray(src.v, np.float64)
    srad = 0.0 if src is None else float(src.radius)
    hashes = np.array(HASH_A + HASH_B, np.float64)
    if shadowed and kind != HARD:
        pyr, offs, sizes = shadow.pyramid()
        levs = np.stack([offs, sizes])  # one argument less per call: ~1 ns a word
    else:
        pyr, levs = np.zeros((0, 0, 8), np.float32), np.zeros((2, 1), np.int64)
    planes = bool(shadow.planes) if shadowed else True  # direct.ShadowMap.planes
    return (mats, ortho, scale, depths, face_view, single, res, planes, kind, su, sv, srad,
            near, hashes, pyr, levs)


def irradiance(light: Light, positions: np.ndarray, normals: np.ndarray,
               shadow=None, src=None) -> np.ndarray:
    """direct.irradiance (M, 3) of a light of a type in KINDS (``shadow`` a direct.ShadowMap or
    None, ``src`` its direct.Source) by ``_direct_kernel``, point by point on two threads (it
    runs per light and sample over every pixel of the frame)."""
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    color = np.asarray(light.color, np.float64)
    kind = KINDS[light.type]
    cos_half = smooth = 0.0
    if kind == 1:
        cos_half = float(np.cos(0.5 * light.spot_size))
        smooth = (1.0 - cos_half) * light.spot_blend
    polys = np.zeros((0, 1, 3))
    radiance = tan_half = norm = 0.0
    if kind == 2:
        polys = np.ascontiguousarray(lights_mod.area_patches(light))
        radiance = float(lights_mod.area_radiance(light))
        tan_half, norm = lights_mod.spread_constants(light)
    pos, nrm = np.ascontiguousarray(positions), np.ascontiguousarray(normals)
    out = np.empty(pos.shape[0], np.float64)
    args = (kind, np.asarray(light.position, np.float64), np.asarray(light.direction, np.float64),
            float(light.power), cos_half, smooth, polys, radiance, tan_half, norm,
            *round_args(light), *_shadow_args(shadow, src, light), pos, nrm, out)
    soft = shadow is not None and src is not None and src.kind != HARD
    # soft shadows make some rows of the frame many times dearer than others (in halves
    # one thread idled: the Cornell box's spot frame's halves took 1.7 and 20 ms); a hard
    # light takes one part per thread (a kernel call costs ~30 us)
    pool.in_parts(lambda sl: _direct_kernel(*args, sl.start, sl.stop), pos.shape[0],
                  8 if soft else 1)
    return out[:, None] * color


def visibility(shadow, src, positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """direct.visibility (M,) of the receivers by ``_visibility_kernel``."""
    light = shadow.light
    pos = np.ascontiguousarray(positions, np.float64)
    nrm = np.ascontiguousarray(normals, np.float64)
    out = np.empty(pos.shape[0], np.float64)
    args = (np.asarray(light.position, np.float64), *_shadow_args(shadow, src, light),
            pos, nrm, out)
    pool.in_parts(lambda sl: _visibility_kernel(*args, sl.start, sl.stop), pos.shape[0],
              8 if src.kind != HARD else 1)
    return out


def pyramid_blocks(view, depth: np.ndarray, eye: np.ndarray, b: int) -> np.ndarray:
    """direct._blocks (n, n, 8) of one view by ``_blocks_kernel``, rows of blocks on the pool's
    threads."""
    res = depth.shape[0]
    out = np.empty((-(-res // b), -(-res // b), 8), np.float64)
    args = (np.asarray(view.view, np.float64), bool(view.ortho),
            float(view.half_extent if view.ortho else view.tan_half), eye,
            np.ascontiguousarray(depth, np.float32), b, out)
    pool.in_parts(lambda sl: _blocks_kernel(*args, sl.start, sl.stop), out.shape[0], 1, 1)
    return out


@jit.kernel
def _blocks_kernel(mat, ortho, sc, eye, depth, b, out, r0, r1):  # pragma: no cover
    """direct._blocks' rows r0..r1-1 of blocks."""
    res = depth.shape[0]
    for by in range(r0, r1):
        for bx in range(out.shape[1]):
            dmin, dmax = np.inf, -np.inf
            l0 = l1 = l2 = np.inf
            h0 = h1 = h2 = -np.inf
            for iy in range(by * b, min(by * b + b, res)):
                vc = 1.0 - (iy + 0.5) / res * 2.0
                for ix in range(bx * b, min(bx * b + b, res)):
                    d = np.float64(depth[iy, ix])
                    dmin, dmax = min(dmin, d), max(dmax, d)
                    if not d < np.inf:
                        continue
                    uc = (ix + 0.5) / res * 2.0 - 1.0
                    if ortho:
                        a0, a1, a2 = uc * sc - mat[0, 3], vc * sc - mat[1, 3], -mat[2, 3]
                        x = a0 * mat[0, 0] + a1 * mat[1, 0] + a2 * mat[2, 0] - d * mat[2, 0]
                        y = a0 * mat[0, 1] + a1 * mat[1, 1] + a2 * mat[2, 1] - d * mat[2, 1]
                        z = a0 * mat[0, 2] + a1 * mat[1, 2] + a2 * mat[2, 2] - d * mat[2, 2]
                    else:
                        fx = uc * sc * mat[0, 0] + vc * sc * mat[1, 0] - mat[2, 0]
                        fy = uc * sc * mat[0, 1] + vc * sc * mat[1, 1] - mat[2, 1]
                        fz = uc * sc * mat[0, 2] + vc * sc * mat[1, 2] - mat[2, 2]
                        ln = np.sqrt(fx * fx + fy * fy + fz * fz)
                        x, y, z = (eye[0] + d * (fx / ln), eye[1] + d * (fy / ln),
                                   eye[2] + d * (fz / ln))
                    l0, l1, l2 = min(l0, x), min(l1, y), min(l2, z)
                    h0, h1, h2 = max(h0, x), max(h1, y), max(h2, z)
            o = out[by, bx]
            o[0], o[1], o[2], o[3], o[4], o[5], o[6], o[7] = dmin, dmax, l0, l1, l2, h0, h1, h2


@jit.kernel
def _edge_term(ax, ay, az, bx, by, bz, nx, ny, nz):  # pragma: no cover
    """lights._edge_term of one edge."""
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    s = np.sqrt(cx * cx + cy * cy + cz * cz)
    if not s > 1e-300:
        return 0.0
    gamma = np.arctan2(s, ax * bx + ay * by + az * bz)
    return gamma * (cx * nx + cy * ny + cz * nz) / s


@jit.kernel
def _polygon(poly, px, py, pz, nx, ny, nz):  # pragma: no cover
    """lights.polygon_irradiance of one receiver: the clipped contour integral."""
    nv = poly.shape[0]
    total = 0.0
    lx = ly = lz = ex = ey = ez = 0.0
    leave = enter = False
    for i in range(nv):
        j = (i + 1) % nv
        ax, ay, az = poly[i, 0] - px, poly[i, 1] - py, poly[i, 2] - pz
        bx, by, bz = poly[j, 0] - px, poly[j, 1] - py, poly[j, 2] - pz
        ha = ax * nx + ay * ny + az * nz
        hb = bx * nx + by * ny + bz * nz
        up_a, up_b = ha >= 0.0, hb >= 0.0
        if not (up_a or up_b):
            continue
        xx, xy, xz = ax, ay, az
        if up_a != up_b:
            t = ha / (ha - hb)
            xx, xy, xz = ax + t * (bx - ax), ay + t * (by - ay), az + t * (bz - az)
        if up_a and not up_b:
            total += _edge_term(ax, ay, az, xx, xy, xz, nx, ny, nz)
            lx, ly, lz, leave = xx, xy, xz, True
        elif up_b and not up_a:
            total += _edge_term(xx, xy, xz, bx, by, bz, nx, ny, nz)
            ex, ey, ez, enter = xx, xy, xz, True
        else:
            total += _edge_term(ax, ay, az, bx, by, bz, nx, ny, nz)
    if leave and enter:
        total += _edge_term(lx, ly, lz, ex, ey, ez, nx, ny, nz)
    return 0.5 * abs(total)


def round_args(light: Light) -> tuple[float, bool]:
    """(r^2, sphere) of a POINT or SPOT light for ``round_geometry`` (r^2 0: a point)."""
    r2 = float(light.radius) ** 2 if light.type in ("POINT", "SPOT") else 0.0
    return r2, not bool(light.soft_falloff)


@jit.kernel
def round_geometry(cos_r, d2, r2, sphere):  # pragma: no cover - compiled
    """lights.round_geometry of one receiver (cos_r signed, d2 > 0), with
    lights.cone_projected_solid_angle written out."""
    if not r2 > 0:
        return max(cos_r, 0.0) / d2
    s2 = min(r2 / d2, 1.0) if sphere else r2 / (r2 + d2)
    if s2 >= 1.0:
        return 1.0 / r2  # inside the sphere: pi L over the hemisphere, L = I / (pi r^2)
    c = min(max(cos_r, -1.0), 1.0)
    sin_a = np.sqrt(s2)
    if c >= sin_a:
        return s2 * c / r2
    if c <= -sin_a:
        return 0.0
    st = np.sqrt(max(1.0 - c * c, 1e-30))
    x = np.sqrt(max(1.0 / s2 - 1.0, 0.0))
    y = min(max(-x * c / st, -1.0), 1.0)
    g = st * np.sqrt(1.0 - y * y)
    return ((c * np.arccos(y) - x * g) * s2 + np.arctan2(g, x)) / (np.pi * r2)


@jit.kernel
def _area(polys, radiance, tan_half, norm, lp, axis, px, py, pz, nx, ny, nz):  # pragma: no cover
    """lights.area_irradiance of one receiver."""
    if (px - lp[0]) * axis[0] + (py - lp[1]) * axis[1] + (pz - lp[2]) * axis[2] <= 0.0:
        return 0.0
    e = 0.0
    for s in range(polys.shape[0]):
        part = _polygon(polys[s], px, py, pz, nx, ny, nz)
        if norm > 0.0:
            nv = polys.shape[1]
            gx = gy = gz = 0.0
            for i in range(nv):
                gx += polys[s, i, 0]
                gy += polys[s, i, 1]
                gz += polys[s, i, 2]
            tx, ty, tz = px - gx / nv, py - gy / nv, pz - gz / nv
            cos_t = (tx * axis[0] + ty * axis[1] + tz * axis[2]) / max(
                np.sqrt(tx * tx + ty * ty + tz * tz), 1e-300)
            tan_t = np.sqrt(max(1.0 - cos_t * cos_t, 0.0)) / max(cos_t, 1e-300)
            part = part * max((tan_half - tan_t) * norm, 0.0)
        e = e + part
    return radiance * e


@jit.kernel
def _direct_kernel(kind, lp, axis, power, cos_half, smooth, polys, radiance, tan_half, norm,
                   lrad2, sphere, mats, ortho, scale, depths, face_view, single, res, planes, skind, su, sv, srad,
                   near, hashes, pyr, levs, pos, nrm, out, m0, m1):  # pragma: no cover
    """``irradiance`` (per unit colour) of points m0..m1-1: lights.intensity and
    lights.round_geometry (the sun: E cos; area lights: the contour integral), then for lit points with
    views their ``visibility``."""
    four_pi = 4.0 * np.pi
    for m in range(m0, m1):
        px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
        nx, ny, nz = nrm[m, 0], nrm[m, 1], nrm[m, 2]
        if kind == 3:
            e = power * max(nx * -axis[0] + ny * -axis[1] + nz * -axis[2], 0.0)
        elif kind == 2:
            e = _area(polys, radiance, tan_half, norm, lp, axis, px, py, pz, nx, ny, nz)
        else:
            tx_, ty_, tz_ = lp[0] - px, lp[1] - py, lp[2] - pz
            d2 = max(tx_ * tx_ + ty_ * ty_ + tz_ * tz_, 1e-30)
            root = np.sqrt(d2)
            wx, wy, wz = tx_ / root, ty_ / root, tz_ / root
            cos_r = nx * wx + ny * wy + nz * wz
            if kind == 0 or (sphere and d2 <= lrad2):  # inside a spot's sphere: no cone
                inten = power / four_pi
            else:
                cos_a = -wx * axis[0] + -wy * axis[1] + -wz * axis[2]
                if smooth > 0:
                    x = min(max((cos_a - cos_half) / smooth, 0.0), 1.0)
                    inten = power / four_pi * (x * x * (3.0 - 2.0 * x))
                else:
                    inten = power / four_pi * (1.0 if cos_a > cos_half else 0.0)
            e = inten * round_geometry(cos_r, d2, lrad2, sphere)
        if e > 0 and mats.shape[0] > 0:
            e *= _visibility(lp, mats, ortho, scale, depths, face_view, single, res, planes,
                             skind, su, sv, srad, near, hashes, pyr, levs, px, py, pz, nx, ny,
                             nz)
        out[m] = e


@jit.kernel
def _visibility_kernel(lp, mats, ortho, scale, depths, face_view, single, res, planes, skind,
                       su, sv, srad, near, hashes, pyr, levs, pos, nrm, out, m0,
                       m1):  # pragma: no cover
    """``visibility`` of points m0..m1-1."""
    for m in range(m0, m1):
        out[m] = _visibility(lp, mats, ortho, scale, depths, face_view, single, res, planes,
                             skind, su, sv, srad, near, hashes, pyr, levs, pos[m, 0],
                             pos[m, 1], pos[m, 2], nrm[m, 0], nrm[m, 1], nrm[m, 2])


@jit.kernel
def _view_of(lp, face_view, single, x, y, z):  # pragma: no cover
    """The view a point falls in: 0 for a single view, else its cube face's (-1: none)."""
    if single:
        return 0
    rx, ry, rz = x - lp[0], y - lp[1], z - lp[2]
    ax, big = 0, abs(rx)
    if abs(ry) > big:
        ax, big = 1, abs(ry)
    if abs(rz) > big:
        ax = 2
    comp = rx if ax == 0 else (ry if ax == 1 else rz)
    return face_view[ax * 2 + (1 if comp < 0 else 0)]


@jit.kernel
def _visibility(lp, mats, ortho, scale, depths, face_view, single, res, planes, skind, su, sv,
                srad, near, hashes, pyr, levs, px, py, pz, nx, ny, nz):  # pragma: no cover
    """direct.visibility of one receiver: its view, normal offset, distance and bias
    (direct._receivers), the bilinear test (direct._hard), then for a source with a size the
    soft shadow (direct._soft)."""
    view = _view_of(lp, face_view, single, px, py, pz)
    if view < 0:
        return 1.0
    mat = mats[view]
    if ortho[view]:
        world = 2.0 * scale[view] / res
        o = world * OFFSET_TEXELS
        qx, qy, qz = px + nx * o, py + ny * o, pz + nz * o
        dist = -(qx * mat[2, 0] + qy * mat[2, 1] + qz * mat[2, 2] + mat[2, 3])
        bias = world * BIAS_TEXELS
        texel = world
    else:
        rx, ry, rz = px - lp[0], py - lp[1], pz - lp[2]
        world = np.sqrt(rx * rx + ry * ry + rz * rz) * (2.0 * scale[view] / res) * 1.8
        qx, qy, qz = px + nx * world, py + ny * world, pz + nz * world
        ox, oy, oz = qx - lp[0], qy - lp[1], qz - lp[2]
        dist = np.sqrt(ox * ox + oy * oy + oz * oz)
        bias = world * BIAS_TEXELS
        texel = 2.0 * scale[view] / res
        view = _view_of(lp, face_view, single, qx, qy, qz)  # direct._receivers: by a seam
        if view < 0:
            return 1.0
        mat = mats[view]
    hard = _pcf(mat, ortho[view], scale[view], depths[view], res, qx, qy, qz, dist, bias,
                planes)
    if skind == HARD:
        return hard
    return _soft(lp, mats, ortho, scale, depths, face_view, single, res, skind, su, sv, srad,
                 near, hashes, pyr, levs, view, px, py, pz, nx, ny, nz, qx, qy, qz, dist,
                 bias, texel, hard)


@jit.kernel
def _pcf(mat, ortho, scale, depth, res, qx, qy, qz, d, bias, planes):  # pragma: no cover
    """direct._hard of one offset receiver: 2x2 bilinear percentage-closer filtering of its
    distance (sun: depth) against the map, 1 outside the view; ``planes``: ShadowMap.planes."""
    vx = qx * mat[0, 0] + qy * mat[0, 1] + qz * mat[0, 2] + mat[0, 3]
    vy = qx * mat[1, 0] + qy * mat[1, 1] + qz * mat[1, 2] + mat[1, 3]
    vz = qx * mat[2, 0] + qy * mat[2, 1] + qz * mat[2, 2] + mat[2, 3]
    if ortho:
        u, v = vx / scale, vy / scale
    else:
        z = max(-vz, 1e-30)
        u, v = vx / z / scale, vy / z / scale
    if not (abs(u) <= 1.0 and abs(v) <= 1.0):
        return 1.0
    fx = (u + 1.0) * 0.5 * res - 0.5
    fy = (1.0 - v) * 0.5 * res - 0.5
    bx, by = np.floor(fx), np.floor(fy)
    tx, ty = fx - bx, fy - by
    x0, y0 = int(bx), int(by)
    acc = 0.0
    lit = 0  # bit k: tap k (dx + 2 dy) passes
    for dy in range(2):
        wy = ty if dy else 1.0 - ty
        ys = min(max(y0 + dy, 0), res - 1)
        for dx in range(2):
            wx = tx if dx else 1.0 - tx
            xs = min(max(x0 + dx, 0), res - 1)
            t = _plane_depth(depth, res, xs, ys, fx - xs, fy - ys) if planes else depth[ys, xs]
            if d <= t + bias:
                acc += wx * wy
                lit |= 1 << (dx + 2 * dy)
    if 0 < lit < 15:
        if planes and _in_crease(depth, res, x0, y0, lit, bias):
            return 0.0
        kept = _around_occluder(depth, res, x0, y0, fx, fy, d, lit, bias)
        if kept != lit:
            acc = 0.0
            for k in range(4):
                if kept & (1 << k):
                    acc += (tx if k & 1 else 1.0 - tx) * (ty if k >> 1 else 1.0 - ty)
    return acc


@jit.kernel
def _around_occluder(depth, res, x0, y0, fx, fy, d, lit, tol):  # pragma: no cover
    """direct._around_occluder of one receiver at (fx, fy), distance d, whose 2x2 taps from
    (x0, y0) pass where ``lit``'s bits are set: those bits with the taps that went round an
    occluder cleared (each occluder's slopes read once)."""
    out = lit
    for j in range(4):
        if lit & (1 << j):
            continue
        xj, yj = min(max(x0 + (j & 1), 0), res - 1), min(max(y0 + (j >> 1), 0), res - 1)
        c = np.float64(depth[yj, xj])
        if not np.isfinite(c):
            continue
        gx, gy = _slopes(depth, res, xj, yj, c)
        if not c + gx * (fx - xj) + gy * (fy - yj) < d - tol:
            continue
        for i in range(4):
            if not out & (1 << i):
                continue
            xi, yi = min(max(x0 + (i & 1), 0), res - 1), min(max(y0 + (i >> 1), 0), res - 1)
            if xi == xj and yi == yj:
                continue
            if c + gx * (xi - xj) + gy * (yi - yj) > d + tol:
                out &= ~(1 << i)
    return out


@jit.kernel
def _in_crease(depth, res, x0, y0, lit, tol):  # pragma: no cover
    """direct._in_crease of one receiver whose 2x2 taps from (x0, y0) pass where ``lit``'s
    bits are set."""
    for i in range(4):
        if not lit & (1 << i):
            continue
        xi, yi = min(max(x0 + (i & 1), 0), res - 1), min(max(y0 + (i >> 1), 0), res - 1)
        for j in range(4):
            if lit & (1 << j):
                continue
            xj, yj = min(max(x0 + (j & 1), 0), res - 1), min(max(y0 + (j >> 1), 0), res - 1)
            if xi == xj and yi == yj:
                continue
            ci, cj = np.float64(depth[yi, xi]), np.float64(depth[yj, xj])
            if not (np.isfinite(ci) and np.isfinite(cj)):
                continue
            if (_plane_depth(depth, res, xj, yj, xi - xj, yi - yj) > ci + tol
                    and _plane_depth(depth, res, xi, yi, xj - xi, yj - yi) > cj + tol):
                return True
    return False


@jit.kernel
def _slope(c, lo, hi, lo2, hi2):  # pragma: no cover
    """direct._slope of one texel of depth c, its neighbours lo, hi and the next out."""
    a, b = c - lo, hi - c
    ea, eb = abs(2.0 * lo - lo2 - c), abs(2.0 * hi - hi2 - c)
    if not np.isfinite(ea):
        ea = abs(a) if np.isfinite(a) else np.inf
    if not np.isfinite(eb):
        eb = abs(b) if np.isfinite(b) else np.inf
    g = a if ea <= eb else b
    return g if np.isfinite(g) else 0.0


@jit.kernel
def _slopes(depth, res, xs, ys, c):  # pragma: no cover
    """direct._slope of texel (xs, ys) of depth c along its columns and rows."""
    gx = _slope(c, np.float64(depth[ys, max(xs - 1, 0)]),
                np.float64(depth[ys, min(xs + 1, res - 1)]),
                np.float64(depth[ys, max(xs - 2, 0)]),
                np.float64(depth[ys, min(xs + 2, res - 1)]))
    gy = _slope(c, np.float64(depth[max(ys - 1, 0), xs]),
                np.float64(depth[min(ys + 1, res - 1), xs]),
                np.float64(depth[max(ys - 2, 0), xs]),
                np.float64(depth[min(ys + 2, res - 1), xs]))
    return gx, gy


@jit.kernel
def _texel_plane(depth, res, xs, ys, ox, oy):  # pragma: no cover
    """direct._plane_depth's plane of one texel (inf where it is empty)."""
    c = np.float64(depth[ys, xs])
    if not np.isfinite(c):
        return np.inf
    gx, gy = _slopes(depth, res, xs, ys, c)
    return c + gx * ox + gy * oy


@jit.kernel
def _ray_point(mat, ortho, s, lp, uc, vc, t):  # pragma: no cover
    """The point at depth t on the ray through map coordinates (uc, vc) (direct._texel_ray)."""
    if ortho:
        ax, ay, az = uc * s - mat[0, 3], vc * s - mat[1, 3], -mat[2, 3]
        ox = ax * mat[0, 0] + ay * mat[1, 0] + az * mat[2, 0]
        oy = ax * mat[0, 1] + ay * mat[1, 1] + az * mat[2, 1]
        oz = ax * mat[0, 2] + ay * mat[1, 2] + az * mat[2, 2]
        return ox - t * mat[2, 0], oy - t * mat[2, 1], oz - t * mat[2, 2]
    ax, ay = uc * s, vc * s
    fx = ax * mat[0, 0] + ay * mat[1, 0] - mat[2, 0]
    fy = ax * mat[0, 1] + ay * mat[1, 1] - mat[2, 1]
    fz = ax * mat[0, 2] + ay * mat[1, 2] - mat[2, 2]
    k = t / np.sqrt(fx * fx + fy * fy + fz * fz)
    return lp[0] + k * fx, lp[1] + k * fy, lp[2] + k * fz


@jit.kernel
def _beside_occluder(depth, res, mat, ortho, s, lp, ix, iy, d, qx, qy, qz,
                     beside):  # pragma: no cover
    """direct._beside_occluder of one tap: the receiver q on the light's side of the plane of
    the occluder at texel (ix, iy), depth d, by over ``beside`` texels."""
    gx, gy = _slopes(depth, res, ix, iy, d)
    uc = (ix + 0.5) / res * 2.0 - 1.0
    vc = 1.0 - (iy + 0.5) / res * 2.0
    step = 2.0 / res
    wx, wy, wz = _ray_point(mat, ortho, s, lp, uc, vc, d)
    ax, ay, az = _ray_point(mat, ortho, s, lp, uc + step, vc, d + gx)
    bx, by, bz = _ray_point(mat, ortho, s, lp, uc, vc - step, d + gy)
    ax, ay, az = ax - wx, ay - wy, az - wz
    bx, by, bz = bx - wx, by - wy, bz - wz
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    if ortho:
        lx, ly, lz = mat[2, 0], mat[2, 1], mat[2, 2]
    else:
        lx, ly, lz = lp[0] - wx, lp[1] - wy, lp[2] - wz
    side = nx * lx + ny * ly + nz * lz
    if side == 0.0 or not np.isfinite(side):
        return False
    gap = (nx * (qx - wx) + ny * (qy - wy) + nz * (qz - wz)) * (1.0 if side > 0.0 else -1.0)
    length = np.sqrt(nx * nx + ny * ny + nz * nz)
    texel = np.sqrt(ax * ax + ay * ay + az * az)
    return gap > beside * texel * length


@jit.kernel
def _plane_depth(depth, res, xs, ys, ox, oy):  # pragma: no cover
    """direct._plane_depth of one texel: its plane, an empty one its neighbours' nearest."""
    p = _texel_plane(depth, res, xs, ys, ox, oy)
    if p != np.inf:
        return p
    for k in range(4):
        sx = 1 if k == 0 else (-1 if k == 1 else 0)
        sy = 1 if k == 2 else (-1 if k == 3 else 0)
        nx, ny = min(max(xs + sx, 0), res - 1), min(max(ys + sy, 0), res - 1)
        p = min(p, _texel_plane(depth, res, nx, ny, ox - (nx - xs), oy - (ny - ys)))
    return p


@jit.kernel
def _frac_hash(px, py, pz, hashes, o):  # pragma: no cover
    x = np.sin(px * hashes[o] + py * hashes[o + 1] + pz * hashes[o + 2]) * hashes[o + 3]
    return x - np.floor(x)


@jit.kernel
def _tap(k, side, sa, sb, round_, ux, uy, uz, vx, vy, vz, s, sun, lp, qx, qy,
         qz):  # pragma: no cover
    """Tap ``k`` of a side x side pattern: the stratum's point on the source (axes u, v),
    seen from the receiver q and scaled by ``s`` onto the map (sun: q moved across by s)."""
    a, b = _stratum(k, side, sa, sb, round_)
    ox, oy, oz = a * ux + b * vx, a * uy + b * vy, a * uz + b * vz
    if sun:
        return qx + s * ox, qy + s * oy, qz + s * oz
    cx, cy, cz = lp[0] + ox, lp[1] + oy, lp[2] + oz
    return cx + s * (qx - cx), cy + s * (qy - cy), cz + s * (qz - cz)


@jit.kernel
def _stratum(idx, side, sa, sb, round_):  # pragma: no cover
    """direct._strata's point ``idx``: shifted stratum on [-1, 1]^2, or concentric-mapped."""
    a = ((idx // side) + 0.5) / side + sa
    b = ((idx % side) + 0.5) / side + sb
    a = 2.0 * (a - np.floor(a)) - 1.0
    b = 2.0 * (b - np.floor(b)) - 1.0
    if not round_:
        return a, b
    if a == 0 and b == 0:
        return 0.0, 0.0
    if abs(a) > abs(b):
        r, phi = a, 0.25 * np.pi * b / a
    else:
        r, phi = b, 0.5 * np.pi - 0.25 * np.pi * a / b
    return r * np.cos(phi), r * np.sin(phi)


@jit.kernel
def _texel(lp, mats, ortho, scale, face_view, single, res, x, y, z):  # pragma: no cover
    """direct._texels of one point: (view, column, row, in front of the eye, inside)."""
    view = _view_of(lp, face_view, single, x, y, z)
    if view < 0:
        return -1, 0, 0, False, False
    mat = mats[view]
    s = scale[view]
    vx = x * mat[0, 0] + y * mat[0, 1] + z * mat[0, 2] + mat[0, 3]
    vy = x * mat[1, 0] + y * mat[1, 1] + z * mat[1, 2] + mat[1, 3]
    vz = x * mat[2, 0] + y * mat[2, 1] + z * mat[2, 2] + mat[2, 3]
    ok = True
    if ortho[view]:
        inv = 1.0 / s
    else:
        zz = -vz
        ok = zz > 0
        inv = 1.0 / (zz * s) if ok else 1.0 / s
    u, v = vx * inv, vy * inv
    ix = int(min(max(np.floor((u + 1.0) * 0.5 * res), 0.0), res - 1.0))
    iy = int(min(max(np.floor((1.0 - v) * 0.5 * res), 0.0), res - 1.0))
    return view, ix, iy, ok, ok and abs(u) <= 1.0 and abs(v) <= 1.0


@jit.kernel
def _lookup(lp, mats, ortho, scale, depths, face_view, single, res, x, y, z,
            qx, qy, qz, nx, ny, nz, dist, bias):  # pragma: no cover
    """direct._lookup of one tap point: (depth, occludes). _texel's projection is written out
    here, not called: calling it cost the soft pass 15-25 % (tools.soft_bench)."""
    view = _view_of(lp, face_view, single, x, y, z)
    if view < 0:
        return np.inf, False
    mat = mats[view]
    s = scale[view]
    vx = x * mat[0, 0] + y * mat[0, 1] + z * mat[0, 2] + mat[0, 3]
    vy = x * mat[1, 0] + y * mat[1, 1] + z * mat[1, 2] + mat[1, 3]
    vz = x * mat[2, 0] + y * mat[2, 1] + z * mat[2, 2] + mat[2, 3]
    ok = True
    if ortho[view]:
        inv = 1.0 / s
    else:
        zz = -vz
        ok = zz > 0
        inv = 1.0 / (zz * s) if ok else 1.0 / s
    u, v = vx * inv, vy * inv
    if single:
        ok = ok and abs(u) <= 1.0 and abs(v) <= 1.0
    if not ok:
        return np.inf, False
    ix = int(min(max(np.floor((u + 1.0) * 0.5 * res), 0.0), res - 1.0))
    iy = int(min(max(np.floor((1.0 - v) * 0.5 * res), 0.0), res - 1.0))
    d = np.float64(depths[view, iy, ix])
    if not d < dist - bias:
        return d, False
    uc = (ix + 0.5) / res * 2.0 - 1.0
    vc = 1.0 - (iy + 0.5) / res * 2.0
    if ortho[view]:
        ax, ay, az = uc * s - mat[0, 3], vc * s - mat[1, 3], -mat[2, 3]
        y0x = ax * mat[0, 0] + ay * mat[1, 0] + az * mat[2, 0]
        y0y = ax * mat[0, 1] + ay * mat[1, 1] + az * mat[2, 1]
        y0z = ax * mat[0, 2] + ay * mat[1, 2] + az * mat[2, 2]
        fx, fy, fz = -mat[2, 0], -mat[2, 1], -mat[2, 2]
        ln = 1.0
    else:
        y0x, y0y, y0z = lp[0], lp[1], lp[2]
        ax, ay, az = uc * s, vc * s, -1.0
        fx = ax * mat[0, 0] + ay * mat[1, 0] + az * mat[2, 0]
        fy = ax * mat[0, 1] + ay * mat[1, 1] + az * mat[2, 1]
        fz = ax * mat[0, 2] + ay * mat[1, 2] + az * mat[2, 2]
        ln = np.sqrt(fx * fx + fy * fy + fz * fz)
    h0 = nx * (y0x - qx) + ny * (y0y - qy) + nz * (y0z - qz)
    den = (nx * fx + ny * fy + nz * fz) / ln
    if not h0 + d * den > bias * abs(den):
        return d, False
    return d, not _beside_occluder(depths[view], res, mat, ortho[view], s, lp, ix, iy, d,
                                   qx, qy, qz, BESIDE_TEXELS)


@jit.kernel
def _corner(k, sun, lp, ux, uy, uz, vx, vy, vz, s, qx, qy, qz):  # pragma: no cover
    """direct._corners' point k (0-3), or the receiver q (4)."""
    if k == 4:
        return qx, qy, qz
    a, b = (1.0 if k < 2 else -1.0), (1.0 if k % 2 == 0 else -1.0)
    ox, oy, oz = a * ux + b * vx, a * uy + b * vy, a * uz + b * vz
    if sun:
        return qx + s * ox, qy + s * oy, qz + s * oz
    cx, cy, cz = lp[0] + ox, lp[1] + oy, lp[2] + oz
    return cx + s * (qx - cx), cy + s * (qy - cy), cz + s * (qz - cz)


@jit.kernel
def _box(lp, mats, ortho, scale, face_view, single, res, vw, sun, ux, uy, uz, vx, vy, vz, s,
         qx, qy, qz):  # pragma: no cover
    """direct._box of one receiver: (x0, x1, y0, y1, usable, inside)."""
    x0 = y0 = res
    x1 = y1 = -1
    usable = inside = True
    for k in range(5):
        x, y, z = _corner(k, sun, lp, ux, uy, uz, vx, vy, vz, s, qx, qy, qz)
        view, ix, iy, front, ins = _texel(lp, mats, ortho, scale, face_view, single, res, x, y,
                                          z)
        usable = usable and view == vw and front
        inside = inside and view == vw and ins
        x0, x1, y0, y1 = min(x0, ix), max(x1, ix), min(y0, iy), max(y1, iy)
    return (max(x0 - 1, 0), min(x1 + 1, res - 1), max(y0 - 1, 0), min(y1 + 1, res - 1), usable,
            inside)


@jit.kernel
def _clear_across(lp, mats, scale, res, pyr, levs, ux, uy, uz, vx, vy, vz, s, qx, qy,
                  qz, nx, ny, nz, lim, bias):  # pragma: no cover
    """direct._clear_across of one receiver."""
    for i in range(mats.shape[0]):
        mat = mats[i]
        n_front = 0
        fx0 = fy0 = np.inf
        fx1 = fy1 = -np.inf
        for k in range(5):
            x, y, z = _corner(k, False, lp, ux, uy, uz, vx, vy, vz, s, qx, qy, qz)
            px = x * mat[0, 0] + y * mat[0, 1] + z * mat[0, 2] + mat[0, 3]
            py = x * mat[1, 0] + y * mat[1, 1] + z * mat[1, 2] + mat[1, 3]
            pz = x * mat[2, 0] + y * mat[2, 1] + z * mat[2, 2] + mat[2, 3]
            if not -pz > 0:
                continue
            n_front += 1
            w = -pz * scale[i]
            fx = min(max(np.floor((px / w + 1.0) * 0.5 * res), -2.0), res + 1.0)
            fy = min(max(np.floor((1.0 - py / w) * 0.5 * res), -2.0), res + 1.0)
            fx0, fx1, fy0, fy1 = min(fx0, fx), max(fx1, fx), min(fy0, fy), max(fy1, fy)
        if n_front == 0:
            continue
        if n_front < 5:
            return False
        if not (fx1 >= -1 and fx0 <= res and fy1 >= -1 and fy0 <= res):
            continue
        x0, x1 = min(max(int(fx0) - 1, 0), res - 1), min(max(int(fx1) + 1, 0), res - 1)
        y0, y1 = min(max(int(fy0) - 1, 0), res - 1), min(max(int(fy1) + 1, 0), res - 1)
        if not _box_test(pyr, levs, i, x0, x1, y0, y1, qx, qy, qz, nx, ny, nz, lim, bias,
                         False)[0]:
            return False
    return True


@jit.kernel
def _block(pyr, levs, vw, lev, bx, by, nx, ny, nz, nq, lim, bias,
           umbra):  # pragma: no cover
    """direct._box_test's test of one block: (passes, its least depth)."""
    at = levs[0, lev] + by * levs[1, lev] + bx
    lo, hi = np.float64(pyr[vw, at, 0]), np.float64(pyr[vw, at, 1])
    ax, bx_ = nx * np.float64(pyr[vw, at, 2]), nx * np.float64(pyr[vw, at, 5])
    ay, by_ = ny * np.float64(pyr[vw, at, 3]), ny * np.float64(pyr[vw, at, 6])
    az, bz = nz * np.float64(pyr[vw, at, 4]), nz * np.float64(pyr[vw, at, 7])
    if umbra:
        return hi < lim and min(ax, bx_) + min(ay, by_) + min(az, bz) - nq > bias, lo
    return lo >= lim or max(ax, bx_) + max(ay, by_) + max(az, bz) - nq <= 0.0, lo


@jit.kernel
def _box_test(pyr, levs, vw, x0, x1, y0, y1, qx, qy, qz, nx, ny, nz, lim, bias,
              umbra):  # pragma: no cover
    """direct._box_test of one receiver's box: (passes, least depth)."""
    lev = PYRAMID_FROM
    while (x1 >> lev) - (x0 >> lev) > 2 or (y1 >> lev) - (y0 >> lev) > 2:
        lev += 1
    nq = nx * qx + ny * qy + nz * qz
    ok = True
    least = np.inf
    for by in range(y0 >> lev, (y1 >> lev) + 1):
        for bx in range(x0 >> lev, (x1 >> lev) + 1):
            good, lo = _block(pyr, levs, vw, lev, bx, by, nx, ny, nz, nq, lim, bias,
                              umbra)
            least = min(least, lo)
            if good or not ok:
                continue
            ok = _sub_blocks(pyr, levs, vw, lev, bx, by, x0, x1, y0, y1, nx, ny, nz, nq,
                             lim, bias, umbra)
    return ok, least


@jit.kernel
def _sub_blocks(pyr, levs, vw, lev, bx, by, x0, x1, y0, y1, nx, ny, nz, nq, lim, bias,
                umbra):  # pragma: no cover
    """direct._box_test's refinement of a failing block: its sub-blocks two levels down in
    the box, a failing one's two levels further."""
    st = min(lev - PYRAMID_FROM, 2)
    lv = lev - st
    for cy in range(max(by << st, y0 >> lv), min((by + 1) << st, (y1 >> lv) + 1)):
        for cx in range(max(bx << st, x0 >> lv), min((bx + 1) << st, (x1 >> lv) + 1)):
            if _block(pyr, levs, vw, lv, cx, cy, nx, ny, nz, nq, lim, bias, umbra)[0]:
                continue
            if lv == PYRAMID_FROM:
                return False
            t = min(lv - PYRAMID_FROM, 2)
            for ey in range(max(cy << t, y0 >> lv - t), min((cy + 1) << t, (y1 >> lv - t) + 1)):
                for ex in range(max(cx << t, x0 >> lv - t),
                                min((cx + 1) << t, (x1 >> lv - t) + 1)):
                    if not _block(pyr, levs, vw, lv - t, ex, ey, nx, ny, nz, nq, lim, bias,
                                  umbra)[0]:
                        return False
    return True


@jit.kernel
def _soft(lp, mats, ortho, scale, depths, face_view, single, res, skind, su, sv, srad, near,
          hashes, pyr, levs, view, px, py, pz, nx, ny, nz, qx, qy, qz, dist, bias, texel,
          hard):  # pragma: no cover
    """direct._soft of one receiver (qx, qy, qz its normal-offset point)."""
    sun = skind == CONE
    round_ = skind != RECTANGLE
    # the source's half-axes as it casts onto this receiver (direct._light_frame)
    if skind == RECTANGLE or skind == ELLIPSE:
        ux, uy, uz, vx, vy, vz = su[0], su[1], su[2], sv[0], sv[1], sv[2]
        extent = max(np.sqrt(ux * ux + uy * uy + uz * uz), np.sqrt(vx * vx + vy * vy + vz * vz))
    elif sun:
        rot = mats[0]
        ux, uy, uz = rot[0, 0] * srad, rot[0, 1] * srad, rot[0, 2] * srad
        vx, vy, vz = rot[1, 0] * srad, rot[1, 1] * srad, rot[1, 2] * srad
        extent = srad
    else:
        d = max(dist, 1e-300)
        wx, wy, wz = (qx - lp[0]) / d, (qy - lp[1]) / d, (qz - lp[2]) / d
        if abs(wz) < 0.9:
            ax, ay, az = 0.0, 0.0, 1.0
        else:
            ax, ay, az = 1.0, 0.0, 0.0
        e1x, e1y, e1z = wy * az - wz * ay, wz * ax - wx * az, wx * ay - wy * ax
        ln = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
        e1x, e1y, e1z = e1x / ln, e1y / ln, e1z / ln
        e2x, e2y, e2z = wy * e1z - wz * e1y, wz * e1x - wx * e1z, wx * e1y - wy * e1x
        ux, uy, uz = e1x * srad, e1y * srad, e1z * srad
        vx, vy, vz = e2x * srad, e2y * srad, e2z * srad
        extent = srad
    if sun:
        s = max(dist - near, 0.0)
        if s * srad >= texel:  # direct._soft: no farther than the nearest blocker's reach
            x0, x1, y0, y1, _, _ = _box(lp, mats, ortho, scale, face_view, single, res, view,
                                        sun, ux, uy, uz, vx, vy, vz, s, qx, qy, qz)
            least = _box_test(pyr, levs, view, x0, x1, y0, y1, qx, qy, qz, nx, ny, nz,
                              dist - bias, bias, False)[1]
            s = min(s, max(dist - least, 0.0))
        search_px = s * srad / texel
    else:
        s = SEARCH_AT
        search_px = extent * (1.0 - SEARCH_AT) / (SEARCH_AT * dist) / texel
    if not search_px >= 1.0:
        return hard
    settled = _settle(lp, mats, ortho, scale, face_view, single, res, pyr, levs, view,
                      sun, ux, uy, uz, vx, vy, vz, s, qx, qy, qz, nx, ny, nz, dist, bias)
    if settled >= 0.0:
        return settled
    return _pcss(lp, mats, ortho, scale, depths, face_view, single, res, sun, round_, srad,
                 extent, hashes, px, py, pz, ux, uy, uz, vx, vy, vz, s, qx, qy, qz, nx, ny, nz,
                 dist, bias, texel, hard)


@jit.kernel
def _settle(lp, mats, ortho, scale, face_view, single, res, pyr, levs, view, sun, ux, uy,
            uz, vx, vy, vz, s, qx, qy, qz, nx, ny, nz, dist, bias):  # pragma: no cover
    """direct._early_outs of one receiver: 1 lit, 0 umbra from the pyramid, as the taps would
    find; -1 not settled."""
    lim = dist - bias
    x0, x1, y0, y1, usable, _ = _box(lp, mats, ortho, scale, face_view, single, res, view, sun,
                                     ux, uy, uz, vx, vy, vz, s, qx, qy, qz)
    if usable:
        clear, least = _box_test(pyr, levs, view, x0, x1, y0, y1, qx, qy, qz, nx, ny, nz,
                                 lim, bias, False)
        if clear:
            return 1.0
        su_ = max(s, dist - least) if sun else min(s, min(max(least / dist, 1e-6), 1.0))
        x0, x1, y0, y1, _, inside = _box(lp, mats, ortho, scale, face_view, single, res, view,
                                         sun, ux, uy, uz, vx, vy, vz, su_, qx, qy, qz)
        if inside and _box_test(pyr, levs, view, x0, x1, y0, y1, qx, qy, qz, nx, ny,
                                nz, lim, bias, True)[0]:
            return 0.0
    elif not single and _clear_across(lp, mats, scale, res, pyr, levs, ux, uy, uz, vx,
                                      vy, vz, s, qx, qy, qz, nx, ny, nz, lim, bias):
        return 1.0
    return -1.0


@jit.kernel
def _pcss(lp, mats, ortho, scale, depths, face_view, single, res, sun, round_, srad, extent,
          hashes, px, py, pz, ux, uy, uz, vx, vy, vz, s, qx, qy, qz, nx, ny, nz, dist, bias,
          texel, hard):  # pragma: no cover
    """direct._soft's blocker search and filter of one receiver."""
    sa = _frac_hash(px, py, pz, hashes, 0)
    sb = _frac_hash(px, py, pz, hashes, 4)
    count = 0
    total = 0.0
    d_own = np.inf
    for k in range(SEARCH_SIDE * SEARCH_SIDE + 1):
        if k < SEARCH_SIDE * SEARCH_SIDE:
            x, y, z = _tap(k, SEARCH_SIDE, sa, sb, round_, ux, uy, uz, vx, vy, vz, s, sun, lp,
                           qx, qy, qz)
        else:
            x, y, z = qx, qy, qz  # the receiver's own texel
        dep, blocked = _lookup(lp, mats, ortho, scale, depths, face_view, single, res, x, y, z,
                               qx, qy, qz, nx, ny, nz, dist, bias)
        if k == SEARCH_SIDE * SEARCH_SIDE:
            d_own = dep
        if blocked:
            count += 1
            total += dep
    if count == 0:
        return 1.0
    t_b = total / count
    s, width_px = _footprint(sun, srad, extent, dist, texel, t_b)
    if not width_px >= 1.0:
        return hard
    # direct._soft: the own texel's surface nearer than the receiver and the blockers' mean,
    # its penumbra under a texel: the contact layer, resolved by the hard filter
    contact = (d_own > t_b and d_own < dist - bias
               and _footprint(sun, srad, extent, dist, texel, d_own)[1] < 1.0)
    if contact and hard <= 0.0:
        return 0.0
    # direct._tap_weights: each stratum's form factor (the sun's: equal)
    ax, ay, az = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    umbra = hard <= 0.0  # direct._soft: then a tap past every surface counts as blocked
    seen = 0.0
    total = 0.0
    for k in range(FILTER_SIDE * FILTER_SIDE):
        x, y, z = _tap(k, FILTER_SIDE, sa, sb, round_, ux, uy, uz, vx, vy, vz, s, sun, lp,
                       qx, qy, qz)
        if sun:
            w = 1.0
        else:
            a, b = _stratum(k, FILTER_SIDE, sa, sb, round_)
            dx = lp[0] + a * ux + b * vx - px
            dy = lp[1] + a * uy + b * vy - py
            dz = lp[2] + a * uz + b * vz - pz
            d2 = dx * dx + dy * dy + dz * dz
            w = (abs(dx * ax + dy * ay + dz * az) * max(dx * nx + dy * ny + dz * nz, 0.0)
                 / max(d2 * d2, 1e-300))
        total += w
        dep, blocked = _lookup(lp, mats, ortho, scale, depths, face_view, single, res, x, y, z,
                               qx, qy, qz, nx, ny, nz, dist, bias)
        if not (blocked or (umbra and dep == np.inf)):
            seen += w
    if not total > 0.0:  # no stratum faces the receiver: equal weights
        seen = 0.0
        for k in range(FILTER_SIDE * FILTER_SIDE):
            x, y, z = _tap(k, FILTER_SIDE, sa, sb, round_, ux, uy, uz, vx, vy, vz, s, sun,
                           lp, qx, qy, qz)
            dep, blocked = _lookup(lp, mats, ortho, scale, depths, face_view, single, res,
                                   x, y, z, qx, qy, qz, nx, ny, nz, dist, bias)
            if not (blocked or (umbra and dep == np.inf)):
                seen += 1.0
        total = FILTER_SIDE * FILTER_SIDE
    if contact:  # every stratum's ray also passes the contact layer
        return seen / total * hard
    return seen / total


@jit.kernel
def _footprint(sun, srad, extent, dist, texel, t_b):  # pragma: no cover
    """direct._footprint of one receiver: the taps' fraction s and the penumbra in texels."""
    if sun:
        s = max(dist - t_b, 0.0)
        return s, s * srad / texel
    s = min(max(t_b / dist, 1e-6), 1.0)
    return s, extent * (1.0 - s) / (s * dist) / texel
