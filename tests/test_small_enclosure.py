"""A light inside a closed space the grid does not resolve is named in the stats, with the grid
resolution that resolves it (planner.enclosure_note); a resolved one is not."""

import numpy as np
import pytest

from lpv_core import engine, planner
from lpv_core.engine import Stats
from lpv_core.render import deferred
from lpv_core.scene import Camera, GISettings, Light, Material, make_scene
from tools import core_scenes as demo


def crate_room(crate: float | None, grid: int):
    """A closed 6 x 6 x 3 m room with a 200 W point light 0.2 m above the floor, inside a
    closed ``crate`` (m) on the floor when given; camera outside the crate."""
    tris = [demo.box_triangles((-3.0, -3.0, 0.0), (3.0, 3.0, 3.0), inward=True)]
    h = 0.5 * crate if crate else 0.2
    if crate:
        c = crate / 2
        tris.append(demo.box_triangles((-c, -c, 0.0), (c, c, crate)))
    light = Light("Lamp", "POINT", demo.light_matrix((0.0, 0.0, h), (0, 0, -1)), power=200.0)
    cam = Camera.look_at((2.6, -2.6, 2.2), (0.0, 0.0, 0.3), fov_y=np.radians(70.0),
                         resolution=(32, 32), near=0.01, far=30.0)
    settings = GISettings(grid_resolution=grid, rsm_resolution=128, shadow_resolution=256,
                          antialias=1)
    return make_scene(np.concatenate(tris), materials=[Material("white")], lights=[light],
                      camera=cam, settings=settings)


def _update(scene):
    eng = engine.Engine()
    stats = Stats()
    res = eng.update(scene, stats)
    return eng, res, stats


def _notes(stats):
    return [s for s in stats.skipped if s["stage"] == "resolution"]


def test_a_light_in_a_crate_too_small_for_the_grid_is_named_with_the_grid_that_resolves_it():
    # 0.4 m crate at 16^3 in a 6 m room: cells 6/14 m, the crate 0.93 cells
    _, _, stats = _update(crate_room(0.4, 16))
    (note,) = _notes(stats)
    assert note["what"] == "light 'Lamp'"
    assert "0.4 m across" in note["reason"] and "grid_resolution 32 gives it 2 cells" in note["reason"]
    (info,) = stats.info["unresolved_enclosures"]
    assert info["resolving_grid_resolution"] == 32  # cells 6/30 m: the crate 2 cells
    assert info["cells"] == pytest.approx(0.4 / (6.0 / 14.0), rel=1e-4)


@pytest.mark.parametrize("crate, grid", [(0.4, 32), (None, 16)])
def test_resolved_enclosures_and_free_lights_get_no_entry(crate, grid):
    _, _, stats = _update(crate_room(crate, grid))
    assert _notes(stats) == [] and "unresolved_enclosures" not in stats.info


def test_the_named_grid_cuts_the_leak():
    """What the entry says: at 16^3 (0.93 cells) most of the crate's light leaks into the
    room (measured 80 %), at the resolution it names (32^3, 2 cells) a tenth (11 %)."""
    leak = {}
    for grid in (16, 32):
        free = crate_room(None, grid)
        eng, res, _ = _update(free)
        lit = deferred.render(eng, free, res)["Diffuse Indirect"].mean()
        boxed = crate_room(0.4, grid)
        eng, res, _ = _update(boxed)
        leak[grid] = deferred.render(eng, boxed, res)["Diffuse Indirect"].mean() / lit
    assert leak[16] > 0.7 and leak[32] < 0.2, leak


def test_only_lights_with_occluders_all_around_within_reach_are_looked_at():
    sc = crate_room(0.4, 16)
    reach = planner.enclosure_reach(6.0 / 14.0)
    assert planner.occluders_around(sc, sc.lights[0].position, reach)  # in the crate
    assert not planner.occluders_around(sc, np.array([1.5, 1.5, 1.5]), 1.0)  # nothing near
    assert not planner.occluders_around(sc, np.array([1.5, 1.5, 2.9]), 1.0)  # a ceiling lamp
