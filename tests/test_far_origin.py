"""The same closed room at the origin and 1e7 m away renders the same (indirect relative RMSE
<= 1e-4): in the core, and from Blender through extraction."""

import numpy as np
import pytest

from lpv_core import engine
from lpv_core.render import deferred, error
from lpv_core.scene import Camera, GISettings, make_scene
from tools import core_scenes as demo

OFFSET = np.array([1e7, -1e7, 1e7])  # exact in float32 (1e7 = 5^7 x 2^7 < 2^24)
TOLERANCE = 1e-4


def _indirect(scene) -> np.ndarray:
    eng = engine.Engine()
    return error.indirect_term(deferred.render(eng, scene, eng.update(scene)))


def closed_cornell(light: str, offset, settings: GISettings) -> "demo.Scene":
    """core_scenes' Cornell box closed at its front (y = -1), camera inside, all of it
    (triangles, light, camera) moved by ``offset``."""
    off = np.asarray(offset, np.float64)
    box = demo.cornell_box(light, (40, 40), settings, offset=off)
    front = demo.quad((-1, -1, 0), (-1, -1, 2), (1, -1, 2), (1, -1, 0)) + off
    cam = Camera.look_at(np.array([0.6, -0.9, 1.4]) + off, np.array([-0.3, 0.8, 0.6]) + off,
                         fov_y=np.radians(70), resolution=(40, 40), near=0.02, far=20.0)
    return make_scene(np.concatenate([box.positions, front]),
                      material_index=np.concatenate([box.material_index, [0, 0]]),
                      materials=box.materials, lights=box.lights, camera=cam,
                      settings=settings)


@pytest.mark.parametrize("light", ["POINT", "SPOT"])
@pytest.mark.parametrize("cascades", [1, 2])
def test_core_renders_the_same_room_far_from_the_origin(light, cascades):
    settings = GISettings(grid_resolution=16, rsm_resolution=64, shadow_resolution=256,
                          cascades=cascades, cascades_auto=False, antialias=1)
    near = _indirect(closed_cornell(light, (0, 0, 0), settings))
    far = _indirect(closed_cornell(light, OFFSET, settings))
    assert near.mean() > 0
    rmse = error.relative_rmse(far, near)
    assert rmse <= TOLERANCE, rmse


# ------------------------------------------------------------------------- through Blender

def _blender_room(offset) -> "object":
    """A closed 4 x 5 x 3 m room with a block, a point light and a camera inside, built with
    bpy, every object placed at ``offset`` + a local position. Blender holds object matrices
    and vertices in float32: vertices are local (exact small numbers), and every object's
    translation is a whole number of metres plus the offset, exact in float32 up to 2^24 m
    (1e7 + 1 is; 1e7 + 0.5 is not, float32 spacing there is 1 m). Its world positions are
    then exact in float64 and the two rooms differ by the offset alone."""
    import bpy

    from lpv_addon.scene_io import demo as blender_demo
    from lpv_addon.scene_io import extract

    scene = blender_demo.new_scene("far_room", (40, 32), True)
    off = tuple(float(v) for v in offset)
    wall = blender_demo.diffuse_material("Wall", (0.75, 0.73, 0.70), "DIFFUSE")
    accent = blender_demo.diffuse_material("Accent", (0.20, 0.35, 0.60), "DIFFUSE")
    lo, hi = (-2.0, -2.5, 0.0), (2.0, 2.5, 3.0)
    blender_demo.add_mesh_object(scene, "Shell", blender_demo.box_geometry(
        lo, hi, ["-z", "+z", "-x", "-y", "+x"], inward=True), wall, location=off)
    blender_demo.add_mesh_object(scene, "Accent", blender_demo.box_geometry(
        lo, hi, ["+y"], inward=True), accent, location=off)
    blender_demo.add_mesh_object(scene, "Block", blender_demo.box_geometry(
        (-0.45, -0.35, 0.0), (0.55, 0.65, 1.25)), accent,
        location=(off[0] + 1, off[1] + 1, off[2]), rotation_z_deg=20.0)
    blender_demo.add_light(scene, "Point", "POINT", 300.0, (off[0], off[1], off[2] + 2))
    blender_demo.add_camera(scene, (off[0] + 1, off[1] - 2, off[2] + 2),
                            (off[0] - 1, off[1] + 2, off[2] + 1), lens_mm=18.0)
    overrides = {"grid_resolution": 16, "rsm_resolution": 64, "antialias": 1}
    return extract.extract_scene(bpy.context.evaluated_depsgraph_get(), scene,
                                 settings_overrides=overrides)


@pytest.mark.bpy
def test_blender_room_renders_the_same_far_from_the_origin():
    pytest.importorskip("bpy")
    near_scene = _blender_room((0.0, 0.0, 0.0))
    far_scene = _blender_room(OFFSET)
    # extraction kept the room's shape: the far corners are the near ones plus the offset, to
    # float64 rounding at 1e7 m (2e-9 m: the rotated block's corners are not whole numbers)
    np.testing.assert_allclose(far_scene.positions - OFFSET, near_scene.positions, rtol=0,
                               atol=4e-9)
    near, far = _indirect(near_scene), _indirect(far_scene)
    assert near.mean() > 0
    rmse = error.relative_rmse(far, near)
    assert rmse <= TOLERANCE, rmse


def test_core_renders_a_sunlit_box_the_same_far_from_the_origin():
    """The sun's orthographic views and cascades at 1e7 m: core_scenes' open Cornell box."""
    settings = GISettings(grid_resolution=16, rsm_resolution=64, shadow_resolution=256,
                          cascades=2, cascades_auto=False, antialias=1)
    near = _indirect(demo.cornell_box("SUN", (40, 40), settings))
    far = _indirect(demo.cornell_box("SUN", (40, 40), settings, offset=OFFSET))
    assert near.mean() > 0
    rmse = error.relative_rmse(far, near)
    assert rmse <= TOLERANCE, rmse
