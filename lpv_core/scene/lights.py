"""Light emission in Blender/Cycles units and the views a light is rasterised from.

Radiant intensity (W/sr) per direction, matching Cycles:
- point: I = P / (4 pi), isotropic;
- spot: the point's intensity times Cycles' cone falloff
  smoothstep((cos a - cos(size/2)) / ((1 - cos(size/2)) * blend)) ("as if a point");
  with a radius r both are Cycles' round emitter of radiance I / (pi r^2), a disk facing the
  receiver (Soft Falloff, Blender's default) or a sphere, seen as a cone of directions cut at
  the receiver's horizon (round_geometry);
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


def cone_projected_solid_angle(cos_t: np.ndarray, sin2_a: np.ndarray) -> np.ndarray:
    """The cosine-weighted solid angle above the horizon of a cone of directions of half-angle
    a (sin^2 a given) whose axis makes angle t with the normal: pi sin^2 a cos t while the cone
    is above the horizon, 0 below it, and between them the horizon-clipped closed form of the
    spherical cap [Snyder 1996, "Area light sources for real-time graphics"]; a cone of
    sin^2 a >= 1 (a receiver inside a sphere) sees the whole hemisphere: pi."""
    c = np.clip(np.asarray(cos_t, np.float64), -1.0, 1.0)
    s2 = np.minimum(np.asarray(sin2_a, np.float64), 1.0)
    c, s2 = np.broadcast_arrays(c, s2)
    sin_a = np.sqrt(s2)
    out = np.where(c >= sin_a, np.pi * s2 * c, 0.0)
    cut = (c < sin_a) & (c > -sin_a)
    if np.any(cut):
        cc, ss = c[cut], s2[cut]
        st = np.sqrt(np.maximum(1.0 - cc * cc, 1e-30))
        x = np.sqrt(np.maximum(1.0 / ss - 1.0, 0.0))  # cot a
        y = np.clip(-x * cc / st, -1.0, 1.0)
        g = st * np.sqrt(1.0 - y * y)
        out[cut] = (cc * np.arccos(y) - x * g) * ss + np.arctan2(g, x)
    return np.where(np.asarray(sin2_a) >= 1.0, np.pi, out)


def round_geometry(light: Light, cos_r: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """Irradiance per unit radiant intensity (E / I, m^-2) of a POINT or SPOT light at
    receivers whose normal makes ``cos_r`` (signed) with the direction to its centre, at
    squared distance ``d2``: cos_r / d2 without a radius; with one, Cycles' emitter of
    radiance I / (pi r^2) (kernel/light/point.h): a disk facing the receiver (sin^2 a =
    r^2 / (r^2 + d^2), Soft Falloff) or a sphere (r^2 / d^2), cut at the horizon
    (cone_projected_solid_angle); far away both tend to the point's cos_r / d^2."""
    cos_r = np.asarray(cos_r, np.float64)
    d2 = np.maximum(np.asarray(d2, np.float64), 1e-30)
    r2 = float(light.radius) ** 2
    if not r2 > 0:
        return np.maximum(cos_r, 0.0) / d2
    sin2 = r2 / (r2 + d2) if light.soft_falloff else np.minimum(r2 / d2, 1.0)
    return cone_projected_solid_angle(cos_r, sin2) / (np.pi * r2)


def inside_sphere(light: Light, d2: np.ndarray) -> np.ndarray:
    """Receivers inside a SPOT light's sphere (Soft Falloff off), which Cycles lights without
    the spot's cone falloff (kernel/light/spot.h): there its intensity is the point's."""
    d2 = np.asarray(d2, np.float64)
    if light.type != "SPOT" or light.soft_falloff or not light.radius > 0:
        return np.zeros(d2.shape, bool)
    return d2 <= float(light.radius) ** 2


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


# --------------------------------------------------------------------------- area emitters

POLYGON_SIDES = 32  # a disk or ellipse emitter as a polygon of this many sides (same area)
SPREAD_SPLIT = 4  # patches per side when a spread below pi weights the emitter's parts


def area_frame(light: Light) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An area light's centre, world half-extent vectors along its local X and Y (the
    object's scale included, as Cycles sizes the emitter) and unit emitting normal."""
    m = np.asarray(light.matrix, np.float64)
    sx, sy = (float(s) for s in light.size)
    return light.position, m[:3, 0] * (0.5 * sx), m[:3, 1] * (0.5 * sy), light.direction


def is_round(light: Light) -> bool:
    return light.type == "AREA" and light.shape in ("DISK", "ELLIPSE")


def emitter_area(light: Light) -> float:
    """World area (m^2) of an area light: 4 |u x v| for a rectangle, pi |u x v| for an ellipse."""
    _, u, v, _ = area_frame(light)
    cross = float(np.linalg.norm(np.cross(u, v)))
    return (np.pi if is_round(light) else 4.0) * cross


def area_radiance(light: Light) -> float:
    """Radiance (W sr^-1 m^-2 per unit colour) of an area light: P / (pi A), Cycles' units
    (tests/test_reference.py measures them; normalize off is folded into P by extraction)."""
    area = emitter_area(light)
    return light.power / (np.pi * area) if area > 0 else 0.0


def spread_constants(light: Light) -> tuple[float, float]:
    """(tan(spread / 2), normalisation) of Cycles' soft-box spread (kernel/light/area.h
    area_light_spread_attenuation; light.cpp): the radiance towards angle t off the normal is
    scaled by max((tan(s/2) - tan t) * norm, 0), norm = 1 / (tan(s/2) - s/2) (3 / (s/2)^3
    below s/2 = 0.05), which keeps the emitted power. (0, 0) for the full spread pi."""
    half = 0.5 * float(light.spread)
    if half >= 0.5 * np.pi - 1e-9:
        return 0.0, 0.0
    half = max(half, 1e-6)  # Cycles' zero spread is a collimated beam: the narrowest here
    norm = 1.0 / (np.tan(half) - half) if half > 0.05 else 3.0 / half**3
    return float(np.tan(half)), float(norm)


def concentric(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shirley & Chiu's concentric map of [-1, 1]^2 onto the unit disk (keeps strata)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    big = np.abs(a) > np.abs(b)
    safe_a = np.where(a == 0, 1.0, a)
    safe_b = np.where(b == 0, 1.0, b)
    r = np.where(big, a, b)
    phi = np.where(big, 0.25 * np.pi * b / safe_a, 0.5 * np.pi - 0.25 * np.pi * a / safe_b)
    r = np.where((a == 0) & (b == 0), 0.0, r)
    return r * np.cos(phi), r * np.sin(phi)


def area_patches(light: Light) -> np.ndarray:
    """The emitter as convex polygons (S, V, 3) in world space, vertices in one winding.

    A rectangle is itself (S = 1, V = 4); a disk or ellipse a POLYGON_SIDES-gon of the same
    area. With a spread below pi the emitter is split into SPREAD_SPLIT^2 quads (rectangle:
    a grid; ellipse: the concentric map of the grid, rescaled to the ellipse's area) so that
    each patch's spread weight is taken at its own centre."""
    c, u, v, _ = area_frame(light)
    round_ = is_round(light)
    if spread_constants(light)[1] == 0.0:
        if not round_:
            corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], np.float64)
        else:
            k = POLYGON_SIDES
            ang = 2.0 * np.pi * np.arange(k) / k
            grow = np.sqrt(2.0 * np.pi / (k * np.sin(2.0 * np.pi / k)))  # polygon area = pi
            corners = np.c_[np.cos(ang), np.sin(ang)] * grow
        return (c + corners[:, :1] * u + corners[:, 1:] * v)[None]
    n = SPREAD_SPLIT
    g = np.linspace(-1.0, 1.0, n + 1)
    quads = []
    for i in range(n):
        for j in range(n):
            quads.append([(g[i], g[j]), (g[i + 1], g[j]), (g[i + 1], g[j + 1]),
                          (g[i], g[j + 1])])
    q = np.array(quads, np.float64)  # (S, 4, 2)
    if round_:
        x, y = concentric(q[..., 0], q[..., 1])
        q = np.stack([x, y], -1)
        e1, e2 = q[:, 1] - q[:, 0], q[:, 3] - q[:, 0]
        f1, f2 = q[:, 1] - q[:, 2], q[:, 3] - q[:, 2]
        area = 0.5 * np.sum(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
                            + np.abs(f1[:, 0] * f2[:, 1] - f1[:, 1] * f2[:, 0]))
        q = q * np.sqrt(np.pi / area)
    return c + q[..., :1] * u + q[..., 1:] * v


def _edge_term(a: np.ndarray, b: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Lambert's edge term gamma (n . (a x b) / |a x b|), gamma the angle a, b subtend."""
    c = np.cross(a, b)
    s = np.sqrt(np.einsum("...k,...k->...", c, c))
    gamma = np.arctan2(s, np.einsum("...k,...k->...", a, b))
    cn = np.einsum("...k,...k->...", c, n)
    return np.where(s > 1e-300, gamma * cn / np.where(s > 1e-300, s, 1.0), 0.0)


def polygon_irradiance(verts: np.ndarray, positions: np.ndarray,
                       normals: np.ndarray) -> np.ndarray:
    """Irradiance (M,) at receivers (unit normals) from a convex polygon (V, 3) of unit
    radiance (or one polygon per receiver, (M, V, 3)), by Lambert's contour integral
    E = 1/2 |sum gamma_i n . u_i| [Lambert 1760; Arvo 1995], with the polygon clipped to each
    receiver's upper hemisphere (the part below the tangent plane sends nothing; the clip adds
    the edge along the horizon)."""
    p = np.asarray(positions, np.float64)
    n = np.asarray(normals, np.float64)
    v = np.asarray(verts, np.float64)
    a = (v if v.ndim == 3 else v[None]) - p[:, None]  # (M, V, 3)
    b = np.roll(a, -1, axis=1)
    ha = np.einsum("mvk,mk->mv", a, n)
    hb = np.roll(ha, -1, axis=1)
    up_a, up_b = ha >= 0.0, hb >= 0.0
    cross = up_a != up_b
    t = np.where(cross, ha / np.where(cross, ha - hb, 1.0), 0.0)
    x = a + t[..., None] * (b - a)
    start = np.where(up_a[..., None], a, x)
    end = np.where(up_b[..., None], b, x)
    nn = n[:, None]
    total = np.sum(np.where(up_a | up_b, _edge_term(start, end, nn), 0.0), axis=1)
    leave, enter = up_a & ~up_b, ~up_a & up_b
    x_leave = np.einsum("mv,mvk->mk", leave.astype(np.float64), x)
    x_enter = np.einsum("mv,mvk->mk", enter.astype(np.float64), x)
    closing = leave.any(axis=1) & enter.any(axis=1)
    total = total + np.where(closing, _edge_term(x_leave, x_enter, n), 0.0)
    return 0.5 * np.abs(total)


def area_irradiance(light: Light, positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Unoccluded irradiance (M,) per unit colour of an area light at receivers: its radiance
    P / (pi A) times the exact polygon integral (area_patches), each patch weighted by
    Cycles' spread attenuation towards the receiver; nothing behind the emitter."""
    p = np.asarray(positions, np.float64)
    n = np.asarray(normals, np.float64)
    c, _, _, axis = area_frame(light)
    front = (p - c) @ axis > 0.0
    patches = area_patches(light)
    tan_half, norm = spread_constants(light)
    e = np.zeros(p.shape[0])
    for poly in patches:
        part = polygon_irradiance(poly, p, n)
        if norm > 0.0:
            to = p - poly.mean(axis=0)
            cos_t = (to @ axis) / np.maximum(np.linalg.norm(to, axis=1), 1e-300)
            tan_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0)) / np.maximum(cos_t, 1e-300)
            part = part * np.maximum((tan_half - tan_t) * norm, 0.0)
        e = e + part
    return np.where(front, area_radiance(light) * e, 0.0)
