"""Direct diffuse lighting with shadow maps, in Cycles' units.

Irradiance at a receiver (W/m^2): I(w) cos(theta) / d^2 for point and spot lights (with a
radius: Cycles' round emitter cut at the horizon, lights.round_geometry), E cos(theta)
for the sun, and for area lights their radiance P / (pi A) times the exact contour integral
over the emitter (lights.area_irradiance). Cycles' "Diffuse Direct" pass is irradiance / pi
(times the light colour); multiplied by "Diffuse Color" it gives the reflected radiance.

Shadows: a hard light (no radius, no sun angle) is 2x2 percentage-closer filtered; a light
with a size casts percentage-closer soft shadows [Fernando 2005] on the same map: a blocker
search over the light's footprint, the penumbra from similar triangles, then stratified taps
over it, every tap compared against the receiver's own plane through that texel's centre and
weighted by its stratum's form factor (docs/algorithm.md, "Soft shadows").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..kernels import direct as _compiled
from ..runtime import jit
from ..scene import lights as lights_mod
from ..scene.model import CASTS_NO_SHADOW, Light
from .raster import Rasterizer

SEARCH_SIDE = 6  # blocker search: 6 x 6 strata over the light, plus the receiver's own texel
FILTER_SIDE = 6  # percentage-closer taps: 6 x 6 strata over the light
SEARCH_AT = 0.5  # the search looks for blockers over the half of the way nearer the receiver
PYRAMID_FROM = 2  # the early outs' finest blocks: 4 x 4 texels (8 channels of 1/12 the map)
REFINE = 2  # a failing block is read again as its sub-blocks 2 and then 4 levels down
# The receiver's offset along its normal, in texels: in front of its own surface at every
# slope a 2 x 2 filter reads (sqrt 2 texels, _plane_depth), so the depth bias only absorbs
# float32 rounding; a bias of texels lit a receiver through a wall closer than that (a thin
# wall's edge, docs/decisions.md)
OFFSET_TEXELS = 1.5
BIAS_TEXELS = 0.001
# A receiver this many texels on the light's side of an occluder's plane is not shaded by it
# (_beside_occluder): a plane rebuilt from one-texel differences is good to a small fraction
# of a texel on a flat surface
BESIDE_TEXELS = 0.02
# Source kinds (Source.kind), shared with kernels/direct.py
HARD, SPHERE, RECTANGLE, ELLIPSE, CONE = 0, 1, 2, 3, 4


@dataclass
class ShadowMap:
    """Per view: the light view and the distance (perspective) or depth (sun) of the occluder."""

    light: Light
    views: list
    depths: list  # (H, W) float32, inf where nothing was hit (views of one stacked array)
    resolution: int
    _stacked: np.ndarray | None = field(default=None, repr=False, compare=False)
    _pyramid: tuple | None = field(default=None, repr=False, compare=False)
    # the taps test each texel's occluder plane (_plane_depth); False: its centre's depth, for
    # the World's 128 maps, where the planes' 9 reads a tap cost the direct light 5.8x
    planes: bool = True

    def stacked(self) -> np.ndarray:
        """The depths as one (views, H, W) float32 array (the compiled direct light reads it
        for every sample of every render); render_shadow_map writes the faces into it."""
        if self._stacked is None:
            self._stacked = np.stack([np.asarray(d, np.float32) for d in self.depths])
        return self._stacked

    def pyramid(self) -> tuple:
        """(blocks (views, T, 8) float32, offsets, sizes): per 2^L x 2^L texel block of each
        view, level L's sizes[L]^2 blocks row by row from offsets[L], levels PYRAMID_FROM..:
        the least and greatest occluder depth and the bounding box (min xyz, max xyz, rounded
        outward) of the occluders' points (texels that hit nothing left out). Built once per
        map (2/3 of its bytes more); the soft shadows' early outs read it."""
        if self._pyramid is None:
            res = self.resolution
            views = []
            for view, depth in zip(self.views, self.stacked()):
                eye = np.asarray(self.light.position, np.float64)
                base = (_compiled.pyramid_blocks(view, depth, eye, 1 << PYRAMID_FROM)
                        if jit.enabled() else _blocks(view, depth, eye))
                levels = []
                for ch in range(8):
                    fill, op = (np.inf, np.minimum) if ch in (0, 2, 3, 4) else (-np.inf,
                                                                               np.maximum)
                    c = base[..., ch]
                    c32 = c.astype(np.float32)  # outward: a bound stays a bound in float32
                    c32 = np.where(op(c32, c) != c32, np.nextafter(c32, np.float32(fill)), c32)
                    levels.append([c32])
                    while c32.shape[0] > 1:
                        if c32.shape[0] % 2:
                            c32 = np.pad(c32, ((0, 1), (0, 1)), constant_values=fill)
                        c32 = _halve(c32, op)
                        levels[-1].append(c32)
                views.append(np.stack([np.concatenate([lv.ravel() for lv in ch])
                                       for ch in levels], -1))  # a block's 8: one cache line
            sizes = [-(-res // (1 << k)) for k in range(PYRAMID_FROM + len(levels[0]))]
            counts = [0] * PYRAMID_FROM + [z * z for z in sizes[PYRAMID_FROM:]]
            offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
            offsets[:PYRAMID_FROM] = 0
            self._pyramid = (np.array(views, np.float32), offsets, np.array(sizes, np.int64))
        return self._pyramid

    @property
    def nbytes(self) -> int:
        """Bytes the map holds, its pyramid once built (the shadow budget counts them,
        render/shadows.py)."""
        extra = 0 if self._pyramid is None else self._pyramid[0].nbytes
        return int(self.stacked().nbytes) + int(extra)


def _blocks(view, depth: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """(n, n, 8) float64 of ShadowMap.pyramid's finest level: per block of 2^PYRAMID_FROM
    texels a side the least and greatest depth and the box (min xyz, max xyz) of the points
    the texel centres' rays (_lookup's) hit."""
    res, b = depth.shape[0], 1 << PYRAMID_FROM
    n0 = -(-res // b)
    pad = ((0, n0 * b - res), (0, n0 * b - res))
    uc = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    gu, gv = np.meshgrid(uc, -uc)
    m = np.asarray(view.view, np.float64)
    rot = m[:3, :3]
    hit = np.isfinite(depth)[..., None]
    d = np.where(hit, depth.astype(np.float64)[..., None], 0.0)
    if view.ortho:
        sc = view.half_extent
        y0 = ((gu * sc - m[0, 3])[..., None] * rot[0]
              + (gv * sc - m[1, 3])[..., None] * rot[1] - m[2, 3] * rot[2])
        pts = y0 - d * rot[2]
    else:
        sc = view.tan_half
        f = (gu * sc)[..., None] * rot[0] + (gv * sc)[..., None] * rot[1] - rot[2]
        f /= np.sqrt(np.einsum("ijk,ijk->ij", f, f))[..., None]
        pts = eye + d * f
    lo, hi = np.where(hit, pts, np.inf), np.where(hit, pts, -np.inf)
    chans = [(depth.astype(np.float64), np.inf, np.minimum),
             (depth.astype(np.float64), -np.inf, np.maximum)]
    chans += [(lo[..., i], np.inf, np.minimum) for i in range(3)]
    chans += [(hi[..., i], -np.inf, np.maximum) for i in range(3)]
    out = []
    for c, fill, op in chans:
        c = np.pad(c, pad, constant_values=fill)
        for _ in range(PYRAMID_FROM):
            c = _halve(c, op)
        out.append(c)
    return np.stack(out, -1)


def _halve(c: np.ndarray, op) -> np.ndarray:
    """op (np.minimum, np.maximum) over the 2 x 2 blocks of an even-sided square array."""
    return op(op(c[0::2, 0::2], c[1::2, 0::2]), op(c[0::2, 1::2], c[1::2, 1::2]))


@dataclass
class Source:
    """What casts the penumbra, seen from the shadow map's eye: ``kind`` HARD (a point),
    SPHERE (a ball of ``radius``: a disk facing each receiver), RECTANGLE or ELLIPSE (half
    extents ``u``, ``v`` in world space) or CONE (the sun: ``radius`` = tan of its angular
    radius)."""

    kind: int
    radius: float = 0.0
    u: np.ndarray = field(default_factory=lambda: np.zeros(3))
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))


def source_of(light: Light, radius: float | None = None) -> Source:
    """The light's own Source, or with ``radius`` a sphere of that radius at the light's
    position (for a sun: an angular radius in radians), for callers whose shadow map stands
    for another emitter (a patch, a piece of sky)."""
    if light.type == "SUN":
        half = 0.5 * float(light.angle) if radius is None else float(radius)
        half = min(max(half, 0.0), 0.25 * np.pi)
        return Source(CONE, float(np.tan(half))) if half > 0 else Source(HARD)
    if radius is None and light.type == "AREA":
        _, u, v, _ = lights_mod.area_frame(light)
        return Source(ELLIPSE if lights_mod.is_round(light) else RECTANGLE, 0.0, u, v)
    r = float(light.radius if radius is None else radius)
    return Source(SPHERE, r) if r > 0 and np.isfinite(r) else Source(HARD)


def render_shadow_map(raster: Rasterizer, light: Light, bounds, resolution: int,
                      fit=None) -> ShadowMap:
    """Rasterise the light's views and keep the nearest occluder per texel (objects that cast
    no shadow left out): its distance from
    the light (depth along the view for the sun), in float32 from the positions relative to
    the rasteriser's origin as they are read back (no float64 copy of the frame: a 1024^2 map
    took 100 ms that way, most of it converting and subtracting 3M floats twice)."""
    views = lights_mod.light_views(light, bounds, fit)  # fit: a sun's window (light_views)
    stack = np.empty((len(views), resolution, resolution), np.float32)
    origin = np.asarray(raster.origin, np.float64)
    for i, view in enumerate(views):
        (target,) = raster.read(view.view, view.projection, resolution, resolution,
                                ortho=view.ortho, targets=(0,), hide=CASTS_NO_SHADOW)
        rel = target[..., :3]  # float32, relative to origin
        if view.ortho:  # depth = -(view @ p).z with p = rel + origin
            row = np.asarray(view.view, np.float64)[2]
            offset = float(row[:3] @ origin + row[3])
            depth = -(rel @ row[:3].astype(np.float32) + np.float32(offset))
        else:
            diff = rel - (np.asarray(light.position, np.float64) - origin).astype(np.float32)
            depth = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
        np.copyto(stack[i], np.where(target[..., 3] > 0.5, depth, np.float32(np.inf)))
    shadow = ShadowMap(light, views, list(stack), resolution, stack)
    if source_of(light).kind != HARD:
        shadow.pyramid()  # before the cache counts the map's bytes
    return shadow


def _transform(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ m[:3, :3].T + m[:3, 3]


def _ortho_near(view) -> float:
    """The near plane's depth of an orthographic view, from its OpenGL projection."""
    proj = np.asarray(view.projection, np.float64)
    return float((proj[2, 3] + 1.0) / proj[2, 2])


def _hash(p: np.ndarray, k: tuple[float, float, float], scale: float) -> np.ndarray:
    """A per-receiver number in [0, 1) from its position (the taps' rotation: no banding)."""
    x = np.sin(p[:, 0] * k[0] + p[:, 1] * k[1] + p[:, 2] * k[2]) * scale
    return x - np.floor(x)


HASH_A = ((12.9898, 78.233, 37.719), 43758.5453)
HASH_B = ((39.3468, 11.135, 83.155), 24634.6345)


def _strata(side: int, sa: np.ndarray, sb: np.ndarray, round_: bool):
    """(M, side^2) points of a side x side stratified pattern, toroidally shifted per
    receiver by (sa, sb) [Cranley & Patterson 1976], on [-1, 1]^2 or the unit disk."""
    cell = (np.arange(side * side) // side, np.arange(side * side) % side)
    a = (cell[0] + 0.5) / side + sa[:, None]
    b = (cell[1] + 0.5) / side + sb[:, None]
    a = 2.0 * (a - np.floor(a)) - 1.0
    b = 2.0 * (b - np.floor(b)) - 1.0
    return lights_mod.concentric(a, b) if round_ else (a, b)


def _view_indices(shadow: ShadowMap, points: np.ndarray) -> np.ndarray:
    """Index into shadow.views of the view each point (N, 3) falls in: 0 for a single view,
    else its cube face's (-1 where that face was not rendered)."""
    light = shadow.light
    if light.type == "SUN" or len(shadow.views) == 1:
        return np.zeros(points.shape[0], int)
    rel = points - light.position
    axis = np.argmax(np.abs(rel), axis=1)
    sign = np.take_along_axis(rel, axis[:, None], 1)[:, 0] < 0
    face_index = {v.face: i for i, v in enumerate(shadow.views)}
    return np.array([face_index.get(f, -1) for f in range(6)])[axis * 2 + sign]


def _texels(shadow: ShadowMap, x: np.ndarray):
    """Per point (N, 3): its view (-1: none), the column and row of its texel there (clipped
    to the map), and whether it is in front of the view's eye and inside it ([-1, 1]^2)."""
    res = shadow.resolution
    view_of = _view_indices(shadow, x)
    ix, iy = np.zeros(x.shape[0], int), np.zeros(x.shape[0], int)
    front, inside = np.zeros(x.shape[0], bool), np.zeros(x.shape[0], bool)
    for i, view in enumerate(shadow.views):
        sel = np.nonzero(view_of == i)[0]
        if sel.size == 0:
            continue
        vp = _transform(np.asarray(view.view, np.float64), x[sel])
        if view.ortho:
            ok = np.ones(sel.size, bool)
            inv = np.full(sel.size, 1.0 / view.half_extent)
        else:
            z = -vp[:, 2]
            ok = z > 0
            inv = np.where(ok, 1.0 / np.where(ok, z * view.tan_half, 1.0), 1.0 / view.tan_half)
        u, v = vp[:, 0] * inv, vp[:, 1] * inv
        front[sel] = ok
        inside[sel] = ok & (np.abs(u) <= 1.0) & (np.abs(v) <= 1.0)
        ix[sel] = np.clip(np.floor((u + 1.0) * 0.5 * res), 0, res - 1).astype(int)
        iy[sel] = np.clip(np.floor((1.0 - v) * 0.5 * res), 0, res - 1).astype(int)
    return view_of, ix, iy, front, inside


def _lookup(shadow: ShadowMap, x: np.ndarray, p_off: np.ndarray, n: np.ndarray,
            dist: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For tap points x (N, 3): the map's depth at the texel each falls in (inf outside the
    views) and whether it occludes the receiver: nearer than the receiver's distance
    ``dist`` and, on that texel's centre ray, in front of the receiver's own plane (through
    p_off, normal n), both by ``bias``: a wide filter finds no acne on the receiver's own
    surface, and a surface behind its plane (the rest of its own box) shades nothing."""
    res = shadow.resolution
    light = shadow.light
    depth_out = np.full(x.shape[0], np.inf)
    blocked = np.zeros(x.shape[0], bool)
    single = light.type == "SUN" or len(shadow.views) == 1
    view_of, ix_all, iy_all, front, inside = _texels(shadow, x)
    for i, (view, depth) in enumerate(zip(shadow.views, shadow.depths)):
        sel = np.nonzero(view_of == i)[0]
        if sel.size == 0:
            continue
        ok = inside[sel] if single else front[sel]
        ix, iy = ix_all[sel], iy_all[sel]
        y0, f = _texel_ray(view, res, ix, iy, light.position)
        nn = n[sel]
        h0 = np.einsum("ij,ij->i", nn, y0 - p_off[sel])
        den = np.einsum("ij,ij->i", nn, f)
        d = depth[iy, ix].astype(np.float64)
        depth_out[sel] = np.where(ok, d, np.inf)
        near = ok & (d < dist[sel] - bias[sel])
        # the occluder d along the ray: in front of the receiver's plane by the bias (behind
        # it, it cannot stand between the receiver and any light it sees)
        hit = near & (h0 + np.where(near, d, 0.0) * den > bias[sel] * np.abs(den))
        k = np.nonzero(hit)[0]
        if k.size:  # and the receiver behind the occluder's own plane (_beside_occluder)
            hit[k] = ~_beside_occluder(view, depth, ix[k], iy[k], d[k], y0[k], f[k],
                                       p_off[sel][k], light.position)
        blocked[sel] = hit
    return depth_out, blocked


def _texel_ray(view, res: int, ix, iy, eye) -> tuple[np.ndarray, np.ndarray]:
    """Origin and unit direction (N, 3) of the ray through texel (ix, iy)'s centre of a view
    (an ortho view's origin on its eye plane; a perspective view's, the light's ``eye``)."""
    m = np.asarray(view.view, np.float64)
    rot = m[:3, :3]
    scale = view.half_extent if view.ortho else view.tan_half
    uc = (ix + 0.5) / res * 2.0 - 1.0
    vc = 1.0 - (iy + 0.5) / res * 2.0
    if view.ortho:
        y0 = (np.c_[uc * scale, vc * scale, np.zeros(uc.size)] - m[:3, 3]) @ rot
        return y0, np.broadcast_to(-rot[2], y0.shape)
    f = np.c_[uc * scale, vc * scale, -np.ones(uc.size)] @ rot
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    return np.broadcast_to(np.asarray(eye, np.float64), f.shape), f


def _beside_occluder(view, depth, ix, iy, d, y0, f, p, eye) -> np.ndarray:
    """Whether receivers ``p`` (N, 3) lie on the light's side of the plane of the occluder
    seen at texel (ix, iy) (depth d along the ray y0 + t f), by over BESIDE_TEXELS of a
    texel: the plane from the texel and its neighbours' depths one texel across (_slope's
    sides), rebuilt in 3D. Such an occluder, locally flat, cannot cut a segment from the
    receiver to any point of the light on that side: a wall seen beside a receiver near its
    foot (a room's corner) does not shade it, as the tap's depth alone said it did."""
    res = depth.shape[0]
    w = y0 + d[:, None] * f
    tangents = []
    for ax, (sx, sy) in ((1, (1, 0)), (0, (0, 1))):
        g = _slope(depth, ix, iy, ax)
        o, fn = _texel_ray(view, res, ix + sx, iy + sy, eye)  # (may lie past the map's edge)
        tangents.append(o + (d + g)[:, None] * fn - w)
    nrm = np.cross(tangents[0], tangents[1])
    light = -f if view.ortho else eye - w
    side = np.sign(np.einsum("ij,ij->i", nrm, light))
    length = np.linalg.norm(nrm, axis=1)
    texel = np.linalg.norm(tangents[0], axis=1)
    gap = side * np.einsum("ij,ij->i", nrm, p - w)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (side != 0) & (gap > BESIDE_TEXELS * texel * length)


def _receivers(shadow: ShadowMap, positions: np.ndarray, normals: np.ndarray):
    """Per receiver: the view it falls in (-1 for none), the normal-offset point, its
    distance (sun: depth), the depth bias and the texel's size (perspective: the angle of a
    texel at the view's centre; sun: its width in metres)."""
    m = positions.shape[0]
    res = shadow.resolution
    light = shadow.light
    face_of = _view_indices(shadow, positions)
    p_off = np.array(positions, np.float64)
    dist = np.zeros(m)
    bias = np.zeros(m)
    texel = np.zeros(m)
    for i, view in enumerate(shadow.views):
        sel = np.nonzero(face_of == i)[0]
        if sel.size == 0:
            continue
        p, n = positions[sel], normals[sel]
        if view.ortho:
            world = 2.0 * view.half_extent / res
            p_off[sel] = p + n * world * OFFSET_TEXELS
            dist[sel] = -_transform(view.view, p_off[sel])[:, 2]
            bias[sel] = world * BIAS_TEXELS
            texel[sel] = world
        else:
            d = np.linalg.norm(p - light.position, axis=1)
            world = d * (2.0 * view.tan_half / res) * 1.8  # worst case at the face corner
            p_off[sel] = p + n * world[:, None]
            dist[sel] = np.linalg.norm(p_off[sel] - light.position, axis=1)
            bias[sel] = world * BIAS_TEXELS
            texel[sel] = 2.0 * view.tan_half / res
    if light.type != "SUN" and len(shadow.views) > 1:
        # the cube face the offset point falls in (a receiver by a seam: its own face's view
        # may not hold it; every face has the same texel, so the rest stands)
        face_of = _view_indices(shadow, p_off)
    return face_of, p_off, dist, bias, texel


def _slope(depth: np.ndarray, xs, ys, ax: int) -> np.ndarray:
    """Per texel, its surface's depth step to the next texel along axis ``ax`` (1: columns,
    0: rows): the one-sided difference whose line through the next texel out predicts the
    texel best, so that at an edge between two surfaces (a wall meeting a floor) each keeps
    its own slope [Mara et al. 2017's depth-derived normals]; 0 where no side is finite."""
    res = depth.shape[0]

    def at(k):
        if ax == 1:
            return depth[ys, np.clip(xs + k, 0, res - 1)].astype(np.float64)
        return depth[np.clip(ys + k, 0, res - 1), xs].astype(np.float64)

    c, lo, hi = at(0), at(-1), at(1)
    with np.errstate(invalid="ignore"):
        a, b = c - lo, hi - c
        ea, eb = np.abs(2.0 * lo - at(-2) - c), np.abs(2.0 * hi - at(2) - c)
    ea = np.where(np.isfinite(ea), ea, np.where(np.isfinite(a), np.abs(a), np.inf))
    eb = np.where(np.isfinite(eb), eb, np.where(np.isfinite(b), np.abs(b), np.inf))
    g = np.where(ea <= eb, a, b)
    return np.where(np.isfinite(g), g, 0.0)


def _plane_depth(depth: np.ndarray, xs, ys, ox, oy) -> np.ndarray:
    """The depth of texel (xs, ys)'s surface at (ox, oy) texels from its centre, its plane
    taken from the map's differences (_slope): a tap then tests a receiver against the
    occluder itself, not against its centre's depth, so that a receiver a texel's slope
    behind a grazing occluder (a ceiling beside a wall) is not lit through it. An empty
    texel takes the nearest of its 4 neighbours' planes carried over to it: a silhouette
    moves out by under a texel, and a receiver at a closed shell's edge, whose own surface
    ends there too, sees the shell, not the empty texel beyond it."""
    res = depth.shape[0]

    def plane(x, y, dx, dy):
        c = depth[y, x].astype(np.float64)
        with np.errstate(invalid="ignore"):
            p = c + _slope(depth, x, y, 1) * dx + _slope(depth, x, y, 0) * dy
        return np.where(np.isfinite(c), p, np.inf)

    out = plane(xs, ys, ox, oy)
    empty = np.isinf(out)
    if empty.any():
        for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            nx = np.clip(xs + sx, 0, res - 1)
            ny = np.clip(ys + sy, 0, res - 1)
            out = np.where(empty, np.minimum(out, plane(nx, ny, ox - (nx - xs),
                                                          oy - (ny - ys))), out)
    return out


def _in_crease(depth: np.ndarray, taps: list, tol: np.ndarray) -> np.ndarray:
    """Per receiver: a tap it passes and a tap that blocks it hold two surfaces meeting in a
    crease that opens towards the light (each one's plane lies behind the other's texel: a
    wall standing on a floor seen from outside), so the receiver lies behind the blocking
    one, whose plane is the nearer where they meet: it is in shadow. Without this, the
    bilinear taps of a receiver inside a room of single faces, by a wall whose outside
    ground is its own floor's plane, read the ground beyond the wall and pass light."""
    out = np.zeros(tol.shape, bool)
    for i, (xi, yi, li) in enumerate(taps):
        for j, (xj, yj, lj) in enumerate(taps):
            if i == j:
                continue
            pair = li & ~lj & ((xi != xj) | (yi != yj))
            if not pair.any():
                continue
            ci, cj = depth[yi, xi].astype(np.float64), depth[yj, xj].astype(np.float64)
            with np.errstate(invalid="ignore"):
                behind_i = _plane_depth(depth, xj, yj, xi - xj, yi - yj) > ci + tol
                behind_j = _plane_depth(depth, xi, yi, xj - xi, yj - yi) > cj + tol
            out |= pair & np.isfinite(ci) & np.isfinite(cj) & behind_i & behind_j
    return out


def _around_occluder(depth: np.ndarray, taps: list, fx, fy, d, tol) -> list:
    """Per tap, whether it passes once the taps that went round an occluder are cleared: a
    tap whose texel's ray, at the receiver's distance ``d``, lies in front of the plane of an
    occluder another tap blocks the receiver with (that plane in front of the receiver where
    it stands), both by ``tol``. That ray passed the occluder's edge on its light side, which
    the receiver, behind the plane, does not reach through it: a wall's receiver just under a
    roof's edge read the ground beyond the edge through such taps (a bright line along a
    room's inner edges). A receiver far behind an occluder (a shadow's edge on a floor) is
    behind its plane at every tap and keeps its filter."""
    lits = [lit.copy() for _, _, lit in taps]
    for j, (xj, yj, lj) in enumerate(taps):
        c = depth[yj, xj].astype(np.float64)
        gx, gy = _slope(depth, xj, yj, 1), _slope(depth, xj, yj, 0)
        with np.errstate(invalid="ignore"):
            occluder = ~lj & np.isfinite(c) & (c + gx * (fx - xj) + gy * (fy - yj) < d - tol)
        if not occluder.any():
            continue
        for i, (xi, yi, _) in enumerate(taps):
            if i == j:
                continue
            with np.errstate(invalid="ignore"):
                round_ = c + gx * (xi - xj) + gy * (yi - yj) > d + tol
            lits[i] &= ~(occluder & round_ & ((xi != xj) | (yi != yj)))
    return lits


def _hard(shadow: ShadowMap, face_of, p_off, dist, bias) -> np.ndarray:
    """2x2 bilinear percentage-closer filtering of each offset receiver in its view, each
    tap against its texel's occluder plane (_plane_depth; with shadow.planes), the taps that
    went round an occluder cleared (_around_occluder) and, with planes, a crease in shadow
    (_in_crease)."""
    res = shadow.resolution
    vis = np.ones(p_off.shape[0])
    for i, (view, depth) in enumerate(zip(shadow.views, shadow.depths)):
        sel = np.nonzero(face_of == i)[0]
        if sel.size == 0:
            continue
        vp = _transform(view.view, p_off[sel])
        if view.ortho:
            u = vp[:, 0] / view.half_extent
            v = vp[:, 1] / view.half_extent
        else:
            z = np.maximum(-vp[:, 2], 1e-30)
            u = vp[:, 0] / z / view.tan_half
            v = vp[:, 1] / z / view.tan_half
        d = dist[sel]
        # (clipped only so that points far outside the view cast to int: they read 1)
        fx = np.clip((u + 1.0) * 0.5 * res - 0.5, -2.0, res + 1.0)
        fy = np.clip((1.0 - v) * 0.5 * res - 0.5, -2.0, res + 1.0)
        x0 = np.floor(fx).astype(int)
        y0 = np.floor(fy).astype(int)
        tx = fx - x0
        ty = fy - y0
        taps, weights = [], []
        for dy, wy in ((0, 1.0 - ty), (1, ty)):
            for dx, wx in ((0, 1.0 - tx), (1, tx)):
                xs = np.clip(x0 + dx, 0, res - 1)
                ys = np.clip(y0 + dy, 0, res - 1)
                # the tap's occluder plane at the receiver (_plane_depth)
                t = (_plane_depth(depth, xs, ys, fx - xs, fy - ys) if shadow.planes
                     else depth[ys, xs])
                taps.append((xs, ys, d <= t + bias[sel]))
                weights.append(wx * wy)
        lits = _around_occluder(depth, taps, fx, fy, d, bias[sel])
        acc = np.zeros(sel.size)
        for w, lit in zip(weights, lits):
            acc += w * lit
        if shadow.planes:
            acc = np.where(_in_crease(depth, taps, bias[sel]), 0.0, acc)
        inside = (np.abs(u) <= 1.0) & (np.abs(v) <= 1.0)
        vis[sel] = np.where(inside, acc, 1.0)
    return vis


def _light_frame(shadow: ShadowMap, src: Source, p_off: np.ndarray, dist: np.ndarray):
    """Per receiver (M, 3) x 2 the half-axes of the source as it casts onto the receiver
    (a sphere: a disk facing it; the sun: metres of offset per metre of depth along its
    map's right and up axes) and its largest half extent (M,)."""
    m = p_off.shape[0]
    if src.kind in (RECTANGLE, ELLIPSE):
        u = np.broadcast_to(src.u, (m, 3))
        v = np.broadcast_to(src.v, (m, 3))
        return u, v, np.full(m, max(np.linalg.norm(src.u), np.linalg.norm(src.v)))
    if src.kind == CONE:
        rot = np.asarray(shadow.views[0].view, np.float64)[:3, :3]
        u = np.broadcast_to(rot[0] * src.radius, (m, 3))
        v = np.broadcast_to(rot[1] * src.radius, (m, 3))
        return u, v, np.full(m, src.radius)
    w = (p_off - shadow.light.position) / np.maximum(dist, 1e-300)[:, None]
    a = np.where(np.abs(w[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]),
                 np.array([[1.0, 0.0, 0.0]]))
    e1 = np.cross(w, a)
    e1 = e1 / np.sqrt(np.einsum("ij,ij->i", e1, e1))[:, None]
    e2 = np.cross(w, e1)
    return e1 * src.radius, e2 * src.radius, np.full(m, src.radius)


def _taps(src: Source, ortho: bool, c, p_off, u, v, s, side, sa, sb):
    """Tap points (M, side^2, 3): on the segment from each stratum's point of the light to
    the receiver, at the fraction ``s`` (M,) of the way (the sun: offsets in its map's plane
    of ``s`` metres of depth times the cone's tangent)."""
    a, b = _strata(side, sa, sb, src.kind != RECTANGLE)
    off = a[..., None] * u[:, None] + b[..., None] * v[:, None]
    if ortho:
        return p_off[:, None] + s[:, None, None] * off
    q = c + off
    return q + s[:, None, None] * (p_off[:, None] - q)


def _corners(ortho: bool, c, p_off, u, v, s) -> np.ndarray:
    """(M, 4, 3) _taps' points of the corners +-u +-v of the source's bounding square: every
    tap at that ``s`` lies in their convex hull, and every tap of a larger footprint's."""
    a, b = np.array([1.0, 1.0, -1.0, -1.0]), np.array([1.0, -1.0, 1.0, -1.0])
    off = a[:, None] * u[:, None] + b[:, None] * v[:, None]
    if ortho:
        return p_off[:, None] + s[:, None, None] * off
    q = c + off
    return q + s[:, None, None] * (p_off[:, None] - q)


def _box(shadow: ShadowMap, corners, p_off, view):
    """Per receiver (x0, x1, y0, y1) the texel box around its corners' texels and its own,
    one texel wider each side (the 2x2 filter's footprint, rounding), clipped to the map;
    whether all five points lie in front of the eye in its ``view`` (the taps' texels are
    then in the box) and whether also inside the view."""
    res = shadow.resolution
    pts = np.concatenate([corners, p_off[:, None]], 1).reshape(-1, 3)
    view_of, ix, iy, front, inside = _texels(shadow, pts)
    ix, iy = ix.reshape(-1, 5), iy.reshape(-1, 5)
    same = (view_of.reshape(-1, 5) == view[:, None]).all(1)
    return (np.maximum(ix.min(1) - 1, 0), np.minimum(ix.max(1) + 1, res - 1),
            np.maximum(iy.min(1) - 1, 0), np.minimum(iy.max(1) + 1, res - 1),
            same & front.reshape(-1, 5).all(1), same & inside.reshape(-1, 5).all(1))


def _box_test(shadow: ShadowMap, view, x0, x1, y0, y1, q, n, lim, bias, umbra: bool):
    """Whether no texel of each box of ``view`` can occlude the receiver (a block's depths at
    least ``lim`` or its occluders' box on or behind the plane through q, normal n: lit) or,
    with ``umbra``, whether every one does (depths below ``lim``, in front of the plane by
    ``bias``: _lookup's test), over the blocks of the level where the box covers at most
    3 x 3, a block that fails read again as its sub-blocks two levels down (at most 4 x 4),
    REFINE times; and the least depth over the first blocks."""
    pyr, offs, sizes = shadow.pyramid()
    m = view.size
    lev = np.full(m, PYRAMID_FROM)
    for _ in range(len(sizes)):
        lev += ((x1 >> lev) - (x0 >> lev) > 2) | ((y1 >> lev) - (y0 >> lev) > 2)
    nq = np.einsum("ij,ij->i", n, q)

    def blocks(rid, lv, bx, by):
        blk = pyr[view[rid], offs[lv] + by * sizes[lv] + bx].astype(np.float64)
        with np.errstate(invalid="ignore"):  # 0 x inf of a block that hits nothing
            lo, hi = n[rid] * blk[:, 2:5], n[rid] * blk[:, 5:8]
            if umbra:
                good = (blk[:, 1] < lim[rid]) & (np.minimum(lo, hi).sum(1) - nq[rid] > bias[rid])
            else:
                good = (blk[:, 0] >= lim[rid]) | (np.maximum(lo, hi).sum(1) - nq[rid] <= 0.0)
        return good, blk[:, 0]

    def within(rid, lv, bx, by):
        return ((bx >= x0[rid] >> lv) & (bx <= x1[rid] >> lv) & (by >= y0[rid] >> lv)
                & (by <= y1[rid] >> lv))

    rid, j = np.repeat(np.arange(m), 9), np.tile(np.arange(9), m)
    lv = lev[rid]
    bx, by = (x0[rid] >> lv) + j % 3, (y0[rid] >> lv) + j // 3
    k = within(rid, lv, bx, by)
    rid, lv, bx, by = rid[k], lv[k], bx[k], by[k]
    good, lo = blocks(rid, lv, bx, by)
    least = np.full(m, np.inf)
    np.minimum.at(least, rid, lo)
    for _ in range(REFINE):
        rid, lv, bx, by = rid[~good], lv[~good], bx[~good], by[~good]
        step = np.repeat(np.minimum(lv - PYRAMID_FROM, 2), 16)
        rid, j = np.repeat(rid, 16), np.tile(np.arange(16), rid.size)
        lv = np.repeat(lv, 16) - step
        bx, by = (np.repeat(bx, 16) << step) + j % 4, (np.repeat(by, 16) << step) + j // 4
        k = (j % 4 < (1 << step)) & (j // 4 < (1 << step)) & within(rid, lv, bx, by)
        rid, lv, bx, by = rid[k], lv[k], bx[k], by[k]
        good, _ = blocks(rid, lv, bx, by)
    ok = np.ones(m, bool)
    ok[rid[~good]] = False
    return ok, least


def _clear_across(shadow: ShadowMap, pts, q, n, lim, bias):
    """_box_test's lit test for receivers whose five points (M, 5, 3) span cube faces: per
    view, the box of the points' projections (the taps falling in it project inside it)
    clipped to the map, each clear; none if all five are behind the view's eye, not settled
    if some are."""
    res = shadow.resolution
    ok = np.ones(pts.shape[0], bool)
    for i, view in enumerate(shadow.views):
        vp = _transform(np.asarray(view.view, np.float64), pts.reshape(-1, 3)).reshape(-1, 5, 3)
        front = -vp[..., 2] > 0
        ok &= front.all(1) | ~front.any(1)
        sel = np.nonzero(ok & front.all(1))[0]
        z = -vp[sel, :, 2] * view.tan_half
        ix = np.clip(np.floor((vp[sel, :, 0] / z + 1.0) * 0.5 * res), -2, res + 1)
        iy = np.clip(np.floor((1.0 - vp[sel, :, 1] / z) * 0.5 * res), -2, res + 1)
        hit = ((ix.max(1) >= -1) & (ix.min(1) <= res) & (iy.max(1) >= -1)
               & (iy.min(1) <= res))
        sel, ix, iy = sel[hit], ix[hit].astype(int), iy[hit].astype(int)
        box = [np.clip(a, 0, res - 1) for a in (ix.min(1) - 1, ix.max(1) + 1, iy.min(1) - 1,
                                               iy.max(1) + 1)]
        clear, _ = _box_test(shadow, np.full(sel.size, i), *box, q[sel], n[sel], lim[sel],
                             bias[sel], False)
        ok[sel] &= clear
    return ok


def _early_outs(shadow: ShadowMap, ortho: bool, p_off, n, u, v, dist, bias, search_s,
                face_of, todo, vis):
    """The receivers ``todo`` that the pyramid settles without taps (their vis set; the rest
    returned), as the taps would: no texel of the search's box can occlude (lit), or every
    texel of the box of the search and of any filter its blockers allow occludes (umbra)."""
    c = shadow.light.position
    t, view = todo, face_of[todo]
    lim = dist[t] - bias[t]
    corners = _corners(ortho, c, p_off[t], u[t], v[t], search_s[t])
    x0, x1, y0, y1, usable, _ = _box(shadow, corners, p_off[t], view)
    clear, least = _box_test(shadow, view, x0, x1, y0, y1, p_off[t], n[t], lim, bias[t], False)
    lit = usable & clear
    if len(shadow.views) > 1 and not ortho:  # a search across cube faces
        j = np.nonzero(~usable)[0]
        pts = np.concatenate([corners[j], p_off[t[j], None]], 1)
        lit[j] = _clear_across(shadow, pts, p_off[t[j]], n[t[j]], lim[j], bias[t[j]])
    vis[t[lit]] = 1.0
    k = np.nonzero(usable & ~lit)[0]  # the filter reads no farther than at t_b = least
    tk = t[k]
    if ortho:
        s = np.maximum(search_s[tk], dist[tk] - least[k])
    else:
        s = np.minimum(search_s[tk], np.clip(least[k] / dist[tk], 1e-6, 1.0))
    x0, x1, y0, y1, _, inside = _box(shadow, _corners(ortho, c, p_off[tk], u[tk], v[tk], s),
                                     p_off[tk], view[k])
    full, _ = _box_test(shadow, view[k], x0, x1, y0, y1, p_off[tk], n[tk], lim[k], bias[tk],
                        True)
    umbra = inside & full
    vis[tk[umbra]] = 0.0
    keep = ~lit
    keep[k[umbra]] = False
    return t[keep]


def _soft(shadow: ShadowMap, src: Source, positions, normals, face_of, p_off, dist, bias,
          texel, hard) -> np.ndarray:
    """Percentage-closer soft shadows of the receivers (see the module docstring)."""
    light = shadow.light
    ortho = light.type == "SUN"
    c = light.position
    m = positions.shape[0]
    u, v, extent = _light_frame(shadow, src, p_off, dist)
    if ortho:  # blockers lie between the near plane and, within its reach, the nearest
        search_s = np.maximum(dist - _ortho_near(shadow.views[0]), 0.0)
        t = np.nonzero((search_s * src.radius >= texel) & (face_of >= 0))[0]
        x0, x1, y0, y1, _, _ = _box(shadow, _corners(True, c, p_off[t], u[t], v[t],
                                                     search_s[t]), p_off[t], face_of[t])
        _, least = _box_test(shadow, face_of[t], x0, x1, y0, y1, p_off[t], normals[t],
                             dist[t] - bias[t], bias[t], False)
        search_s[t] = np.minimum(search_s[t], np.maximum(dist[t] - least, 0.0))
        search_px = search_s * src.radius / texel
    else:
        search_s = np.full(m, SEARCH_AT)
        search_px = extent * (1.0 - SEARCH_AT) / (SEARCH_AT * dist) / texel
    sa = _hash(positions, *HASH_A)
    sb = _hash(positions, *HASH_B)
    vis = hard.copy()
    todo = np.nonzero((search_px >= 1.0) & (face_of >= 0))[0]
    todo = _early_outs(shadow, ortho, p_off, normals, u, v, dist, bias, search_s, face_of,
                       todo, vis)
    if todo.size == 0:
        return vis
    k = SEARCH_SIDE * SEARCH_SIDE
    x = _taps(src, ortho, c, p_off[todo], u[todo], v[todo], search_s[todo], SEARCH_SIDE,
              sa[todo], sb[todo])
    x = np.concatenate([x, p_off[todo][:, None]], axis=1)  # and the receiver's own texel
    rep = lambda arr: np.repeat(arr[todo], k + 1, axis=0)
    depth, blocked = _lookup(shadow, x.reshape(-1, 3), rep(p_off), rep(normals), rep(dist),
                             rep(bias))
    depth, blocked = depth.reshape(-1, k + 1), blocked.reshape(-1, k + 1)
    count = blocked.sum(axis=1)
    found = count > 0
    vis[todo[~found]] = 1.0
    todo = todo[found]
    if todo.size == 0:
        return vis
    t_b = np.where(blocked[found], depth[found], 0.0).sum(axis=1) / count[found]
    # the surface on the receiver's own texel, when nearer than the receiver and the blockers'
    # mean: its layer's penumbra under a texel is the hard filter's to resolve (a wall right
    # beside the receiver, which the taps at t_b fly past)
    d_own = depth[found][:, -1]
    near = (d_own > t_b) & (d_own < dist[todo] - bias[todo])
    s, width_px = _footprint(src, ortho, dist[todo], texel[todo], extent[todo], t_b)
    contact = near & (_footprint(src, ortho, dist[todo], texel[todo], extent[todo], d_own)[1]
                      < 1.0)
    wide = width_px >= 1.0  # narrower penumbrae keep the bilinear filter
    wide &= ~(contact & (hard[todo] <= 0.0))  # shut out by the contact layer: vis = hard = 0
    todo, s, contact = todo[wide], s[wide], contact[wide]
    if todo.size == 0:
        return vis
    k = FILTER_SIDE * FILTER_SIDE
    x = _taps(src, ortho, c, p_off[todo], u[todo], v[todo], s, FILTER_SIDE, sa[todo], sb[todo])
    rep = lambda arr: np.repeat(arr[todo], k, axis=0)
    depth, blocked = _lookup(shadow, x.reshape(-1, 3), rep(p_off), rep(normals), rep(dist),
                             rep(bias))
    # a receiver in the hard filter's umbra counts a tap that sees past every surface (beyond
    # a closed shell's silhouette) as blocked: the light's far side lies behind the same shell
    blocked |= np.isinf(depth) & rep(hard <= 0.0)
    w = _tap_weights(src, ortho, c, positions[todo], normals[todo], u[todo], v[todo],
                     FILTER_SIDE, sa[todo], sb[todo])
    vis[todo] = (w * ~blocked.reshape(-1, k)).sum(axis=1) / w.sum(axis=1)  # exact 0 and 1
    # every stratum's ray also passes the contact layer: the hard filter's share of it
    vis[todo[contact]] *= hard[todo[contact]]
    return vis


def _footprint(src: Source, ortho: bool, dist, texel, extent, t_b):
    """The filter's tap fraction s (the sun: metres of depth) for blockers at depth t_b, and
    the penumbra's width on the receiver in texels (similar triangles)."""
    if ortho:
        s = np.maximum(dist - t_b, 0.0)
        return s, s * src.radius / texel
    s = np.clip(t_b / dist, 1e-6, 1.0)
    return s, extent * (1.0 - s) / (s * dist) / texel


def _tap_weights(src: Source, ortho: bool, c, p, n, u, v, side, sa, sb) -> np.ndarray:
    """(M, side^2) weights: each stratum's share of the receiver's irradiance,
    its point's form factor |n_l.d| max(n.d, 0) / |d|^4 (d from the receiver p to the point,
    n_l the source's normal u x v): near a large light its near part lights most, and
    the unweighted share of taps made the penumbra too dark. The sun's cone (and a receiver
    no stratum faces): equal."""
    m = p.shape[0]
    if ortho:
        return np.ones((m, side * side))
    a, b = _strata(side, sa, sb, src.kind != RECTANGLE)
    d = c + a[..., None] * u[:, None] + b[..., None] * v[:, None] - p[:, None]
    d2 = np.einsum("ijk,ijk->ij", d, d)
    axis = np.cross(u, v)
    w = (np.abs(np.einsum("ijk,ik->ij", d, axis))
         * np.maximum(np.einsum("ijk,ik->ij", d, n), 0.0) / np.maximum(d2 * d2, 1e-300))
    return np.where(w.sum(axis=1, keepdims=True) > 0.0, w, 1.0)


def visibility(shadow: ShadowMap, positions: np.ndarray, normals: np.ndarray,
               radius: float | None = None) -> np.ndarray:
    """Fraction of the light seen by each receiver (M,): 2x2 percentage-closer filtered for a
    hard light, percentage-closer soft shadows for one with a size (source_of: the light's
    own, or a sphere of ``radius`` / a sun of angular radius ``radius``)."""
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    m = positions.shape[0]
    if not shadow.light.cast_shadow or m == 0:
        return np.ones(m)
    src = source_of(shadow.light, radius)
    if jit.enabled():
        return _compiled.visibility(shadow, src, positions, normals)
    face_of, p_off, dist, bias, texel = _receivers(shadow, positions, normals)
    hard = _hard(shadow, face_of, p_off, dist, bias)
    if src.kind == HARD:
        return hard
    return _soft(shadow, src, positions, normals, face_of, p_off, dist, bias, texel, hard)


def irradiance(
    light: Light, positions: np.ndarray, normals: np.ndarray, shadow: ShadowMap | None = None
) -> np.ndarray:
    """Direct irradiance (M, 3) in W/m^2 at receivers with unit normals (facing the viewer)."""
    if jit.enabled() and light.type in _compiled.KINDS and np.shape(positions)[0]:
        src = source_of(light) if shadow is not None else None
        return _compiled.irradiance(light, positions, normals, shadow, src)
    positions = np.asarray(positions, np.float64)
    normals = np.asarray(normals, np.float64)
    color = np.asarray(light.color, np.float64)
    if light.type == "SUN":
        cos_r = np.maximum(normals @ (-light.direction), 0.0)
        e = light.power * cos_r
    elif light.type == "AREA":
        e = lights_mod.area_irradiance(light, positions, normals)
    else:
        to_light = light.position - positions
        d2 = np.einsum("ij,ij->i", to_light, to_light)
        d2 = np.maximum(d2, 1e-30)
        w = to_light / np.sqrt(d2)[:, None]
        cos_r = np.einsum("ij,ij->i", normals, w)
        inten = lights_mod.intensity(light, -w)
        inten[lights_mod.inside_sphere(light, d2)] = light.power / (4.0 * np.pi)
        e = inten * lights_mod.round_geometry(light, cos_r, d2)
    if shadow is not None:
        lit = e > 0
        vis = np.zeros_like(e)
        vis[lit] = visibility(shadow, positions[lit], normals[lit])
        e = e * vis
    return e[:, None] * color
