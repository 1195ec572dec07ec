"""Leave-out planner (lpv_core/planner.py): skip decisions, their reasons, and conservativeness
(a skipped light deposits no flux; a skipped geometry volume blocks nothing)."""

import numpy as np
import pytest

from lpv_core import cascades, geometry_volume, injection, planner
from lpv_core.engine import Stats
from lpv_core.grid import Grid, fit_grid
from lpv_core.scene import Camera, GISettings, Light, make_scene
from tools import core_scenes as demo

BOX_LO, BOX_HI = np.array([4.0, -1.0, -1.0]), np.array([6.0, 1.0, 1.0])


def _scene(tris, lights=(), **kw):
    return make_scene(np.concatenate(tris), lights=list(lights), **kw)


def _light(name, kind, position, direction, **kw):
    return Light(name, kind, demo.light_matrix(np.asarray(position, float), direction), **kw)


def _box_scene(lights=(), **kw):
    """A 2 m cube of triangles at x = 4..6 and a floor far away at x = -10..-8."""
    floor = demo.quad((-10, -1, -1), (-8, -1, -1), (-8, 1, -1), (-10, 1, -1))
    return _scene([demo.box_triangles(BOX_LO, BOX_HI), floor], lights, **kw)


def _box_grid():
    return fit_grid(BOX_LO, BOX_HI, 8)


# ------------------------------------------------------------------------------------ lights

def test_spot_pointing_away_from_a_box_is_skipped_and_into_it_kept():
    sc = _box_scene()
    g = _box_grid()
    away = _light("Away", "SPOT", (0, 0, 0), (-1, 0, 0), spot_size=np.radians(60))
    into = _light("Into", "SPOT", (0, 0, 0), (1, 0, 0), spot_size=np.radians(10))
    beside = _light("Beside", "SPOT", (0, 0, 0), (0.5, 1, 0), spot_size=np.radians(40))
    d_away, d_into, d_beside = planner.light_plan([away, into, beside], g, sc, "cascade 0")
    assert not d_away.keep and "'Away'" in d_away.what
    assert "60\u00b0 spot cone" in d_away.reason and "cascade 0" in d_away.reason
    assert d_into.keep and "reaches" in d_into.reason
    assert not d_beside.keep and "spot cone" in d_beside.reason
    # the single-light form agrees
    assert planner.light_reach(away, g, sc).keep is False


def test_spot_whose_cone_meets_the_box_but_none_of_its_casters_is_skipped():
    # a big grid holding the cube; the spot lights the grid's empty part above the cube
    sc = _box_scene()
    g = Grid((2.0, -3.0, -1.5), 0.5, 16)  # x 2..10, y -3..5, z -1.5..6.5
    spot = _light("Up", "SPOT", (5.0, 0.0, 3.0), (0, 0, 1), spot_size=np.radians(90))
    d = planner.light_reach(spot, g, sc, "cascade 1")
    assert not d.keep
    assert "none of the 12 caster triangles inside cascade 1" in d.reason
    down = _light("Down", "SPOT", (5.0, 0.0, 3.0), (0, 0, -1), spot_size=np.radians(20))
    assert planner.light_reach(down, g, sc).keep


def test_point_and_area_lights_outside_a_box():
    sc = _box_scene()
    g = _box_grid()
    point = _light("Point", "POINT", (0, 0, 0), (-1, 0, 0))
    d = planner.light_reach(point, g, sc)
    assert d.keep and "12 caster triangles" in d.reason
    facing = _light("AreaIn", "AREA", (0, 0, 0), (1, 0.3, 0), size=(1.0, 1.0))
    away = _light("AreaOut", "AREA", (0, 0, 0), (-1, 0.3, 0), size=(1.0, 1.0))
    d_in, d_out = planner.light_plan([facing, away], g, sc)
    assert d_in.keep
    assert not d_out.keep and "'AreaOut'" in d_out.what
    assert "hemisphere" in d_out.reason and "lies outside" in d_out.reason
    # an area light whose plane cuts the box: the box is partly in front, its casters are not
    cut = _light("AreaCut", "AREA", (3.9, 0, 0), (-1, 0, 0))
    d_cut = planner.light_reach(cut, Grid((2.0, -2.0, -2.0), 0.5, 16), sc)
    assert not d_cut.keep and "none of the 12 caster triangles" in d_cut.reason


def test_lights_need_caster_geometry_in_the_box():
    empty = Grid((20.0, 20.0, 20.0), 0.25, 8)
    sc = _box_scene()
    sun = _light("Sun", "SUN", (0, 0, 0), (0.2, 0.1, -1), power=3.0)
    point = _light("Point", "POINT", (21, 21, 21), (0, 0, -1))
    for d in planner.light_plan([sun, point], empty, sc, "cascade 0"):
        assert not d.keep and "no caster geometry inside cascade 0" in d.reason
    assert planner.light_reach(sun, _box_grid(), sc).keep  # a sun reaches any caster
    # geometry that does not cast GI (flag off, or black) puts no VPL into the box
    no_cast = _box_scene(caster=np.zeros(14, bool))
    assert not planner.light_reach(point, _box_grid(), no_cast).keep


def test_a_triangle_crossing_the_box_counts_without_a_vertex_inside():
    ground = demo.quad((-100, -100, 0), (100, -100, 0), (100, 100, 0), (-100, 100, 0))
    sc = _scene([ground])
    g = Grid((-1.0, -1.0, -1.0), 0.25, 8)  # 2 m box around the origin, far from every corner
    lamp = _light("Lamp", "SPOT", (0, 0, 5), (0, 0, -1), spot_size=np.radians(30))
    assert planner.light_reach(lamp, g, sc).keep
    assert planner.occlusion_needed(sc, g).keep
    off = _light("Off", "SPOT", (30, 0, 5), (0, 0, -1), spot_size=np.radians(30))
    d = planner.light_reach(off, g, sc)  # lights the same two triangles, but outside the box
    assert not d.keep and "spot cone" in d.reason


# ---------------------------------------------------------------------------------- cascades

def test_inner_cascades_in_empty_space_are_skipped():
    # two buildings 60 m apart; the camera stands between them looking at the sky
    sc = _scene([demo.box_triangles((-5, -5, 0), (5, 5, 20)),
                 demo.box_triangles((55, -5, 0), (65, 5, 20))])
    sc.camera = Camera.look_at((30, 0, 2), (30.5, 0.3, 40))
    lo, hi = sc.bounds()
    chain = cascades.place(lo, hi, 16, 3, sc.camera)
    # independent check that the inner boxes hold no geometry: dense surfels of every triangle
    pts, _, _ = geometry_volume.surfels(sc.positions, 0.1 * chain[0].cell_size)
    for g in chain[:2]:
        glo, ghi = g.bounds()
        assert not np.any(np.all((pts >= glo) & (pts <= ghi), axis=1))
    plan = planner.cascade_plan(chain, sc)
    assert [d.keep for d in plan] == [False, False, True]
    assert plan[0].reason.startswith("no caster or receiver geometry inside cascade 0 (cell ")
    assert plan[0].what == planner.cascade_label(0, chain[0])
    # a camera next to a building, looking at it: the inner cascades hold geometry
    sc.camera = Camera.look_at((8, 0, 2), (0, 0, 5))
    chain = cascades.place(lo, hi, 16, 3, sc.camera)
    assert all(d.keep for d in planner.cascade_plan(chain, sc))


def test_finer_cascades_hold_the_middle_of_what_the_screen_shows():
    """A camera looking at a group of objects 45-50 m away over a near ground 5-15 m away,
    the group 70 % of the seen points: each finer cascade is centred on the median of the
    seen points its parent holds, so the finest (under 30 m wide) holds the whole group. Centred on
    the points within its width of the eye (the near ground) it held none of it, and the
    group was read from cells twice as large."""
    rng = np.random.default_rng(3)
    group = rng.uniform([25.0, -3.0, 0.0], [30.0, 3.0, 4.0], (700, 3))
    near = np.c_[rng.uniform(-15.0, -5.0, 300), rng.uniform(-4.0, 4.0, 300), np.zeros(300)]
    focus = np.concatenate([group, near])
    camera = Camera.look_at((-20.0, 0.0, 5.0), (28.0, 0.0, 1.0))
    chain = cascades.place(np.full(3, -50.0), np.full(3, 50.0), 16, 3, camera, focus)
    assert chain[0].cell_size * 16 < 30.0  # narrower than the eye's distance to the group
    for g in chain:
        lo, hi = g.bounds()
        assert np.all((group >= lo) & (group <= hi))
    # the middle cascade's box holds the group and none of the near ground
    lo, hi = chain[1].bounds()
    assert not np.any(np.all((near >= lo) & (near <= hi), axis=1))
    # no seen point in the parent: KD10's push along the view, as without focus points
    assert ([g.origin for g in cascades.place(np.full(3, -50.0), np.full(3, 50.0), 16, 3,
                                              camera, np.full((4, 3), 1e3))]
            == [g.origin for g in cascades.place(np.full(3, -50.0), np.full(3, 50.0), 16, 3,
                                                 camera)])


def test_a_room_that_fits_in_the_finest_cascade_needs_one():
    room = demo.cornell_box("SPOT")
    lo, hi = room.bounds()
    fine = fit_grid(lo, hi, 16)
    side = fine.cell_size * 16
    outer = Grid(tuple(fine.origin_array - 0.5 * side), 2 * fine.cell_size, 16)
    plan = planner.cascade_plan([fine, outer], room)
    assert [d.keep for d in plan] == [True, False]
    assert "cascade 0" in plan[1].reason and "already holds all" in plan[1].reason
    assert "kept instead of the 1 coarser" in plan[0].reason
    # three cascades, the middle one fits: the finest keeps its detail, the outer one goes
    finest = Grid(tuple(fine.origin_array + 0.25 * side), 0.5 * fine.cell_size, 16)
    plan = planner.cascade_plan([finest, fine, outer], room)
    assert [d.keep for d in plan] == [True, True, False]
    # cascades.place keeps the inner ones smaller than the scene: all three are needed outdoors
    out = demo.outdoor(settings=GISettings(grid_resolution=32, cascades=3))
    chain = cascades.place(*out.bounds(), 32, 3, out.camera)
    assert all(d.keep for d in planner.cascade_plan(chain, out))


def test_geometry_that_neither_casts_nor_receives_keeps_one_cascade():
    tris = demo.box_triangles((0, 0, 0), (1, 1, 1))
    flags = np.zeros(12, bool)
    sc = _scene([tris], caster=flags, receiver=flags)
    sc.camera = Camera.look_at((0.5, -3, 0.5), (0.5, 0.5, 0.5))
    chain = cascades.place(*sc.bounds(), 8, 2, sc.camera)
    plan = planner.cascade_plan(chain, sc)
    assert [d.keep for d in plan] == [False, True]
    assert "no caster or receiver geometry in the scene" in plan[0].reason
    assert all(not d.keep for d in planner.cascade_plan(chain, _scene([np.zeros((0, 3, 3))])))


# --------------------------------------------------------------------------------- occlusion

def test_geometry_volume_needs_occluders_in_the_grid():
    g = _box_grid()
    d = planner.occlusion_needed(_box_scene(occluder=np.zeros(14, bool)), g, "cascade 0")
    assert not d.keep and d.reason == "no occluder in the scene" and "cascade 0" in d.what
    only_far = np.r_[np.zeros(12, bool), np.ones(2, bool)]  # only the far floor occludes
    d = planner.occlusion_needed(_box_scene(occluder=only_far), g)
    assert not d.keep and d.reason.startswith("no occluder triangle inside")
    assert planner.occlusion_needed(_box_scene(), g).keep
    off = _box_scene(settings=GISettings(occlusion=False))
    assert "off" in planner.occlusion_needed(off, g).reason


def test_skipped_geometry_volumes_block_nothing():
    rng = np.random.default_rng(3)
    g = Grid((0.0, 0.0, 0.0), 0.5, 8)
    skipped = kept = 0
    for _ in range(60):
        c = rng.uniform(-1.5, 5.5, 3)
        tri = c + rng.normal(scale=0.4, size=(1, 3, 3))
        sc = _scene([tri])
        d = planner.occlusion_needed(sc, g)
        blocks = np.any(geometry_volume.occluder_visibility(g, sc.positions) < 1)
        if d.keep:
            kept += 1
        else:
            skipped += 1
            assert not blocks, d.reason
    assert skipped > 5 and kept > 5


# ------------------------------------------------------------------------------ stats helper

def test_record_reports_skips_to_stats():
    stats = Stats()
    plan = [planner.Decision(True, "fine", "cascade 0"),
            planner.Decision(False, "no geometry", "cascade 1")]
    assert planner.record(plan, stats, "cascades") == [True, False]
    assert stats.skipped == [{"stage": "cascades", "what": "cascade 1", "reason": "no geometry"}]
    assert planner.record(plan[1], None, "rsm") == [False]


# ------------------------------------------------------------------ conservative vs the RSM

@pytest.fixture(scope="module")
def raster():
    from lpv_core.render.raster import Rasterizer

    r = Rasterizer()
    yield r
    r.release()


def test_a_skipped_light_deposits_no_flux_in_the_grid(raster):
    from lpv_core.rsm import render_rsm

    rng = np.random.default_rng(11)
    tris = [demo.quad((-6, -6, 0), (6, -6, 0), (6, 6, 0), (-6, 6, 0))]
    for _ in range(5):
        c = rng.uniform(-4, 4, 3) * [1, 1, 0]
        tris.append(demo.box_triangles(c, c + rng.uniform(0.5, 2.5, 3)))
    caster = np.ones(sum(len(t) for t in tris), bool)
    caster[-12:] = False  # one block shadows but does not bounce
    sc = _scene(tris, caster=caster, settings=GISettings(rsm_resolution=64))
    raster.upload(sc.positions, sc.normals, sc.albedo_per_triangle(),
                  sc.reflectance_per_triangle())
    bounds = sc.bounds()
    skipped = kept = 0
    for _ in range(24):
        kind = rng.choice(["SPOT", "SPOT", "AREA", "POINT", "SUN"])
        direction = rng.normal(size=3)
        light = _light(f"L{kind}", kind, rng.uniform(-7, 7, 3) + [0, 0, 3], direction,
                       spot_size=rng.uniform(np.radians(10), np.radians(170)),
                       spot_blend=rng.uniform(0, 1), power=100.0)
        cell = rng.uniform(0.1, 0.6)
        g = Grid(tuple(rng.uniform(-6, 6, 3) * [1, 1, 0.3]), cell, 8)
        d = planner.light_reach(light, g, sc)
        if d.keep:
            kept += 1
            continue
        skipped += 1
        rsm = render_rsm(raster, light, bounds, sc.settings.rsm_resolution)
        grid = injection.inject(g, rsm.position, rsm.normal, rsm.flux)
        assert not np.any(grid), f"{d.what}: {d.reason}"
    assert skipped >= 5 and kept >= 3


# ------------------------------------------------------------------- wired into Engine.update

def _skips(stats, stage):
    return [s for s in stats.skipped if s["stage"] == stage]


def test_engine_skips_empty_cascades_and_unreachable_lights_and_says_why():
    """Engine.update runs the planner: empty inner cascades and a light that reaches no caster
    are left out (listed in the stats with their reasons); the others still run."""
    from lpv_core import engine

    sc = _scene([demo.box_triangles((-5, -5, 0), (5, 5, 20)),
                 demo.box_triangles((55, -5, 0), (65, 5, 20))],
                lights=[_light("Sky", "SPOT", (30, 0, 30), (0, 0, 1), spot_size=np.radians(30),
                               power=1000.0),
                        _light("Wall", "SPOT", (30, 0, 10), (-1, 0, -0.2),
                               spot_size=np.radians(30), power=1000.0)],
                settings=GISettings(grid_resolution=12, cascades_auto=False, cascades=3))
    sc.camera = Camera.look_at((30, 0, 2), (30.5, 0.3, 40))
    stats = Stats()
    res = engine.Engine().update(sc, stats)
    cascade_skips = _skips(stats, "cascades")
    assert [s["what"].split(" (")[0] for s in cascade_skips] == ["cascade 0", "cascade 1"]
    assert all("no caster or receiver geometry" in s["reason"] for s in cascade_skips)
    assert res.fine == []  # only the outer cascade ran
    rsm_skips = {s["what"]: s["reason"] for s in _skips(stats, "rsm")}
    assert "light 'Sky'" in rsm_skips and "spot cone" in rsm_skips["light 'Sky'"]
    assert "light 'Wall'" not in rsm_skips
    assert res.values is not None and res.values[..., 0].sum() > 0  # the wall light ran
    assert float(np.abs(res.per_light["Sky"]).max()) == 0.0


def test_engine_skips_the_geometry_volume_without_occluders_in_the_grid():
    from lpv_core import engine

    sc = demo.cornell_box("SPOT", (16, 16), GISettings(grid_resolution=8))
    sc.occluder = np.zeros(sc.triangle_count, bool)
    stats = Stats()
    res = engine.Engine().update(sc, stats)
    occ = _skips(stats, "occlusion")
    assert len(occ) == 1 and occ[0]["reason"] == "no occluder in the scene"
    assert res.visibility is None and "geometry_volume" not in stats.ms


# ------------------------------------------------------------------------------ cascade count
def _view_at(distances, eye=(-10.0, 0.0, 5.0)):
    """Visible points at the given distances from ``eye`` along +x."""
    eye = np.asarray(eye, float)
    return eye, eye + np.outer(np.asarray(distances, float), [1.0, 0.0, 0.0])


def test_cascade_count_follows_the_nearest_part_of_an_open_view():
    """n - 1 = round(log2(extent / d)), d the distance to the nearest tenth of the visible
    surface: each cascade halves the cell, so the finest one resolves the near part of the
    view as the outer one resolves the scene."""
    lo, hi = (0.0, 0.0, 0.0), (100.0, 100.0, 10.0)
    for near, expect in ((100.0, 1), (50.0, 2), (25.0, 3), (12.0, 3), (160.0, 1)):
        eye, pts = _view_at(np.linspace(near, near * 3, 101))
        count, why = planner.cascade_count(3, lo, hi, eye, pts, sky_share=0.4)
        assert count == expect, (near, count, why)
        assert f"{1.2 * near:.3g} m" in why and "100 m wide" in why  # 10 % quantile: 1.2 near
    eye, pts = _view_at(np.linspace(12.0, 36.0, 101))
    assert planner.cascade_count(2, lo, hi, eye, pts, 0.4)[0] == 2  # capped by the setting
    assert planner.cascade_count(1, lo, hi, eye, pts, 0.4)[0] == 1


def test_cascade_count_is_one_for_an_enclosed_view_and_scale_free():
    lo, hi = np.zeros(3), np.array([16.0, 10.0, 4.0])
    eye = np.array([2.0, 5.0, 1.6])
    pts = eye + np.outer(np.linspace(1.0, 14.0, 50), [1.0, 0.0, 0.0])
    count, why = planner.cascade_count(3, lo, hi, eye, pts, sky_share=0.0)
    assert count == 1 and "enclosed view" in why
    # the same room with a large opening to the sky is an open view: the ratio decides
    open_count = planner.cascade_count(3, lo, hi, eye, pts, sky_share=0.3)[0]
    assert open_count == min(3, 1 + round(np.log2(16.0 / np.quantile(np.linspace(1, 14, 50), 0.1))))
    for k in (1e-3, 1e3):  # the decision depends on ratios only
        assert planner.cascade_count(3, lo * k, hi * k, eye * k, pts * k, 0.3)[0] == open_count
    assert planner.cascade_count(3, lo, hi, eye, np.zeros((0, 3)), 0.3)[0] == 1
    assert planner.cascade_count(3, lo, hi, None, pts, 0.3)[0] == 1


def test_cascade_count_holds_within_the_hysteresis_band():
    """A count changes only when log2(extent / d) is COUNT_HYSTERESIS past the rounding
    boundary, so a camera moving back and forth near it does not flip the whole LPV."""
    lo, hi = (0.0, 0.0, 0.0), (100.0, 100.0, 10.0)

    def at(log_ratio, previous):
        near = 100.0 / 2.0**log_ratio
        eye, pts = _view_at(np.full(20, near))
        return planner.cascade_count(3, lo, hi, eye, pts, 0.5, previous)[0]

    assert at(1.6, None) == 3 and at(1.6, 2) == 2  # past 1.5 but within the band: hold 2
    assert at(1.8, 2) == 3  # beyond it: change
    assert at(0.4, None) == 1 and at(0.4, 2) == 2 and at(0.2, 2) == 1


def test_engine_holds_a_cascade_count_for_a_moving_camera_only():
    """The count the hysteresis holds is the last update's under the same cap: after the camera
    moves within the band it stays, but a changed settings.cascades or a clear_cache decides
    afresh (a settings sweep's runs, each from cleared caches, do not depend on their order)."""
    from lpv_core import engine

    def view(height: float, cap: int = 3):
        sc = demo.outdoor((48, 32), GISettings(grid_resolution=8, rsm_resolution=32,
                                               cascades=cap))
        sc.camera = Camera.look_at((0.0, -60.0, height), (0.0, 40.0, 8.0),
                                   fov_y=np.radians(50), resolution=(48, 32), near=0.1,
                                   far=500.0)
        return sc

    def count(eng, sc) -> int:
        stats = Stats()
        eng.update(sc, stats)
        return stats.info["cascade_count"]["count"]

    stats = Stats()
    engine.Engine().update(view(50.0), stats)
    ratio = float(stats.info["cascade_count"]["why"].split("log2 ratio ")[1].split(")")[0])
    assert 1.5 <= ratio < 1.5 + planner.COUNT_HYSTERESIS  # 3 afresh, 2 held from below
    assert stats.info["cascade_count"]["count"] == 3
    eng = engine.Engine()
    assert count(eng, view(60.0)) == 2 and count(eng, view(50.0)) == 2  # moved: held
    eng.clear_cache()
    assert count(eng, view(50.0)) == 3
    eng = engine.Engine()
    assert count(eng, view(50.0, cap=2)) == 2
    assert count(eng, view(50.0)) == 3  # the cap raised to 3: not held at the old cap's 2


def test_engine_picks_the_cascade_count_per_view_and_says_why():
    """On built scenes: the street-level outdoor view gets all 3 cascades, a camera inside a
    closed room and the Cornell box seen from outside get one; the stats say why."""
    from lpv_core import engine

    cases = {"outdoor": (demo.outdoor((48, 32), GISettings(grid_resolution=8, rsm_resolution=32)),
                         3),
             "room": (demo.two_rooms(GISettings(grid_resolution=8, rsm_resolution=32)), 1),
             "cornell": (demo.cornell_box("SPOT", (24, 24), GISettings(grid_resolution=8,
                                                                       rsm_resolution=32)), 1)}
    for name, (sc, expect) in cases.items():
        assert sc.settings.cascades == 3 and sc.settings.cascades_auto  # the defaults
        stats = Stats()
        res = engine.Engine().update(sc, stats)
        info = stats.info["cascade_count"]
        assert info["count"] == expect, (name, info)
        assert len(res.fine) + 1 <= expect
        if expect < 3:
            assert any(s["stage"] == "cascades" and s["reason"] == info["why"]
                       for s in stats.skipped), name
    assert "enclosed view" in stats_reason(cases["room"][0])
    fixed = demo.outdoor((48, 32), GISettings(grid_resolution=8, rsm_resolution=32,
                                              cascades=2, cascades_auto=False))
    stats = Stats()
    engine.Engine().update(fixed, stats)
    assert "cascade_count" not in stats.info and len(stats.info["cascades"]) == 2


def stats_reason(scene) -> str:
    from lpv_core import engine

    stats = Stats()
    engine.Engine().update(scene, stats)
    return stats.info["cascade_count"]["why"]
