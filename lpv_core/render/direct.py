"""Direct diffuse lighting with shadow maps, in Cycles' units.

Irradiance at a receiver (W/m^2): I(w) cos(theta) / d^2 for point, spot and area lights,
E cos(theta) for the sun. Cycles' "Diffuse Direct" pass is irradiance / pi (times the light
colour); multiplied by "Diffuse Color" it gives the reflected radiance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..runtime import jit, pool
from ..scene import lights as lights_mod
from ..scene.model import Light
from .raster import Rasterizer


@dataclass
class ShadowMap:
    """Per view: the light view and the distance (perspective) or depth (sun) of the occluder."""

    light: Light
    views: list
    depths: list  # (H, W) float32, inf where nothing was hit
    resolution: int
    _stacked: np.ndarray | None = field(default=None, repr=False, compare=False)

    def stacked(self) -> np.ndarray:
        """The depths as one (views, H, W) float32 array, made once (the compiled direct
        light reads it for every sample of every render)."""
        if self._stacked is None:
            self._stacked = np.stack([np.asarray(d, np.float32) for d in self.depths])
        return self._stacked


def render_shadow_map(raster: Rasterizer, light: Light, bounds, resolution: int) -> ShadowMap:
    """Rasterise the light's views and keep the nearest occluder per texel: its distance from
    the light (depth along the view for the sun), in float32 from the positions relative to
    the rasteriser's origin as they are read back (no float64 copy of the frame: a 1024^2 map
    took 100 ms that way, most of it converting and subtracting 3M floats twice)."""
    from ..scene import lights as lights_mod

    views, depths = [], []
    origin = np.asarray(raster.origin, np.float64)
    for view in lights_mod.light_views(light, bounds):
        (target,) = raster.read(view.view, view.projection, resolution, resolution,
                                ortho=view.ortho, targets=(0,))
        rel = target[..., :3]  # float32, relative to origin
        if view.ortho:  # depth = -(view @ p).z with p = rel + origin
            row = np.asarray(view.view, np.float64)[2]
            offset = float(row[:3] @ origin + row[3])
            depth = -(rel @ row[:3].astype(np.float32) + np.float32(offset))
        else:
            diff = rel - (np.asarray(light.position, np.float64) - origin).astype(np.float32)
            depth = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
        depths.append(np.where(target[..., 3] > 0.5, depth, np.float32(np.inf)))
        views.append(view)
    return ShadowMap(light, views, depths, resolution)


def _transform(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ m[:3, :3].T + m[:3, 3]


def visibility(shadow: ShadowMap, positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Fraction of the light seen by each receiver (M,), 2x2 percentage-closer filtered."""
    m = positions.shape[0]
    vis = np.ones(m)
    if not shadow.light.cast_shadow or m == 0:
        return vis
    res = shadow.resolution
    light = shadow.light
    if light.type == "SUN" or len(shadow.views) == 1:
        face_of = np.zeros(m, int)
    else:
        rel = positions - light.position
        axis = np.argmax(np.abs(rel), axis=1)
        sign = np.take_along_axis(rel, axis[:, None], 1)[:, 0] < 0
        cube_face = axis * 2 + sign
        face_index = {v.face: i for i, v in enumerate(shadow.views)}
        face_of = np.array([face_index.get(f, -1) for f in range(6)])[cube_face]
    for i, (view, depth) in enumerate(zip(shadow.views, shadow.depths)):
        sel = np.nonzero(face_of == i)[0]
        if sel.size == 0:
            continue
        p = positions[sel]
        n = normals[sel]
        if view.ortho:
            texel = 2.0 * view.half_extent / res
            p_off = p + n * texel * 1.5
            vp = _transform(view.view, p_off)
            u = vp[:, 0] / view.half_extent
            v = vp[:, 1] / view.half_extent
            d = -vp[:, 2]
            bias = texel * 1.5
        else:
            dist = np.linalg.norm(p - light.position, axis=1)
            texel = dist * (2.0 * view.tan_half / res) * 1.8  # worst case at the face corner
            p_off = p + n * texel[:, None]
            vp = _transform(view.view, p_off)
            z = np.maximum(-vp[:, 2], 1e-30)
            u = vp[:, 0] / z / view.tan_half
            v = vp[:, 1] / z / view.tan_half
            d = np.linalg.norm(p_off - light.position, axis=1)
            bias = texel * 1.5
        # Bilinear percentage-closer filtering over the 2x2 nearest texels.
        fx = (u + 1.0) * 0.5 * res - 0.5
        fy = (1.0 - v) * 0.5 * res - 0.5
        x0 = np.floor(fx).astype(int)
        y0 = np.floor(fy).astype(int)
        tx = fx - x0
        ty = fy - y0
        acc = np.zeros(sel.size)
        for dy, wy in ((0, 1.0 - ty), (1, ty)):
            for dx, wx in ((0, 1.0 - tx), (1, tx)):
                xs = np.clip(x0 + dx, 0, res - 1)
                ys = np.clip(y0 + dy, 0, res - 1)
                lit = d <= depth[ys, xs] + bias
                acc += wx * wy * lit
        inside = (np.abs(u) <= 1.0) & (np.abs(v) <= 1.0)
        vis[sel] = np.where(inside, acc, 1.0)
    return vis


def irradiance(
    light: Light, positions: np.ndarray, normals: np.ndarray, shadow: ShadowMap | None = None
) -> np.ndarray:
    """Direct irradiance (M, 3) in W/m^2 at receivers with unit normals (facing the viewer)."""
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    color = np.asarray(light.color, np.float64)
    if jit.enabled() and light.type in _KINDS and positions.shape[0]:
        return _irradiance_compiled(light, positions, normals, shadow)[:, None] * color
    if light.type == "SUN":
        cos_r = np.maximum(normals @ (-light.direction), 0.0)
        e = light.power * cos_r
    else:
        to_light = light.position - positions
        d2 = np.einsum("ij,ij->i", to_light, to_light)
        d2 = np.maximum(d2, 1e-30)
        w = to_light / np.sqrt(d2)[:, None]
        cos_r = np.maximum(np.einsum("ij,ij->i", normals, w), 0.0)
        e = lights_mod.intensity(light, -w) * cos_r / d2
    if shadow is not None:
        lit = e > 0
        vis = np.zeros_like(e)
        vis[lit] = visibility(shadow, positions[lit], normals[lit])
        e = e * vis
    return e[:, None] * color


_KINDS = {"POINT": 0, "SPOT": 1, "AREA": 2, "SUN": 3}


def _irradiance_compiled(light: Light, positions: np.ndarray, normals: np.ndarray,
                         shadow: ShadowMap | None) -> np.ndarray:
    """``irradiance`` per unit colour (M,) by ``_direct_kernel``: the same float64 arithmetic
    as the numpy code (lights.intensity, then ``visibility`` for the lit points), point by
    point on two threads (1280x720 pixels: numpy ~80 ms per light and sample)."""
    kind = _KINDS[light.type]
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
    return out


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
