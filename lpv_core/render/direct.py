"""Direct diffuse lighting with shadow maps, in Cycles' units.

Irradiance at a receiver (W/m^2): I(w) cos(theta) / d^2 for point, spot and area lights,
E cos(theta) for the sun. Cycles' "Diffuse Direct" pass is irradiance / pi (times the light
colour); multiplied by "Diffuse Color" it gives the reflected radiance.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..kernels import direct as _compiled
from ..runtime import jit
from ..scene import lights as lights_mod
from ..scene.model import Light
from .raster import Rasterizer


@dataclass
class ShadowMap:
    """Per view: the light view and the distance (perspective) or depth (sun) of the occluder."""

    light: Light
    views: list
    depths: list  # (H, W) float32, inf where nothing was hit (views of one stacked array)
    resolution: int
    _stacked: np.ndarray | None = field(default=None, repr=False, compare=False)

    def stacked(self) -> np.ndarray:
        """The depths as one (views, H, W) float32 array (the compiled direct light reads it
        for every sample of every render); render_shadow_map writes the faces into it."""
        if self._stacked is None:
            self._stacked = np.stack([np.asarray(d, np.float32) for d in self.depths])
        return self._stacked

    @property
    def nbytes(self) -> int:
        """Bytes the map holds (the shadow budget counts them, render/shadows.py)."""
        return int(self.stacked().nbytes)


def render_shadow_map(raster: Rasterizer, light: Light, bounds, resolution: int) -> ShadowMap:
    """Rasterise the light's views and keep the nearest occluder per texel: its distance from
    the light (depth along the view for the sun), in float32 from the positions relative to
    the rasteriser's origin as they are read back (no float64 copy of the frame: a 1024^2 map
    took 100 ms that way, most of it converting and subtracting 3M floats twice)."""
    from ..scene import lights as lights_mod

    views = lights_mod.light_views(light, bounds)
    stack = np.empty((len(views), resolution, resolution), np.float32)
    origin = np.asarray(raster.origin, np.float64)
    for i, view in enumerate(views):
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
        np.copyto(stack[i], np.where(target[..., 3] > 0.5, depth, np.float32(np.inf)))
    return ShadowMap(light, views, list(stack), resolution, stack)


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
    if jit.enabled() and light.type in _compiled.KINDS and np.shape(positions)[0]:
        return _compiled.irradiance(light, positions, normals, shadow)
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    color = np.asarray(light.color, np.float64)
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
