"""Light emission in Blender/Cycles units and the views a light is rasterised from.

Radiant intensity (W/sr) per direction, matching Cycles:
- point: I = P / (4 pi), isotropic;
- spot: the point's intensity times Cycles' cone falloff
  smoothstep((cos a - cos(size/2)) / ((1 - cos(size/2)) * blend)) ("as if a point");
- area: a Lambertian emitter of total flux P, I(theta) = P cos(theta) / pi (treated as a
  point at its centre: the documented approximation, exact for distances >> its size);
- sun: irradiance E (W/m^2) on a surface facing it, no distance falloff.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import Light, look_at_matrix, orthographic_matrix, perspective_matrix

CUBE_DIRECTIONS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64
)
CUBE_UPS = np.array(
    [[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 1, 0], [0, 1, 0]], np.float64
)
SINGLE_FACE_MAX_CONE = np.radians(120.0)


@dataclass
class LightView:
    """One rasterisation of a light: perspective (tan_half > 0) or orthographic."""

    view: np.ndarray
    projection: np.ndarray
    ortho: bool
    tan_half: float = 1.0  # perspective: image plane [-t, t]^2 at distance 1
    half_extent: float = 1.0  # orthographic: view box [-h, h]^2
    face: int = -1  # cube face index, -1 for a single view


def _smoothstep01(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def intensity(light: Light, directions: np.ndarray) -> np.ndarray:
    """Radiant intensity (W/sr per unit colour) towards unit world directions (..., 3) -> (...)."""
    d = np.asarray(directions, np.float64)
    if light.type == "POINT":
        return np.full(d.shape[:-1], light.power / (4.0 * np.pi))
    axis = light.direction
    cos_a = d @ axis
    if light.type == "SPOT":
        cos_half = np.cos(0.5 * light.spot_size)
        smooth = (1.0 - cos_half) * light.spot_blend
        if smooth > 0:
            falloff = _smoothstep01((cos_a - cos_half) / smooth)
        else:
            falloff = (cos_a > cos_half).astype(np.float64)
        return light.power / (4.0 * np.pi) * falloff
    if light.type == "AREA":
        return light.power / np.pi * np.maximum(cos_a, 0.0)
    raise ValueError(f"light '{light.name}': intensity() is not defined for {light.type}")


def light_views(light: Light, bounds: tuple[np.ndarray, np.ndarray],
                fit: tuple[np.ndarray, np.ndarray] | None = None) -> list[LightView]:
    """The views that cover what ``light`` can illuminate inside the scene ``bounds``.

    ``fit`` (sun only): a box inside ``bounds`` the view's window is fitted to (a cascade
    [KD10 sec. 4.1]: finer texels where the cells are finer); the depth range still spans
    ``bounds``, so whatever stands between the sun and the box casts its shadow."""
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    extent = float(np.linalg.norm(hi - lo))
    if not np.isfinite(extent) or extent <= 0:
        extent = 1.0
    if light.type == "SUN":
        window = None if fit is None else tuple(np.asarray(b, np.float64) for b in fit)
        return [_sun_view(light, lo, hi, extent, window)]
    pos = light.position
    far_dist = float(np.max(np.linalg.norm(_corners(lo, hi) - pos, axis=1))) * 1.01
    far_dist = max(far_dist, extent * 1e-3)
    near = max(far_dist * 1e-4, 1e-9)
    if light.type == "SPOT" and light.spot_size <= SINGLE_FACE_MAX_CONE:
        half = 0.5 * light.spot_size * 1.02
        up = _any_up(light.direction)
        view = look_at_matrix(pos, pos + light.direction, up)
        return [LightView(view, perspective_matrix(2 * half, 1.0, near, far_dist), False,
                          tan_half=float(np.tan(half)))]
    views = []
    for face, (d, up) in enumerate(zip(CUBE_DIRECTIONS, CUBE_UPS)):
        view = look_at_matrix(pos, pos + d, up)
        proj = perspective_matrix(np.pi / 2, 1.0, near, far_dist)
        views.append(LightView(view, proj, False, tan_half=1.0, face=face))
    return views


def _sun_view(light: Light, lo, hi, extent, window=None) -> LightView:
    d = light.direction
    w_lo, w_hi = window if window is not None else (lo, hi)
    centre = 0.5 * (w_lo + w_hi)
    # Back off along the sun so that every corner of the whole bounds is in front of the eye.
    back = extent if window is None else float(np.max((_corners(lo, hi) - centre) @ -d)) + extent
    eye = centre - d * back
    view = look_at_matrix(eye, centre, _any_up(d))
    pts = (view @ np.c_[_corners(lo, hi), np.ones(8)].T).T[:, :3]
    fitted = (view @ np.c_[_corners(w_lo, w_hi), np.ones(8)].T).T[:, :3]
    half = float(np.max(np.abs(fitted[:, :2]))) * 1.01
    half = max(half, extent * 1e-6)
    near = max(float(-pts[:, 2].max()) - extent * 0.01, extent * 1e-6)
    far = float(-pts[:, 2].min()) + extent * 0.01
    return LightView(view, orthographic_matrix(half, half, near, far), True, half_extent=half)


def _corners(lo, hi) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])])


def _any_up(d) -> np.ndarray:
    return np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([0.0, 1.0, 0.0])


def texel_rays(view: LightView, rows: np.ndarray, cols: np.ndarray, width: int,
               height: int) -> tuple[np.ndarray, np.ndarray]:
    """World directions (N, 3) through the centres of texels (rows top-first, columns) of a
    perspective view, and their solid angles (N,).

    A texel of size du x dv on the image plane at distance 1, at plane coordinates (u, v),
    subtends du dv / (1 + u^2 + v^2)^(3/2) steradians.
    """
    t = view.tan_half
    u = ((np.asarray(cols) + 0.5) / width * 2.0 - 1.0) * t
    v = (1.0 - (np.asarray(rows) + 0.5) / height * 2.0) * t
    inv = np.linalg.inv(view.view)
    right, up, fwd = inv[:3, 0], inv[:3, 1], -inv[:3, 2]
    r2 = 1.0 + u * u + v * v
    dirs = (u[:, None] * right + v[:, None] * up + fwd) / np.sqrt(r2)[:, None]
    solid = (2.0 * t / width) * (2.0 * t / height) / (r2 * np.sqrt(r2))
    return dirs, solid
