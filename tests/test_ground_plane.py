"""A closed room standing on a huge ground keeps its indirect light: the LPV box is the space
the camera is in, not the ground's 2 km (cascades.fit_bounds with the camera's surroundings,
planner.cascade_count); an open outdoor scene on a big ground keeps its cascades."""

import numpy as np
import pytest
from test_far_origin import closed_cornell

from lpv_core import engine
from lpv_core.engine import Stats
from lpv_core.render import deferred, error
from lpv_core.scene import GISettings, Material, make_scene
from tools import core_scenes as demo

SETTINGS = GISettings(grid_resolution=16, rsm_resolution=64, shadow_resolution=256,
                      antialias=1)


def _on_ground(scene, ground: np.ndarray):
    """``scene`` with the triangles ``ground`` added (their own grey material)."""
    mats = list(scene.materials) + [Material("ground", np.full(3, 0.5, np.float32))]
    return make_scene(np.concatenate([scene.positions, ground]),
                      material_index=np.concatenate([scene.material_index,
                                                     np.full(len(ground), len(mats) - 1)]),
                      materials=mats, lights=scene.lights, camera=scene.camera,
                      settings=scene.settings)


def _render(scene):
    eng = engine.Engine()
    stats = Stats()
    passes = deferred.render(eng, scene, eng.update(scene, stats))
    return passes["Diffuse Indirect"].astype(np.float64), stats


GROUNDS = {
    # a 2 km ground quad 5 cm below the room's floor
    "2 km quad": demo.quad((-1000, -1000, -0.05), (1000, -1000, -0.05), (1000, 1000, -0.05),
                           (-1000, 1000, -0.05)),
    # one triangle 1e6 m across, under the room
    "1e6 m triangle": np.array([[[-5e5, -5e5, -0.05], [5e5, -5e5, -0.05], [0, 5e5, -0.05]]]),
}


@pytest.mark.parametrize("ground", list(GROUNDS))
def test_closed_room_on_a_huge_ground_keeps_its_indirect_light(ground):
    room = closed_cornell("POINT", (0, 0, 0), SETTINGS)
    alone, _ = _render(room)
    on_ground, stats = _render(_on_ground(room, GROUNDS[ground]))
    assert alone.mean() > 0
    ratio = on_ground.mean() / alone.mean()
    rmse = error.relative_rmse(on_ground, alone)
    assert 0.9 <= ratio <= 1.1 and rmse <= 0.1, (ratio, rmse)
    # the stats say that the ground outside the room was left out, and why
    assert stats.info["lpv_bounds"]["outside_triangles"] == len(GROUNDS[ground])
    assert any(s["stage"] == "lpv" and "enclos" in s["reason"] for s in stats.skipped)


def test_open_outdoor_scene_on_a_big_ground_keeps_its_cascades():
    """core_scenes.outdoor with its 200 m ground replaced by a 2 km one: the street-level view
    sees the sky, so the LPV still covers the ground (nothing left out) and the view gets all
    three cascades, the finest around what the camera sees."""
    base = demo.outdoor((48, 32), GISettings(grid_resolution=8, rsm_resolution=32))
    big = demo.quad((-1000, -1000, 0), (1000, -1000, 0), (1000, 1000, 0), (-1000, 1000, 0))
    sc = make_scene(np.concatenate([big, base.positions[2:]]),
                    material_index=base.material_index, materials=base.materials,
                    lights=base.lights, camera=base.camera, settings=base.settings)
    stats = Stats()
    res = engine.Engine().update(sc, stats)
    assert stats.info["cascade_count"]["count"] == 3
    assert stats.info["lpv_bounds"]["outside_triangles"] == 0
    lo, hi = np.array(stats.info["lpv_bounds"]["lo"]), np.array(stats.info["lpv_bounds"]["hi"])
    assert np.allclose(lo[:2], -1000) and np.allclose(hi[:2], 1000)
    finest = res.fine[0][0] if res.fine else res.grid
    f_lo, f_hi = finest.bounds()
    eye = sc.camera.position
    assert np.all(f_lo <= eye) and np.all(eye <= f_hi)  # the finest cascade holds the camera


def test_a_small_space_in_a_large_box_is_not_an_enclosed_view():
    """The camera inside the box and surrounded by walls, but the space around it (the
    surroundings' size) a hundredth of the box: finer cascades, by the near-view rule."""
    from lpv_core import planner

    lo, hi = np.array([-1000.0, -1000.0, -1.0]), np.array([1000.0, 1000.0, 3.0])
    eye = np.array([0.0, 0.0, 1.0])
    pts = eye + np.outer(np.linspace(1.0, 2.0, 50), [1.0, 0.0, 0.0])
    assert planner.cascade_count(3, lo, hi, eye, pts, 0.0)[0] == 1  # without the space: enclosed
    count, why = planner.cascade_count(3, lo, hi, eye, pts, 0.0, space=4.0)
    assert count == 3 and "enclosed" not in why
    assert planner.cascade_count(3, lo, hi, eye, pts, 0.0, space=1500.0)[0] == 1


def test_the_enclosure_box_is_the_room_wherever_the_eye_stands():
    """Its faces sit on the walls (triangle corners), not on float32 hit points: the same box
    from two eye positions, exactly the room's bounds, so the cached grids stay valid."""
    from lpv_core.scene import Camera

    room = _on_ground(closed_cornell("POINT", (0, 0, 0), SETTINGS), GROUNDS["2 km quad"])
    boxes = []
    for eye in ((0.6, -0.9, 1.4), (-0.5, -0.6, 1.6)):
        room.camera = Camera.look_at(eye, (0.0, 0.0, 1.0), resolution=(16, 16), near=0.02)
        lo, hi = engine.Engine().lpv_bounds(room)
        boxes.append(np.concatenate([lo, hi]))
    np.testing.assert_array_equal(boxes[0], boxes[1])
    np.testing.assert_array_equal(boxes[0], [-1, -1, 0, 1, 1, 2])
