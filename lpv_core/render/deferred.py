"""Deferred renderer: G-buffer from the scene camera, direct light with shadow maps, LPV lookup.

Output passes follow Cycles' names and meaning:
  Diffuse Color    albedo of the surface seen by the pixel;
  Diffuse Direct   direct irradiance / pi (so Direct x Color is the reflected direct radiance);
  Diffuse Indirect LPV irradiance / pi;
  Combined         (Direct + Indirect) x Color + emission, the World where no surface is seen,
                   alpha 1 (Cycles' film is opaque by default).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .. import areas, cascades, lookup, sky, sources
from ..engine import Engine, LPVResult, Stats, Timer, light_weight
from ..scene import lights as lights_mod
from ..scene.model import Camera, Scene
from . import contact, direct, raster

VIEWER_NUDGE_CELLS = 0.02  # toward_viewer's distance in cells of the finest cascade
PASS_NAMES = ("Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color")


def toward_viewer(camera, positions: np.ndarray, distance: float) -> np.ndarray:
    """Visible surface points moved ``distance`` towards the camera.

    A pixel on the edge where two walls meet can land exactly on a cell face plane (here the
    other wall's plane), where the lookup's choice of the nearest cell is a tie, and the cell
    behind the other wall reads the dark side (measured: a black line along the Cornell box's
    ceiling edges). The camera sees the point, so the side towards it is open; 2 % of a cell
    decides the tie (injection.visible_corners' tolerance is 0.1 %) and moves the sample by
    2 % of a cell's trilinear span elsewhere."""
    return positions + raster.to_eye(camera.view, camera.projection, positions) * distance


MAX_ANTIALIAS = 8
# A pixel none of whose s x s samples hit a surface, beside one whose samples did, may hold a
# sliver of a surface (Cycles' Diffuse Direct there is that surface's full irradiance): it
# takes the samples on the border of a SLIVER_GRID^2 grid too (render's docstring).
SLIVER_GRID = 4


def render(engine: Engine, scene: Scene, lpv: LPVResult, stats: Stats | None = None) -> dict:
    """Render the scene's camera view; returns {pass name: (H, W, C) float32}, rows top-first.

    Each pass is the mean over settings.antialias^2 sub-pixel samples on a regular grid in the
    pixel: Cycles' one-pixel box filter, so that an edge pixel holds the footprint average of
    both surfaces (and the sky's zero), as the reference does; the diffuse light passes are,
    as Cycles', the samples' reflected light over their colour (even_divide), so that an edge
    pixel's Diffuse Direct is its surfaces' irradiance, not a share of it. One sample at the centre
    aliases: measured at 96x96, indirect relative RMSE against Cycles city 0.765 / sunlit room
    0.422 with one sample, 0.637 / 0.391 with 2^2 and 0.618 / 0.380 with 4^2.

    Sliver pixels: where the s^2 samples all missed but a neighbour's hit, the 12 samples on
    the border of a 4 x 4 grid are added (only there, through a camera cropped to those pixels);
    a pixel's mean is then over its s^2 + 12 samples. A surface covering under a quarter of a
    pixel from its side is missed by 2 x 2 samples and found from an eighth (measured: the
    factory cube at 64 x 48, Diffuse Direct over Cycles' lit pixels 0.964 -> 0.989)."""
    stats = stats or lpv.stats
    if scene.camera is None:
        raise ValueError("the scene has no camera to render from")
    w, h = scene.camera.resolution
    if w <= 0 or h <= 0:
        raise ValueError(f"render resolution {w}x{h} is not positive")
    s = getattr(scene.settings, "antialias", 1)
    if not isinstance(s, (int, np.integer)) or not 1 <= s <= MAX_ANTIALIAS:
        raise ValueError(f"antialias must be a whole number of samples per pixel side from 1 "
                         f"to {MAX_ANTIALIAS}, not {s!r}")
    s = int(s)
    if s == 1:
        return _render_samples(engine, scene, lpv, stats, scene.camera.projection)[0]
    grid = [((i + 0.5) / s, (j + 0.5) / s) for i in range(s) for j in range(s)]
    views: dict = {}  # the contact light's sun views: the same for every sample
    total, hits = _sample_sums(engine, scene, lpv, stats, grid, 1.0 / s, views=views)
    count = np.full((h, w, 1), float(s * s))
    if s * s < SLIVER_GRID * SLIVER_GRID:
        slivers = (hits == 0) & _beside(hits > 0)
        if slivers.any():
            n = SLIVER_GRID
            ring = [((i + 0.5) / n, (j + 0.5) / n) for i in range(n) for j in range(n)
                    if min(i, j) == 0 or max(i, j) == n - 1]
            with Timer(stats, "slivers"):
                ys, xs = np.nonzero(slivers)
                y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
                part = dataclasses.replace(scene, camera=crop(scene.camera, x0, y0, x1, y1))
                only = slivers[y0:y1, x0:x1]
                more, found = _sample_sums(engine, part, lpv, Stats(), ring, 1.0 / n, only,
                                           views)
            # only where the border found a surface: elsewhere the s^2 samples' mean stands
            at = np.zeros_like(slivers)
            at[y0:y1, x0:x1][only] = found > 0
            for name, arr in total.items():
                arr[at] += more[name][found > 0]
            count[at] += len(ring)
            stats.info["sliver_pixels"] = {"looked_at": int(slivers.sum()),
                                           "found": int(at.sum())}
    out = {name: arr / count for name, arr in total.items()}
    for name in LIGHT_PASSES:  # Cycles: the samples' light over the samples' colour
        out[name] = even_divide(total[name], total["Diffuse Color"])
    return {name: arr.astype(np.float32) for name, arr in out.items()}


def _sample_sums(engine: Engine, scene: Scene, lpv: LPVResult, stats: Stats,
                 offsets: list, footprint: float, only: np.ndarray | None = None,
                 views: dict | None = None) -> tuple[dict, np.ndarray]:
    """(sums over the samples at ``offsets`` ((x, y) in the pixel, 0-1) of every pass, the
    light passes weighted by their sample's colour; how many samples hit a surface (H, W)),
    float64; with ``only`` (H, W) bool, of its pixels alone, (K, C) and (K,) in row-major
    order. ``footprint``: a sample's cell side in pixels (the texture footprint)."""
    w, h = scene.camera.resolution
    # the samples take turns over sets of the World's directions (sky.render_directions):
    # their mean integrates the sky over more directions than one set's bands resolve
    sets = min(len(offsets), sky.RENDER_SETS)
    views = {} if views is None else views  # the contact light's sun views, for every sample
    total: dict = {}
    hits = np.zeros((h, w) if only is None else int(only.sum()), np.int32)
    for k, (ox, oy) in enumerate(offsets):
        # the projection moved by a sub-pixel offset, with the image's memory (one image
        # at s times the resolution would need s^2 times)
        proj = np.array(scene.camera.projection, np.float64)
        proj[0] += (ox - 0.5) * 2.0 / w * proj[3]
        proj[1] += (oy - 0.5) * 2.0 / h * proj[3]
        # later samples' skips (the shadow maps the first sample rendered, reused) are
        # not this render's decisions: only their times and drops are kept
        sub = stats if k == 0 else Stats()
        samples, seen = _render_samples(engine, scene, lpv, sub, proj, footprint,
                                        (k % sets, sets), (k, len(offsets)), only, views)
        hits += seen if only is None else seen[only]
        if sub is not stats:
            for key, v in sub.ms.items():
                stats.ms[key] = stats.ms.get(key, 0.0) + v
            for key, v in sub.dropped.items():
                stats.dropped[key] = stats.dropped.get(key, 0) + v
        color = samples["Diffuse Color"] if only is None else samples["Diffuse Color"][only]
        for name, arr in samples.items():
            if only is not None:
                arr = arr[only]
            if name in LIGHT_PASSES:  # weighted by the sample's colour (render)
                arr = arr * color
            if name in total:
                total[name] += arr
            else:
                total[name] = arr.astype(np.float64)
    return total, hits


def crop(camera: Camera, x0: int, y0: int, x1: int, y1: int) -> Camera:
    """The camera that sees only pixels [x0, x1) x [y0, y1) (rows top-first) of ``camera``'s
    image, at the same pixel size: its NDC scaled and shifted so that they fill the frame."""
    w, h = camera.resolution
    cw, ch = int(x1 - x0), int(y1 - y0)
    proj = np.array(camera.projection, np.float64)
    out = proj.copy()
    out[0] = (w / cw) * proj[0] + ((w - 2.0 * x0) / cw - 1.0) * proj[3]
    out[1] = (h / ch) * proj[1] + (1.0 - (h - 2.0 * y0) / ch) * proj[3]
    return dataclasses.replace(camera, projection=out, resolution=(cw, ch))


def _beside(mask: np.ndarray) -> np.ndarray:
    """The pixels of ``mask`` (H, W) and their eight neighbours."""
    pad = np.pad(mask, 1)
    h, w = mask.shape
    return np.logical_or.reduce([pad[y:y + h, x:x + w] for y in range(3) for x in range(3)])


LIGHT_PASSES = ("Diffuse Direct", "Diffuse Indirect")


def even_divide(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a / b per colour channel of (H, W, 3) arrays, as Cycles divides its diffuse light passes
    by the colour (safe_divide_even_color): a channel whose b is 0 takes the mean ratio of
    the pixel's other channels, a pixel whose b is 0 in every channel 0."""
    ok = b > 0
    ratio = np.where(ok, a / np.where(ok, b, 1.0), 0.0)
    count = ok.sum(axis=-1, keepdims=True)
    mean = ratio.sum(axis=-1, keepdims=True) / np.maximum(count, 1)
    return np.where(ok, ratio, np.where(count > 0, mean, 0.0))


def _direct(engine: Engine, scene: Scene, bounds, pos, nrm, stats: Stats, sky_set,
            held: dict | None = None, apart: frozenset = frozenset()):
    """Direct irradiance (M, 3) of every lamp, the World and the emitters at the receivers,
    or None when there is none; with ``held`` (LPVResult.per_light), (that, the same sum with
    each source weighted as combine weighs its grids, 0 for one without grids and for the
    lamps named in ``apart``, or None)."""
    e_dir = e_gi = None
    g = float(scene.settings.intensity)
    for light in scene.lights:
        if light.power <= 0:
            continue
        shadow = engine.shadow_map(scene, light, bounds, scene.settings.shadow_resolution,
                                   stats)
        e = direct.irradiance(light, pos, nrm, shadow)
        e_dir = e if e_dir is None else e_dir + e  # the first light: no zeros added
        if held is not None and held.get(light.name) is not None and light.name not in apart:
            part = e * (light_weight(light)[:, 0] * g)
            e_gi = part if e_gi is None else e_gi + part
    weights = None if held is None else sources.gi_weights(scene, held)
    e_src = sources.direct(engine, scene, bounds, pos, nrm, stats, sky_set=sky_set,
                           weights=weights)
    if held is not None:
        e_src, src_gi = e_src
        if src_gi is not None:
            e_gi = src_gi if e_gi is None else e_gi + src_gi
    if e_src is not None:
        e_dir = e_src if e_dir is None else e_dir + e_src
    return e_dir if held is None else (e_dir, e_gi)


def _sun_views(scene: Scene, lpv: LPVResult) -> list:
    """The suns whose first bounce the contact light gathers in their own view: those with
    grids (LPVResult.per_light)."""
    return [light for light in scene.lights if light.type == "SUN" and light.power > 0
            and lpv.per_light.get(light.name) is not None]


def _contact(engine: Engine, scene: Scene, lpv: LPVResult, bounds, projection, mask, pos,
             nrm, refl, e_gi, stats: Stats, views: dict):
    """Contact irradiance (M, 3) at the covered pixels (render/contact.py), None when no
    pixel bounces light; each pixel's reach is REACH_CELLS cells of the finest cascade
    holding it (0 outside the LPV). ``e_gi``: the GI-weighted direct light the camera's
    pixels bounce, the suns' (_sun_views) left out: their bounce is gathered in each sun's
    view fitted to each cascade (every surface the sun lights, seen or not), ``views``
    caching those views' sources over a render's samples."""
    h, w = mask.shape
    suns = _sun_views(scene, lpv) if refl is not None else []
    flux = None if e_gi is None or refl is None else np.asarray(refl, np.float64) * e_gi
    bounces = flux is not None and bool(flux.any())  # the camera's pixels send light
    if not bounces and not suns:
        return None

    def image(values, shape=()):
        out = np.zeros((h, w) + shape, np.float64)
        out[mask] = values
        return out

    with Timer(stats, "contact"):
        chain = [g for g, _, _ in lpv.fine] + [lpv.grid]  # finest first
        cells = np.array([g.cell_size for g in chain])
        # a surface on a cascade's face (a wall the box was fitted to) is inside it, whatever
        # float rounding says (FACE_TOLERANCE cells): its reach must not depend on where the
        # scene sits
        tol = contact.FACE_TOLERANCE
        level = cascades.assign(chain, pos, margin_cells=-tol)
        reach = contact.REACH_CELLS * cells[level]
        lo, hi = lpv.grid.bounds()
        pad = tol * lpv.grid.cell_size
        reach[~np.all((pos >= lo - pad) & (pos <= hi + pad), axis=1)] = 0.0  # outside: none
        clip_areas = [a for a in scene.areas or () if a.type == "CLIP"]
        region = _regions(clip_areas, pos)
        e = np.zeros((len(pos), 3))
        if bounces:
            area_px, size_px = contact.footprints(scene.camera.view, projection, w, h, pos, nrm)
            edges = contact.patch_edges(scene.camera.view, projection, w, h, pos, nrm)
            e = contact.gather(image(pos, (3,)), image(nrm, (3,)), mask, image(flux, (3,)),
                               image(area_px), image(size_px), image(reach), image(region),
                               image(edges, (2, 3)))[mask]
        g = float(scene.settings.intensity)
        for light in suns:
            weight = light_weight(light)[:, 0] * g
            for c, grid in enumerate(chain):
                rows = np.flatnonzero((level == c) & (reach > 0))
                if not rows.size:
                    continue
                key = (light.name, c)
                if key not in views:
                    # the cascade and a reach around it: its receivers' taps on every side
                    c_lo, c_hi = grid.bounds()
                    margin = contact.REACH_CELLS * grid.cell_size
                    view = lights_mod.light_views(light, bounds,
                                                  (c_lo - margin, c_hi + margin))[0]
                    size = contact.sun_view_size(view, grid.cell_size)
                    source = contact.sun_source(engine.raster, light, view, size, weight)
                    views[key] = view, size, source
                view, size, source = views[key]
                at = region[rows]
                if clip_areas:  # numbered over the receivers and the sun's texels together
                    ids = _regions(clip_areas, np.concatenate(
                        [pos[rows], source.position[source.covered]]))
                    at, source.region[source.covered] = ids[:rows.size], ids[rows.size:]
                texel = 2.0 * view.half_extent / size
                e[rows] += contact.gather_at(
                    pos[rows], nrm[rows], reach[rows], np.full(rows.size, texel), at,
                    contact.view_texels(view, size, pos[rows]), source, False)
    return e


def _regions(clip_areas: list, points: np.ndarray) -> np.ndarray:
    """Clip-region id (N,) int64 of ``points``: the same for points inside the same set of
    clip areas (pixels in different ones do not light each other)."""
    if not clip_areas:
        return np.zeros(len(points), np.int64)
    inside = np.array([areas.inside(a, points) for a in clip_areas]).T
    return np.unique(inside, axis=0, return_inverse=True)[1].ravel().astype(np.int64)


def _through(near, far, trans: np.ndarray, rows: np.ndarray):
    """``near`` (M, 3) with its ``rows`` mixed with ``far`` (len(rows), 3) by the pixels'
    translucency: (1 - t) near + t far."""
    if far is None:
        far = np.zeros((rows.size, 3))
    out = np.zeros((trans.size, 3)) if near is None else np.array(near, np.float64)
    t = trans[rows].astype(np.float64)[:, None]
    out[rows] = (1.0 - t) * out[rows] + t * far
    return out


def _render_samples(engine: Engine, scene: Scene, lpv: LPVResult, stats: Stats,
                    projection: np.ndarray, footprint: float = 1.0,
                    sky_set: tuple[int, int] = (0, 1),
                    seed: tuple[int, int] = (0, 1),
                    only: np.ndarray | None = None,
                    views: dict | None = None) -> tuple[dict, np.ndarray]:
    """(the passes, the pixels whose sample hit a surface (H, W) bool) of one sample per
    pixel through the camera ``projection`` (render's sub-pixel offsets move it); a textured
    albedo is integrated over each sample's cell, ``footprint`` pixels a side
    (Rasterizer.gbuffer); the World's direct light over its directions' set ``sky_set``
    (sources.maps); ``seed``: (sample, samples) of the hashed alpha (each sample keeps other
    fragments of a partly covered surface, their mean its coverage). ``only`` (H, W) bool:
    light only these pixels' surfaces (the others as if they saw none). ``views``: the
    contact light's sun views, kept over a render's samples (_contact)."""
    w, h = scene.camera.resolution
    color = np.zeros((h, w, 3), np.float32)
    diff_dir = np.zeros((h, w, 3), np.float32)
    diff_ind = np.zeros((h, w, 3), np.float32)
    if scene.triangle_count:
        lo, hi = engine.upload(scene, stats)  # the LPV box: shadow maps cover it, not outliers
        with Timer(stats, "gbuffer"):
            # the contact light (our transport's, not KD10's) needs the GI reflectance
            near = (lpv.values is not None and scene.settings.angular == "dom"
                    and scene.settings.contact_light)
            mask, pos, nrm, albedo, receiver, holdout, trans, *refl = engine.raster.gbuffer(
                scene.camera.view, projection, w, h, footprint, holdout=True, seed=seed,
                only=only, reflectance=near)
            color[mask] = albedo
        # a Translucent BSDF's share of a pixel is lit from the far side: its normal turned
        through = np.flatnonzero(trans > 0)
        with Timer(stats, "direct"):
            if near:
                apart = frozenset(light.name for light in _sun_views(scene, lpv))
                e_dir, e_gi = _direct(engine, scene, (lo, hi), pos, nrm, stats, sky_set,
                                      lpv.per_light, apart)
            else:
                e_dir, e_gi = _direct(engine, scene, (lo, hi), pos, nrm, stats, sky_set), None
            if through.size:
                back = _direct(engine, scene, (lo, hi), pos[through], -nrm[through], Stats(),
                               sky_set)
                e_dir = _through(e_dir, back, trans, through)
            if e_dir is not None:
                diff_dir[mask] = e_dir / np.pi
        if lpv.values is not None:
            with Timer(stats, "lookup"):
                # Pixels of non-receivers (Object.lpv.gi_receiver off) get no indirect light.
                recv = receiver
                if not recv.all():
                    stats.skip("lookup", f"{int((~recv).sum())} pixels", "gi_receiver is off")
                e_ind = np.zeros((pos.shape[0], 3))
                backend = engine.backend(scene.settings)  # the lookup runs where it is fastest
                finest = min([lpv.grid.cell_size] + [g.cell_size for g, _, _ in lpv.fine])
                at = toward_viewer(scene.camera, pos, VIEWER_NUDGE_CELLS * finest)
                every = bool(recv.all())  # no masked copies of 1M points when all receive
                rows = slice(None) if every else np.nonzero(recv)[0]
                at_r, nrm_r = at[rows], nrm[rows]
                turned = through[recv[through]] if through.size else through
                far = np.zeros((turned.size, 3))  # the translucent share's, from the far side

                def read(r, at_, nrm_):  # the receivers this read is for, and their light
                    take = r.takes(at_)
                    if take.all():
                        take = slice(None)
                    elif not take.any():
                        return take, None
                    pts = lookup.sample_points(r.grid, at_[take], nrm_[take],
                                               lpv.gaps.get(r.grid))
                    return take, backend.irradiance(
                        r.grid, r.values, pts, nrm_[take], offset_cells=0.0,
                        angular=scene.settings.angular, visibility=r.visibility)

                for r in cascades.reads(lpv):  # the finest cascade holding each, coarser ones added
                    take, e = read(r, at_r, nrm_r)
                    if e is not None:
                        e_ind[take if every else rows[take]] += e
                    if turned.size:
                        take, e = read(r, at[turned], -nrm[turned])
                        if e is not None:
                            far[take] += e
                if near:
                    e_near = _contact(engine, scene, lpv, (lo, hi), projection, mask, pos,
                                      nrm, refl[0] if refl else None, e_gi, stats,
                                      {} if views is None else views)
                    if e_near is not None:  # >= 0 as the lookup's (negative GI weights)
                        e_ind[recv] = np.maximum(e_ind[recv] + e_near[recv], 0.0)
                if turned.size:
                    e_ind = _through(e_ind, far, trans, turned)
                if areas.has_transition(scene.areas):
                    e_ind *= areas.transition_factor(scene.areas, pos)
                diff_ind[mask] = e_ind / np.pi
        else:
            stats.skip("lookup", "all pixels", "no LPV (no GI-contributing light or geometry)")
    # Cycles divides its diffuse light passes by the diffuse colour: where a surface has no
    # diffuse part at all (a metal, glass, emission, holdout shader) they are 0
    bare = ~(color > 0).any(axis=-1)
    diff_dir[bare] = 0.0
    diff_ind[bare] = 0.0
    combined = np.ones((h, w, 4), np.float32)
    combined[..., :3] = (diff_dir + diff_ind) * color
    seen = mask if scene.triangle_count else np.zeros((h, w), bool)
    if scene.film_transparent:  # alpha: what covers the pixel (the samples' mean)
        combined[..., 3] = seen
    sources.camera_light(engine, scene, projection, seen, combined,  # emitters, the World
                         world=not scene.film_transparent, seed=seed, only=only)
    if scene.triangle_count and holdout.any():  # holdouts: 0 with alpha 0, as Cycles
        cut = np.zeros((h, w), bool)
        cut[mask] = holdout
        for arr in (combined, diff_dir, diff_ind, color):
            arr[cut] = 0.0
    passes = {
        "Combined": combined,
        "Diffuse Direct": diff_dir,
        "Diffuse Indirect": diff_ind,
        "Diffuse Color": color,
    }
    for name, arr in passes.items():
        if not np.isfinite(arr).all():
            bad = int((~np.isfinite(arr)).sum())
            stats.dropped[f"nonfinite_pixels_{name}"] = bad
            passes[name] = np.nan_to_num(arr, nan=0.0, posinf=0.0, neginf=0.0)
    return passes, seen
