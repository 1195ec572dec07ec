"""Light sources without an RSM, the World (sky.py) and emissive triangles (emitters.py), in an
update and a render: their shadow maps (cached per geometry and LPV box), their direct light at
any points (Diffuse Direct), their GI (caster surfels lit by that direct light, x area x GI
reflectance, injected and propagated like VPLs: Diffuse Indirect), and what the camera sees of
them (emitting surfaces, the World behind everything: Combined only)."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

import numpy as np

from . import cascades, emitters, mirror_lobe, propagation, sky
from .geometry_volume import MAX_SPLITS, surfels
from .scene import textures
from .scene.model import HIDDEN_FROM_CAMERA


@dataclass
class Source:
    """A GI source for Engine.update's per-source grids (combine weighs it like a light)."""

    name: str
    kind: str  # "world" or "emission"
    gi_intensity: float
    source_key: tuple  # what its propagated grids depend on besides the scene key
    material: int = -1  # emission: the material
    gi_color: None = None


def _digest(*arrays) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def source_name(kind: str, what) -> str:
    """The name a source's Source, grids, GI weight and stats go by: "World 'name'" etc."""
    return f"{kind} '{what.name}'"


def gi_sources(scene, refl: str, stats) -> list[Source]:
    """The World and emissive materials that contribute GI; the rest in the stats with why."""
    out = []
    world, g = scene.world, scene.settings.intensity
    why = sky.lit(world)
    if not why and world.gi_intensity == 0:
        why = "its GI intensity is 0 (direct light only)"
    if not why and g == 0:
        why = "global GI intensity is 0"
    if why:
        stats.skip("sources", "World", why)
    else:
        key = ("world", world.digest or _digest(world.radiance), sky.DIRECTIONS, refl)
        out.append(Source(source_name("World", world), "world", float(world.gi_intensity), key))
    mats = emitters.emissive_materials(scene)
    if not mats:
        stats.skip("sources", "emission", "no material emits")
    for mi in mats:
        m = scene.materials[mi]
        label = source_name("emission", m)
        if m.emission_gi_intensity == 0 or g == 0:
            stats.skip("sources", label, "GI intensity is 0 (direct light only)")
            continue
        key = ("emission", mi, np.asarray(m.emission, np.float64).tobytes(), refl)
        out.append(Source(label, "emission", float(m.emission_gi_intensity), key, mi))
    return out


class SourceMaps:
    """Shadow maps of the World's directions and of the emitter clusters, for one geometry and
    LPV box (Engine.source_maps)."""

    def __init__(self):
        self.key = None
        self.world: dict = {}  # K -> (world digest, directions, weights, radiance, maps)
        self.clusters = None  # (emission digest, [(Cluster, ShadowMap)])
        self.atlas = None  # render/atlas.DepthAtlas of the engine's rasteriser (the World's maps)

    def reset(self, key) -> None:
        if key != self.key:
            self.key, self.world, self.clusters = key, {}, None


def maps(engine, scene, bounds, stats, k: int | None = None,
         sky_set: tuple[int, int] = (0, 1)) -> SourceMaps:
    """engine's SourceMaps made current for ``scene`` in ``bounds``: the World's ``k``
    directions (sky.DIRECTIONS: the GI's; RENDER_DIRECTIONS: the pixels', set ``sky_set`` =
    (index, sets) of sky.render_directions) and their maps (one atlas, render/atlas.py), and
    the clusters' cube maps (the scene without emitters: they do not shadow themselves),
    rendered when missing; stats.info["sources"] names what each approximates. SourceMaps.world
    is keyed by (k, index, sets)."""
    from .render import direct
    from .render.atlas import DepthAtlas

    sm = engine.source_maps
    lo, hi = (np.asarray(b, np.float64) for b in bounds)
    b = engine._bounds
    geo = b.geometry if b is not None else _digest(scene.positions)
    sm.reset((geo, lo.tobytes(), hi.tobytes()))
    info = stats.info.setdefault("sources", {})
    t0 = time.perf_counter()
    world, k = scene.world, k or sky.DIRECTIONS
    key = _world_key(k, sky_set)
    if not sky.lit(world):
        digest = world.digest or _digest(world.radiance)
        if key not in sm.world or sm.world[key][0] != digest:
            cells = sky.cells(world, k, None if key[2] == 1 else sky.render_directions(*key[1:]))
            old = sm.world.get(key)  # the maps depend on the geometry alone
            if sm.atlas is None or sm.atlas.raster is not engine.raster:
                sm.atlas = DepthAtlas(engine.raster)
            # windows on the LPV box, depth over all the geometry (what stands outside the
            # box, a closed space's walls, shades it from the sky too)
            made = old[4] if old is not None else sky.shadow_maps(
                sm.atlas, sky.suns(cells[0]), scene.bounds(), (lo, hi), sky.SHADOW_RESOLUTION)
            sm.world[key] = (digest, *cells, made)
        counts = {n: sum(1 for m, _, _ in sm.world if m == n) for n, _, _ in sm.world}
        if k == sky.RENDER_DIRECTIONS:  # this render's sets (the first sample asks for its own)
            counts[k] = max(counts[k], sky_set[1])
        info[source_name("World", world)] = (
            f"{' and '.join(f'{c} x {n}' if c > 1 else str(n) for n, c in sorted(counts.items()))}"
            " directions (GI, pixels: a set per antialias sample), radiance averaged over each "
            f"one's cell; sky visibility from {sky.SHADOW_RESOLUTION}^2 orthographic shadow "
            "maps")
    mats = emitters.emissive_materials(scene)
    if mats:
        table = np.array([scene.materials[i].emission for i in mats], np.float64)
        digest = _digest(table, np.array(mats), scene.material_index)
        if sm.clusters is None or sm.clusters[0] != digest:
            found = emitters.clusters(scene, float(np.linalg.norm(hi - lo)))
            keep = ~np.isin(scene.material_index, mats)
            raster, origin = engine.raster, 0.5 * (lo + hi)
            raster.upload(scene.positions[keep], scene.normals[keep],
                          scene.albedo_per_triangle()[keep],
                          scene.reflectance_per_triangle()[keep], origin=origin)
            made = [(c, direct.render_shadow_map(raster, c.light(), (lo, hi),
                                                 emitters.SHADOW_RESOLUTION)) for c in found]
            engine.upload(scene, stats)  # the whole scene back for the other passes
            for c, shadow in made:  # a closed emitter's outer side, else an uncapped one
                c.side = c.side or emitters.capped_side(c, shadow)
            sm.clusters = (digest, made)
        for c, _ in sm.clusters[1]:
            info[f"emission {c.name}"] = (
                f"{c.triangles.size} triangles, exact unoccluded form factors; visibility "
                f"from the cluster's centre ({emitters.SHADOW_RESOLUTION}^2 cube map, "
                f"{c.radius:.3g} m source)" + ("" if not c.side else
                                                  "; emits from one side: a closed object's "
                                                  "outer one, or the one not capped"))
    stats.add_ms("source_maps", time.perf_counter() - t0)
    return sm


def _world_key(k: int, sky_set: tuple[int, int]) -> tuple[int, int, int]:
    """SourceMaps.world's key of ``k`` directions in set ``sky_set``: a set of the pixels'
    but the first (the unturned sphere, the same directions as one set) is its own."""
    index, sets = sky_set
    return (k, index % sets, sets) if k == sky.RENDER_DIRECTIONS and index % sets else (k, 0, 1)


def direct(engine, scene, bounds, positions, normals, stats, material: int | None = None,
           world: bool = True, gi: bool = False, sky_set: tuple[int, int] = (0, 1),
           weights: dict | None = None):
    """Direct irradiance (M, 3) W/m^2 of the World (``world``; over the GI's directions with
    ``gi``, else the pixels' set ``sky_set``, maps()) and the emitters (of ``material`` only,
    when given) at receivers; None when none of them sends light. With ``weights`` (source
    name -> GI weight, gi_weights): (that, the same sum with each source x its weight)."""
    if sky.lit(scene.world) and not emitters.emissive_materials(scene):
        return None if weights is None else (None, None)
    k = sky.DIRECTIONS if gi else sky.RENDER_DIRECTIONS
    sm = maps(engine, scene, bounds, stats, k, sky_set)
    key = _world_key(k, sky_set)
    e = e_gi = None

    def add(name: str, part: np.ndarray) -> None:  # summed as it comes: two arrays held
        nonlocal e, e_gi
        e = part if e is None else e + part
        w = (weights or {}).get(name, 0.0)
        if w:
            e_gi = part * w if e_gi is None else e_gi + part * w

    if world and key in sm.world:
        add(source_name("World", scene.world),
            sky.irradiance(*sm.world[key][1:], positions, normals, pcf=not gi))
    for c, shadow in (sm.clusters[1] if sm.clusters else []):
        if material is None or c.material == material:
            add(source_name("emission", scene.materials[c.material]),
                emitters.irradiance(c, shadow, positions, normals))
    return e if weights is None else (e, e_gi)


def gi_weights(scene, held) -> dict:
    """Source name -> the weight combine gives its grids (GI intensity x global intensity) for
    the World and emissive materials whose grids ``held`` (LPVResult.per_light) holds."""
    world = [] if scene.world is None else [("World", scene.world, scene.world.gi_intensity)]
    mats = [scene.materials[mi] for mi in emitters.emissive_materials(scene)]
    weights = ((source_name(kind, what), w) for kind, what, w in
               world + [("emission", m, m.emission_gi_intensity) for m in mats])
    g = float(scene.settings.intensity)
    return {name: float(w) * g for name, w in weights if held.get(name) is not None}


def cascade_surfels(positions: np.ndarray, chain: list):
    """Surfels (centres, normals, areas, triangle) one cell of their own cascade apart: those
    of cascade c where it is the finest (cascades.assign), from the triangles touching its box
    (an RSM's texels are about a cell apart too; the injection splats them over 8 cells)."""
    from .cascades import assign

    lo_t, hi_t = positions.min(axis=1), positions.max(axis=1)
    longest = np.max(hi_t - lo_t, axis=1)
    parts = []
    for c, g in enumerate(chain):
        lo, hi = g.bounds()
        hit = np.nonzero(np.all((hi_t >= lo) & (lo_t <= hi), axis=1))[0]
        # a triangle too long for cell-sized pieces (a 1 km ground) is cut to the box first
        big = longest[hit] > MAX_SPLITS * g.cell_size
        tris, index = positions[hit], hit
        if big.any():
            pieces = [clip_to_box(positions[t], lo, hi) for t in hit[big]]
            tris = np.concatenate([positions[hit[~big]]] + pieces)
            index = np.concatenate([hit[~big]] + [np.full(len(q), t) for q, t in
                                                  zip(pieces, hit[big])]).astype(np.int64)
        pos, nrm, area, tri = surfels(tris, g.cell_size, with_index=True)
        tri = index[tri]
        own = assign(chain, pos) == c if len(chain) > 1 else slice(None)
        parts.append((pos[own], nrm[own], area[own], tri[own]))
    return tuple(np.concatenate(a) for a in zip(*parts))


def clip_to_box(triangle: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The part of ``triangle`` (3, 3) inside the box [lo, hi] as a fan of triangles (M, 3, 3),
    M = 0 when none is (Sutherland-Hodgman against the six planes): same plane, same winding,
    its area the area inside."""
    poly = [np.asarray(v, np.float64) for v in triangle]
    for axis in range(3):
        for bound, sign in ((lo[axis], 1.0), (hi[axis], -1.0)):
            out = []
            for a, b in zip(poly, poly[1:] + poly[:1]):
                da, db = sign * (a[axis] - bound), sign * (b[axis] - bound)
                if da >= 0:
                    out.append(a)
                if (da >= 0) != (db >= 0):
                    out.append(a + (b - a) * (da / (da - db)))
            poly = out
            if len(poly) < 3:
                return np.zeros((0, 3, 3))
    fan = np.array([[poly[0], poly[i], poly[i + 1]] for i in range(1, len(poly) - 1)])
    # a corner on a plane repeats: keep the pieces with area (relative to the triangle's own)
    cross = np.linalg.norm(np.cross(fan[:, 1] - fan[:, 0], fan[:, 2] - fan[:, 0]), axis=1)
    own = np.linalg.norm(np.cross(triangle[1] - triangle[0], triangle[2] - triangle[0]))
    return fan[cross > 1e-12 * own]


def propagate(engine, scene, src: Source, run, bounds, stats) -> list:
    """A source's propagated grids (one per cascade, unweighted): caster surfels (two-sided,
    cascade_surfels) lit by its direct light, their flux E x area x GI reflectance injected
    and propagated through ``run`` (Engine._source caches them). The glossy reflectance
    (Material.specular) bounces too: the World's surfels add it, sky light reflected off a
    metal leaving around the normal, as the cosine lobe it is under a uniform sky (its mirror
    image of uniform radiance); an emitter's light leaves along its mirror direction
    (emitter_mirror_vpls)."""
    chain = run.chain
    maps(engine, scene, bounds, stats, sky.DIRECTIONS)  # timed on its own (source_maps)
    t0 = time.perf_counter()
    pos, nrm, area, tri = cascade_surfels(scene.positions, chain)
    refl = scene.reflectance_per_triangle()[tri].astype(np.float64)
    if engine.raster.surface is not None:  # the texture and corner colour at each surfel
        refl *= engine.raster.surface.factor(
            tri, textures.barycentric(scene.positions[tri], pos), gi=True)
    glossy = scene.specular_per_triangle()
    if glossy is not None and src.kind == "world":
        refl += glossy[tri]
    pos2, nrm2 = np.concatenate([pos, pos]), np.concatenate([nrm, -nrm])
    # the sides facing into the LPV box (cascades.facing_into): a closed room's outer sides
    # are left out, and not lit
    inside = np.nonzero(cascades.facing_into(pos2, nrm2, *bounds))[0]  # the sides lit, in order
    pos2, nrm2 = pos2[inside], nrm2[inside]
    e = np.zeros((0, 3))
    if inside.size:
        e = direct(engine, scene, bounds, pos2, nrm2, stats,
                   material=src.material if src.kind == "emission" else -1,
                   world=src.kind == "world", gi=True)
    side = inside % max(len(pos), 1)  # each side's surfel
    flux = e * area[side][:, None] * refl[side]
    keep = np.maximum(np.maximum(flux[:, 0], flux[:, 1]), flux[:, 2]) > 0
    vpls = (pos2[keep], nrm2[keep], flux[keep], np.zeros_like(nrm2[keep]))
    if glossy is not None and src.kind == "emission" and inside.size:
        mirror = emitter_mirror_vpls(engine.source_maps.clusters[1], src.material, pos2, nrm2,
                                     area[side], glossy[tri][side])
        vpls = tuple(np.concatenate(pair) for pair in zip(vpls, mirror))
    stats.add_ms("sources", time.perf_counter() - t0)
    stats.info.setdefault("source_flux", {})[src.name] = float(vpls[2].sum())
    if not len(vpls[0]):
        seen = bool((e > 0).any())
        stats.skip("sources", f"GI of {src.name}",
                   "no caster it lights inside the LPV" if seen else
                   "no surface inside the LPV sees it (every surfel's visibility is 0)")
        return [g.zeros(propagation.coefficients(scene.settings.angular)) for g in chain]
    totals = run.propagate(*vpls[:3], lift=vpls[3] if vpls[3].any() else None)
    if scene.settings.bounces > 1:
        totals = engine._more_bounces(scene, run, totals)
    return totals


def emitter_mirror_vpls(clusters: list, material: int, positions: np.ndarray,
                        normals: np.ndarray, area: np.ndarray, specular: np.ndarray) -> tuple:
    """The glossy bounce of emissive ``material``'s light as VPLs (position, axis, flux, lift):
    per cluster of it, each glossy surfel side's irradiance from it x area x glossy reflectance
    ``specular`` (M, 3), leaving around the mirror direction of the ray from the cluster's
    centre (mirror_lobe.above, the rsm.mirror_vpls lobe), injected from the surface's side."""
    parts = [np.zeros((0, 3))] * 4
    lit = np.flatnonzero(specular.max(axis=1) > 0)
    for c, shadow in clusters if lit.size else []:
        if c.material != material:
            continue
        p, n = positions[lit], normals[lit]
        flux = emitters.irradiance(c, shadow, p, n) * area[lit, None] * specular[lit]
        d = p - np.asarray(c.centre, np.float64)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        dn = np.einsum("nc,nc->n", d, n)
        ok = (dn < 0) & (flux.max(axis=1) > 0) & np.isfinite(flux).all(axis=1)
        if ok.any():
            axis = mirror_lobe.above(d[ok] - 2.0 * dn[ok, None] * n[ok], n[ok])
            part = (p[ok], axis, flux[ok], n[ok] - axis)
            parts = [np.concatenate(pair) for pair in zip(parts, part)]
    return tuple(parts)


def camera_light(engine, scene, projection, mask: np.ndarray, combined: np.ndarray,
                 world: bool = True, seed: tuple[int, int] = (0, 1),
                 only: np.ndarray | None = None) -> None:
    """Add what the camera sees of the sources to ``combined`` (H, W, 4): each emitting
    surface's radiance where it is seen (its triangle per pixel, the RSM pass's index) and,
    with ``world`` (not Film > Transparent), the World along the view ray where no surface is
    (bilinear in its map); ``seed``: the G-buffer's hashed alpha, so that the same fragments
    are seen; ``only`` (H, W) bool: the World at these pixels only."""
    h, w = mask.shape
    mats = emitters.emissive_materials(scene)
    if mats and mask.any():
        raster = engine.raster
        fbo = raster._fbo(w, h, 2)
        raster._draw(raster.rsm_program, raster._rsm_vao, fbo, scene.camera.view, projection,
                     False, HIDDEN_FROM_CAMERA, seed)
        pos, nrm = raster._targets(fbo, (0, 1), w, h)
        tri = raster.triangles(pos[mask], nrm[mask])
        table = np.array([m.emission for m in scene.materials], np.float32)
        ok = (tri >= 0) & (tri < scene.triangle_count)
        glow = np.zeros((tri.size, 3), np.float32)
        glow[ok] = table[scene.material_index[tri[ok]]]
        combined[..., :3][mask] += glow
    empty = ~mask if only is None else ~mask & only
    if world and not sky.lit(scene.world) and empty.any():
        from .render.raster import PixelRays

        ys, xs = np.nonzero(empty)
        d = PixelRays(scene.camera.view, projection, w, h, empty, 0.0).at(
            np.arange(xs.size), np.zeros((1, 2)))[1][:, 0]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
        combined[ys, xs, :3] += sky.lookup(scene.world, d)
