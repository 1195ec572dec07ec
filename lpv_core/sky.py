"""The World as a light source: DIRECTIONS directions over the sphere, each carrying the World's
radiance averaged over its solid-angle cell, sky visibility from one orthographic shadow map
per direction, and the World seen along the camera's rays (the background).

Irradiance at a receiver with normal n: E = pi sum_k w_k L_k max(0, n.w_k) V_k / sum_k w_k
max(0, n.w_k); the denominator makes a uniform unoccluded World give exactly pi L on every
normal (the quadrature's own cosine error cancels). See docs/algorithm.md, "The World".
"""

from __future__ import annotations

import numpy as np

from .kernels import sky as _compiled
from .propagation.quadrature import quadrature_directions
from .runtime import jit
from .scene.model import Light
from .scene.world import World

# The GI's directions: the DOM transport's own count, 64 cells of 4 pi / 64 sr (~29 deg wide);
# the pixels' direct light takes 128, whose banding through a skylight is finer
# (docs/decisions.md: HDR-FLIP of Combined 0.40 with 64, 0.28 with 128, 0.22 with 256).
DIRECTIONS = 64
RENDER_DIRECTIONS = 128
# Antialias samples take turns over up to this many sets of the pixels' directions
# (render_directions): a pixel's mean integrates the sky over RENDER_DIRECTIONS x RENDER_SETS
# directions (sky_room's HDR-FLIP 0.244 -> 0.134, docs/decisions.md), for 4 x 32 MiB of maps
RENDER_SETS = 4
SHADOW_RESOLUTION = 256  # texels per side of each direction's map (64 maps: 16 MiB, 128: 32 MiB)
# The GI's surfels: a surface in front of a surfel's plane by more than this share of a texel
# hides the sky (depths and planes are exact to float32; a thinner layer is below the map)
FIRST_HIT_TEXELS = 0.05
MAX_MAP_SIDE = 512  # the map is box-averaged down to at most this many columns first
MIN_MAP_SIDE = 64  # and sampled at least this finely (a 1x1 uniform World included)


def lit(world: World | None) -> str:
    """Why ``world`` sends no light (empty string: it does)."""
    if world is None:
        return "no World"
    if not world.enabled:
        return "World light is switched off"
    r = np.asarray(world.radiance)
    if r.size == 0 or not np.isfinite(r).all() or float(r.max(initial=0.0)) <= 0.0:
        return "World is black"
    return ""


def map_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (H, W, 3) of an equirectangular map's texel centres (rows bottom-first,
    World's convention) and their solid angles (H, W)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(width) + 0.5) / width
    elev = (v - 0.5) * np.pi
    phi = (0.5 - u) * 2.0 * np.pi  # atan2(y, x)
    ce = np.cos(elev)[:, None]
    dirs = np.stack(np.broadcast_arrays(ce * np.cos(phi), ce * np.sin(phi),
                                        np.sin(elev)[:, None]), axis=-1)
    edges = np.sin((np.arange(height + 1) / height - 0.5) * np.pi)  # rows' z bounds
    solid = (2.0 * np.pi / width) * np.diff(edges)[:, None]
    return dirs, np.ascontiguousarray(np.broadcast_to(solid, (height, width)))


def render_directions(index: int = 0, sets: int = 1) -> np.ndarray:
    """Set ``index`` of ``sets`` sets of the pixels' directions: the RENDER_DIRECTIONS
    Fibonacci sphere turned about its pole by index / sets of its spiral's azimuth step (the
    golden angle), so the sets' spirals interleave: each set as evenly spread as the base one
    (its largest gap 13.5 deg), four together leave 9.2 deg (the 512-direction sphere 6.8)."""
    t = (index % max(sets, 1)) / max(sets, 1) * np.pi * (3.0 - np.sqrt(5.0))
    c, s = np.cos(t), np.sin(t)
    return quadrature_directions(RENDER_DIRECTIONS) @ np.array([[c, s, 0.0], [-s, c, 0.0],
                                                                [0.0, 0.0, 1.0]])


def cells(world: World, k: int | None = None,
          directions: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(directions (K, 3), solid angles w_k (K,), radiance (K, 3)): the World's map averaged
    over each direction's cell (the map texels nearest to it), weighted by texel solid angle;
    the ``k`` quadrature directions, or the given ``directions``."""
    r = np.asarray(world.radiance, np.float64).reshape(
        np.shape(world.radiance)[0], np.shape(world.radiance)[1], 3)
    h, w = r.shape[:2]
    step = max(1, w // MAX_MAP_SIDE)
    if step > 1:  # box average (texels of a row have equal solid angles; rows are weighted)
        h2, w2 = h // step, w // step
        _, sa = map_directions(h, w)
        r = r[:h2 * step, :w2 * step] * sa[:h2 * step, :w2 * step, None]
        r = r.reshape(h2, step, w2, step, 3).sum((1, 3))
        r /= sa[:h2 * step, :w2 * step].reshape(h2, step, w2, step).sum((1, 3))[..., None]
        h, w = h2, w2
    rep = max(1, -(-MIN_MAP_SIDE // w))  # nearest-texel upsampling of a small map
    r = np.repeat(np.repeat(r, rep, axis=0), rep, axis=1)
    dirs, solid = map_directions(*r.shape[:2])
    ks = quadrature_directions(k or DIRECTIONS) if directions is None else np.asarray(
        directions, np.float64)
    k = len(ks)
    near = np.argmax(dirs.reshape(-1, 3) @ ks.T, axis=1)
    sa = solid.reshape(-1)
    weight = np.bincount(near, sa, minlength=k)
    rad = np.stack([np.bincount(near, sa * r.reshape(-1, 3)[:, c], minlength=k)
                    for c in range(3)], axis=1) / np.maximum(weight, 1e-300)[:, None]
    return ks, weight, rad


def lookup(world: World, directions: np.ndarray) -> np.ndarray:
    """The World's radiance (N, 3) along unit ``directions`` (N, 3), bilinear in the map
    (wrapping around in longitude): what the camera sees where it sees no surface."""
    r = np.asarray(world.radiance, np.float32)
    h, w = r.shape[:2]
    d = np.asarray(directions, np.float64)
    u = 0.5 - np.arctan2(d[:, 1], d[:, 0]) / (2.0 * np.pi)
    v = 0.5 + np.arcsin(np.clip(d[:, 2], -1.0, 1.0)) / np.pi
    fx, fy = u * w - 0.5, np.clip(v * h - 0.5, 0.0, h - 1.0)
    x0, y0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    tx, ty = (fx - x0)[:, None], (fy - y0)[:, None]
    y1 = np.minimum(y0 + 1, h - 1)
    x0, x1 = x0 % w, (x0 + 1) % w
    return ((r[y0, x0] * (1 - tx) + r[y0, x1] * tx) * (1 - ty)
            + (r[y1, x0] * (1 - tx) + r[y1, x1] * tx) * ty)


def suns(directions: np.ndarray) -> list[Light]:
    """One unit SUN light per direction, shining along -w_k: render_shadow_map and the direct
    kernel give it max(0, n.w_k) V_k (hard: softening each over its cell's cone, PCSS, measured
    worse and 7x slower, docs/decisions.md); kept per direction set (the GI's, the pixels')."""
    key = np.asarray(directions, np.float64).tobytes()
    if key in _SUNS:
        return _SUNS[key]
    out = _SUNS.setdefault(key, []) if len(_SUNS) < 2 * (1 + RENDER_SETS) else []
    for i, d in enumerate(directions):
        z = np.asarray(d, np.float64)
        x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2] = x, np.cross(z, x), z
        out.append(Light(f"World direction {i}", "SUN", m, np.ones(3, np.float32), 1.0))
    return out


def shadow_maps(atlas, lights: list, bounds, fit, res: int) -> list:
    """The orthographic maps of the ``lights`` (suns) at ``res``, depth over ``bounds`` and
    windows on ``fit`` (lights.light_views), drawn together into ``atlas`` (render/atlas.py)."""
    from .render.direct import ShadowMap
    from .scene.lights import light_views

    key = tuple(np.asarray(b, np.float64).tobytes() for b in (*bounds, *fit))
    held = [v for ls, k, v in _VIEWS if ls is lights and k == key]
    views = held[0] if held else [light_views(s, bounds, fit)[0] for s in lights]
    _VIEWS[:] = [(lights, key, views),
                 *(e for e in _VIEWS if e[2] is not views)][:1 + RENDER_SETS]
    stack = atlas.render(views, res)
    maps = [ShadowMap(s, [v], [stack[i]], res, stack[i:i + 1], planes=False)
            for i, (s, v) in enumerate(zip(lights, views))]
    _STACK[:] = [(maps, stack), *_STACK[:RENDER_SETS]]
    return maps


def irradiance(directions: np.ndarray, weights: np.ndarray, radiance: np.ndarray, maps: list,
               positions: np.ndarray, normals: np.ndarray, pcf: bool = True) -> np.ndarray:
    """World irradiance (M, 3) W/m^2 at receivers: the normalised shadowed sum (module doc);
    ``maps`` the shadow maps of ``suns`` (None: unoccluded); each visibility the direct
    light's 2x2 percentage-closer test, or with ``pcf`` False the nearest texel's (``_one_tap``:
    the GI's surfels, whose sum over the directions smooths the steps)."""
    from .render import direct

    if jit.enabled() and maps and all(m is not None for m in maps) and len(positions):
        views = np.array([m.views[0].view for m in maps], np.float64)
        half = np.array([m.views[0].half_extent for m in maps], np.float64)
        return _compiled.irradiance(directions, weights, radiance, views, half,
                                    _stacked(maps), positions, normals, pcf,
                                    FIRST_HIT_TEXELS)
    pos = np.asarray(positions, np.float64)
    nrm = np.asarray(normals, np.float64)
    cos = np.maximum(nrm @ np.asarray(directions, np.float64).T, 0.0)  # (M, K)
    den = cos @ weights
    e = np.zeros((pos.shape[0], 3))
    for k, shadow in enumerate(maps):
        if not radiance[k].any():
            continue
        # the direct kernel tests visibility only where the cosine is positive
        vis_cos = cos[:, k] if shadow is None else cos[:, k] * _one_tap(shadow, pos, nrm) \
            if not pcf else direct.irradiance(shadow.light, pos, nrm, shadow)[:, 0]
        e += np.multiply.outer(weights[k] * vis_cos, radiance[k])
    return e * (np.pi / np.maximum(den, 1e-300))[:, None]


def _one_tap(shadow, pos: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    """Visibility (M,) of surfels in a sun's map, 1 or 0 from one texel each: the direct light's
    test of the point offset along its normal and biased by 1.5 texels (1 outside the window),
    and a first-hit test without either: 0 where the texel the surfel falls in holds a surface
    in front of the surfel's plane (extended to the texel's centre) by over FIRST_HIT_TEXELS
    of a texel. Surfels also sample hidden faces (a floor under a rug, a face buried in a
    solid), which the offset and bias alone light (docs/decisions.md)."""
    v, half, res = shadow.views[0].view, shadow.views[0].half_extent, shadow.resolution
    world = 2.0 * half / res
    off, depths = 1.5 * world, shadow.stacked()[0]
    q = [pos[:, 0] * v[r, 0] + pos[:, 1] * v[r, 1] + pos[:, 2] * v[r, 2] + v[r, 3]
         for r in range(3)]
    m = [nrm[:, 0] * v[r, 0] + nrm[:, 1] * v[r, 1] + nrm[:, 2] * v[r, 2] for r in range(3)]
    u, w = (q[0] + off * m[0]) / half, (q[1] + off * m[1]) / half
    inside = (np.abs(u) <= 1.0) & (np.abs(w) <= 1.0)
    x = np.minimum(((np.where(inside, u, 0.0) + 1.0) * 0.5 * res).astype(np.int64), res - 1)
    y = np.minimum(((1.0 - np.where(inside, w, 0.0)) * 0.5 * res).astype(np.int64), res - 1)
    lit = ~(inside & (-(q[2] + off * m[2]) > depths[y, x].astype(np.float64) + off))
    u, w = q[0] / half, q[1] / half
    lim = 1.0 + 2.0 / res  # a surfel on the LPV box's edge: in its window up to rounding
    inside = (np.abs(u) <= lim) & (np.abs(w) <= lim)
    x = np.clip(((np.where(inside, u, 0.0) + 1.0) * 0.5 * res).astype(np.int64), 0, res - 1)
    y = np.clip(((1.0 - np.where(inside, w, 0.0)) * 0.5 * res).astype(np.int64), 0, res - 1)
    cx, cy = ((x + 0.5) * 2.0 / res - 1.0) * half, (1.0 - (y + 0.5) * 2.0 / res) * half
    plane = (m[0] * (cx - q[0]) + m[1] * (cy - q[1])) / np.maximum(m[2], 1e-12) - q[2]
    lit &= ~(inside & (depths[y, x].astype(np.float64) < plane - FIRST_HIT_TEXELS * world))
    return lit.astype(np.float64)


# the last 1 + RENDER_SETS (the GI's and the pixels' sets): [(maps list, their depths (K, R, R)
# float32)] and [(suns, bounds and window bytes, their views)]
_STACK: list = []
_SUNS: dict = {}  # direction set's bytes -> its suns
_VIEWS: list = []


def _stacked(maps: list) -> np.ndarray:
    """The maps' depths as one (K, R, R) float32 array, kept for the last 1 + RENDER_SETS
    lists of maps (the GI's and the pixels' sets)."""
    for held, stack in _STACK:
        if held is maps:
            return stack
    _STACK[:] = [(maps, np.stack([m.stacked()[0] for m in maps])), *_STACK[:RENDER_SETS]]
    return _STACK[0][1]


# An image's sun (split_sun): the region around the map's brightest texel is a sun when it fits
# in a cone of SUN_MAX_DIAMETER and carries SUN_MIN_SHARE of the map's light. 8 deg: a sun
# straddling 2 x 2 texels of the coarsest map (a 128 x 64 bake: a 6.4 deg cone) fits, with
# room for a lens' glare; under half the pixels' direction spacing (~20 deg) it undoes.
SUN_MAX_DIAMETER = float(np.radians(8.0))
# A lamp costs what a World direction costs (a shadow map, an RSM): worth it when it carries
# more than an average direction's share of the light, 1 / DIRECTIONS.
SUN_MIN_SHARE = 1.0 / DIRECTIONS
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance (Blender's scene linear)


def split_sun(radiance: np.ndarray) -> tuple[np.ndarray, tuple | None]:
    """(map, sun or None): an equirect ``radiance`` map (H, W, 3, bottom-first) split into the map
    with its sun replaced by the sun's surroundings' level and the sun as (rgb irradiance W/m^2
    normal to it, unit direction, angular diameter); map + sun keep the map's light exactly.
    The sun is the component of {luminance > t} around the brightest texel for the lowest t
    that keeps it within SUN_MAX_DIAMETER's cone, if it carries SUN_MIN_SHARE (docs/decisions.md)."""
    import heapq

    r = np.maximum(np.nan_to_num(np.asarray(radiance, np.float32), nan=0.0, posinf=0.0), 0.0)
    h, w = r.shape[:2]
    dirs, sa = map_directions(h, w)
    y, sa_f = (r.reshape(-1, 3) @ LUMA), sa.reshape(-1)
    total = float(y @ sa_f)
    bound = 2.0 * np.pi * (1.0 - np.cos(SUN_MAX_DIAMETER / 2.0))
    start = int(np.argmax(y))
    if not total > 0.0 or sa_f[start] > bound:
        return r, None
    # Priority flood from the peak: the texels popped before the first one below all earlier
    # ones form the component of {luminance > that one's}; keep the largest within the bound.
    heap, seen, order = [(-y[start], start)], {start}, []
    omega, lowest, cut = 0.0, np.inf, 0
    while heap:
        v, i = heapq.heappop(heap)
        if -v < lowest:
            cut, lowest = len(order), -v
        if omega + sa_f[i] > bound:
            break
        order.append(i)
        omega += sa_f[i]
        for j in _neighbours(i, h, w):
            if j not in seen:
                seen.add(j)
                heapq.heappush(heap, (-y[j], j))
    region = np.array(order[:cut], np.int64)
    if not len(region):
        return r, None
    inside = set(order[:cut])
    ring = np.array(sorted({j for i in order[:cut] for j in _neighbours(i, h, w)} - inside))
    flat = r.reshape(-1, 3)
    level = (flat[ring] * sa_f[ring, None]).sum(0) / sa_f[ring].sum()
    level = np.minimum(level, flat[region].min(0)).astype(np.float32)  # no negative channel
    excess = (flat[region].astype(np.float64) - level) * sa_f[region, None]
    e = excess.sum(0)
    lum = excess @ LUMA
    if not float(e @ LUMA) >= SUN_MIN_SHARE * total:
        return r, None
    d = lum @ dirs.reshape(-1, 3)[region]
    # diameter of the uniform disc with the region's light at its peak radiance (excess)
    peak = float((lum / sa_f[region]).max())
    cone = min(float(e @ LUMA) / peak, bound) if peak > 0 else bound
    out = r.copy()
    out.reshape(-1, 3)[region] = level
    return out, (e.astype(np.float32), d / np.linalg.norm(d),
                 float(2.0 * np.arccos(1.0 - cone / (2.0 * np.pi))))


def _neighbours(i: int, h: int, w: int):
    """Flat indices of texel ``i``'s 8 neighbours in an (h, w) equirect map: columns wrap, the
    top and bottom rows also touch the texel across the pole."""
    row, col = divmod(int(i), w)
    for rr in (row - 1, row, row + 1):
        if 0 <= rr < h:
            for cc in (col - 1, col, col + 1):
                yield rr * w + cc % w
    if row in (0, h - 1):
        yield row * w + (col + w // 2) % w
