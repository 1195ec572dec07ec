"""The World's shadow maps drawn in one atlas (lpv_core/render/atlas.py): each tile's depth
against the plane a ray through its texel centre meets (analytic), and against the one-pass-
per-map shadow map of render/direct.py (which reads positions back) on a scene of boxes; the
GI's one-tap sky light (sky._one_tap) against the visible sky's view factor."""

import numpy as np

from lpv_core import engine, sky, sources
from lpv_core.propagation.quadrature import quadrature_directions
from lpv_core.render import atlas, direct
from lpv_core.render.raster import Rasterizer
from lpv_core.scene import Material, lights, make_scene
from tools.core_scenes import box_triangles, quad


def _raster(tris: np.ndarray, alpha=None) -> Rasterizer:
    r = Rasterizer()
    n = np.broadcast_to(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])[:, None],
                        tris.shape).copy()
    r.upload(tris, n, np.ones((len(tris), 3)), np.ones((len(tris), 3)), origin=[0.3, -0.2, 0.1],
             alpha=alpha)
    return r


Z0 = 0.5  # the square's height


def _square_and_views():
    """A 2 x 2 m square at z = Z0 and the views of 11 of the 12 of 32 directions more than
    15 degrees above it, their windows on the square."""
    tris = quad([-1, -1, Z0], [1, -1, Z0], [1, 1, Z0], [-1, 1, Z0])
    d = quadrature_directions(32)
    suns = sky.suns(d[d[:, 2] > np.sin(np.radians(15))][:11])
    bounds = (np.array([-2.0, -2, -1]), np.array([2.0, 2, 2]))
    fit = (np.array([-1.2, -1.2, 0.4]), np.array([1.2, 1.2, 0.6]))
    return tris, [lights.light_views(s, bounds, fit)[0] for s in suns]


def test_each_tile_holds_the_depth_of_the_plane_its_texels_see():
    """A 2 x 2 m square at z = 0.5 seen from 11 of the 12 of 32 directions more than 15 degrees
    above it (one tile each, a 4 x 3 atlas with one tile empty): texels whose centre's ray meets the square away from its edges hold
    -(view @ hit).z (1e-5 m), those missing it by more than a texel inf."""
    res = 48
    tris, views = _square_and_views()
    got = atlas.DepthAtlas(_raster(tris)).render(views, res)
    assert got.shape == (11, res, res)
    c = (np.arange(res) + 0.5) / res * 2 - 1
    for view, tile in zip(views, got):
        inv = np.linalg.inv(view.view)
        u, v = np.meshgrid(c * view.half_extent, -c * view.half_extent)  # rows top-first
        start = (inv[:3, :3] @ np.stack([u, v, np.zeros_like(u)]).reshape(3, -1)).T + inv[:3, 3]
        ray = -inv[:3, 2]
        t = (Z0 - start[:, 2]) / ray[2]
        hit = start + t[:, None] * ray
        depth = -(np.c_[hit, np.ones(len(hit))] @ view.view[2]).reshape(res, res)
        texel = 2 * view.half_extent / res / abs(ray[2])
        edge = np.max(np.abs(hit[:, :2]), axis=1).reshape(res, res)
        inside, outside = edge < 1 - 2 * texel, edge > 1 + 2 * texel
        assert inside.sum() > 100 and outside.sum() > 100
        np.testing.assert_allclose(tile[inside], depth[inside], atol=1e-5)
        assert np.isinf(tile[outside]).all()


def test_a_squares_coverage_is_the_share_of_its_texels_each_tile_holds():
    """The square of the test above at Alpha 0.3, 0.7 and 1 (Material.alpha per triangle): the
    hashed coverage keeps that share of the texels inside it (over the 11 tiles' ~4,000
    texels within 0.02; a tile's ~400 within 0.08, 3.5 binomial deviations), so the World's
    maps shade by it as Cycles' transparent shadows; an opaque scene's maps are drawn without
    the hash (Rasterizer.hashed) and hold every texel."""
    res = 48
    tris, views = _square_and_views()
    opaque = atlas.DepthAtlas(_raster(tris)).render(views, res)
    inside = np.isfinite(opaque)
    assert inside.sum() > 11 * 300
    for alpha in (0.3, 0.7, 1.0):
        r = _raster(tris, np.full(len(tris), alpha))
        assert r.hashed == (alpha < 1.0)
        got = atlas.DepthAtlas(r).render(views, res)
        assert not np.isfinite(got[~inside]).any()
        share = np.isfinite(got).sum(axis=(1, 2)) / inside.sum(axis=(1, 2))
        np.testing.assert_allclose(share, alpha, atol=0.08 if alpha < 1 else 0.0)
        assert abs(np.isfinite(got).sum() / inside.sum() - alpha) <= 0.02


def test_atlas_matches_one_pass_per_direction():
    """The pixels' 128 directions at 256^2 (two columns of tiles where the driver's largest
    viewport is 16384) over a room of boxes, then 40 of them at 96^2 in the same atlas's corner
    as in an atlas of their own: the atlas and render_shadow_map agree but
    on silhouette texels (0.04 %: the atlas draws each map upside down, so that GL's rows come
    back top-first, and the fill rule breaks a texel centre on an edge the other way)."""
    tris = np.concatenate([box_triangles(np.array([-1.0, -1, 0]), np.array([1.0, 1, 2]),
                                         inward=True),
                           box_triangles(np.array([-0.4, -0.3, 0]), np.array([0.2, 0.4, 1.2]))])
    raster, res = _raster(tris), sky.SHADOW_RESOLUTION
    box = (np.array([-1.0, -1, 0]), np.array([1.0, 1, 2]))
    fit = (np.array([-0.9, -0.9, 0.1]), np.array([0.9, 0.9, 1.9]))
    suns = sky.suns(quadrature_directions(sky.RENDER_DIRECTIONS))
    shared = atlas.DepthAtlas(raster)
    maps = sky.shadow_maps(shared, suns, box, fit, res)
    want = np.stack([direct.render_shadow_map(raster, s, box, res, fit).stacked()[0]
                     for s in suns])
    got = sky._stacked(maps)
    assert got.shape == want.shape and all(m.resolution == res for m in maps)
    assert [m.views[0].half_extent for m in maps] == [
        lights.light_views(s, box, fit)[0].half_extent for s in suns]
    g, w = (np.nan_to_num(a, posinf=-1.0) for a in (got, want))  # the scene lies at depth > 0
    differ = np.abs(g - w) >= 1e-4
    near = np.lib.stride_tricks.sliding_window_view(
        np.pad(w, ((0, 0), (1, 1), (1, 1)), mode="edge"), (3, 3), axis=(1, 2))
    silhouette = np.ptp(near, axis=(-2, -1)) > 1e-3  # a depth step within a texel
    assert np.isfinite(want).mean() > 0.5 and differ.sum() <= 1e-3 * differ.size
    assert not (differ & ~silhouette).any()
    views = [m.views[0] for m in maps[:40]]  # fewer, smaller maps in the same, larger atlas
    np.testing.assert_array_equal(shared.render(views, 96),
                                  atlas.DepthAtlas(raster).render(views, 96))


def test_gi_sky_light_of_one_tap_beside_a_long_wall_is_the_visible_skys_view_factor():
    """Floor points 0.5..8 m from a 4 m wall (tests/test_sources.py's case) lit by the GI's 64
    directions with one tap per direction: E / (pi L) within 10 % of the view factor at each
    point (the 64 directions' banding: 8.8 % measured, 8.3 % with 2x2 PCF) and 2 % over the
    points' mean (0.3 %)."""
    from tests.test_sources import L, camera, floor_and_wall, sky_fraction, uniform

    x = np.array([0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0])
    scene = make_scene(floor_and_wall(), materials=[Material("grey")], lights=[],
                       camera=camera([0, -12, 6], [0, -3, 0]), world=uniform())
    eng = engine.Engine()
    eng.update(scene)
    sm = sources.maps(eng, scene, eng.lpv_bounds(scene), engine.Stats())
    e = sky.irradiance(*sm.world[(sky.DIRECTIONS, 0, 1)][1:], np.c_[0.3 * x, -x, np.zeros_like(x)],
                       np.tile([0, 0, 1.0], (len(x), 1)), pcf=False)
    got, want = e[:, 0] / (np.pi * L), sky_fraction(x, 4.0)
    np.testing.assert_allclose(got, want, rtol=0.10)
    assert abs(got.mean() / want.mean() - 1.0) < 0.02
