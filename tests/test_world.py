"""World extraction (lpv_addon/scene_io/world.py) in real headless Blender, checked against
Cycles' own renders: uniform colours, Environment Texture orientation and colour space, the
Sky Texture bake (every sky type, cached, the user's data untouched), the sun disc as a lamp,
the Scene panel's World GI controls and the approximations' way to the warnings."""

from __future__ import annotations

import math
import os
import tempfile

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from mathutils import Vector

from lpv_addon import ui
from lpv_addon.scene_io import world as W
from lpv_addon.scene_io.extract import extract_scene
from lpv_core.render import exr

pytestmark = pytest.mark.bpy


@pytest.fixture(scope="module", autouse=True)
def addon(registered_addon):
    """Every test here runs with the add-on registered (conftest.registered_addon)."""


@pytest.fixture(autouse=True)
def fresh(tmp_path, monkeypatch):
    bpy.ops.wm.read_homefile(use_empty=True)
    monkeypatch.setenv("LPV_GI_CACHE_DIR", str(tmp_path / "cache"))
    W._MEMORY.clear()
    renders = []

    def count(*_):
        renders.append(1)

    bpy.app.handlers.render_pre.append(count)
    yield renders
    bpy.app.handlers.render_pre.remove(count)


def new_world(name="W"):
    world = bpy.data.worlds.new(name)
    if world.node_tree is None:  # Blender < 5
        world.use_nodes = True
    bpy.context.scene.world = world
    bg = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
    return world, bg


def extract():
    return extract_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene,
                         require_camera=False)


def cycles_view(direction, size=4, spp=4, ortho_target=None) -> np.ndarray:
    """Mean Combined of a Cycles render (own temporary scene sharing the context scene's
    World) through a 0.5 deg camera looking along ``direction``."""
    world = bpy.context.scene.world
    sc = bpy.data.scenes.new("probe")
    cam = bpy.data.objects.new("probe", bpy.data.cameras.new("probe"))
    try:
        sc.world = world
        sc.collection.objects.link(cam)
        sc.camera = cam
        cam.data.angle = math.radians(0.5)
        cam.rotation_euler = Vector(direction).to_track_quat("-Z", "Y").to_euler()
        return _render(sc, size, spp)["Combined"][..., :3].mean(axis=(0, 1))
    finally:
        data = cam.data
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(data)
        bpy.data.scenes.remove(sc)


def _render(sc, size, spp, passes=False) -> dict:
    r = sc.render
    r.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = spp
    sc.cycles.use_denoising = False
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.max_bounces = 0
    r.resolution_x = r.resolution_y = size
    r.resolution_percentage = 100
    r.image_settings.media_type = "MULTI_LAYER_IMAGE"
    r.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    r.image_settings.color_depth = "32"
    if passes:
        sc.view_layers[0].use_pass_diffuse_direct = True
    fd, path = tempfile.mkstemp(suffix=".exr")
    os.close(fd)
    try:
        r.filepath = path
        r.use_file_extension = False
        bpy.ops.render.render(write_still=True, scene=sc.name)
        return exr.read_multilayer(path)
    finally:
        os.unlink(path)


def texel_direction(c, r, w, h):
    u, v = (c + 0.5) / w, (r + 0.5) / h
    phi, el = (0.5 - u) * 2 * math.pi, (v - 0.5) * math.pi
    return (math.cos(el) * math.cos(phi), math.cos(el) * math.sin(phi), math.sin(el))


# ---------------------------------------------------------------------------------- colours


def test_uniform_background_is_colour_times_strength_as_cycles_renders_it(fresh):
    world, bg = new_world()
    bg.inputs["Color"].default_value = (0.2, 0.5, 0.9, 1.0)
    bg.inputs["Strength"].default_value = 1.5
    s = extract()
    assert s.world.radiance.shape == (1, 1, 3)
    seen = cycles_view((0.3, 0.8, 0.2))
    assert s.world.radiance[0, 0] == pytest.approx(seen, rel=1e-3)
    assert s.world.radiance[0, 0] == pytest.approx((0.3, 0.75, 1.35), rel=1e-5)
    # An RGB node feeding the colour is the same constant.
    rgb = world.node_tree.nodes.new("ShaderNodeRGB")
    rgb.outputs[0].default_value = (1.0, 0.5, 0.25, 1.0)
    world.node_tree.links.new(rgb.outputs[0], bg.inputs["Color"])
    assert extract().world.radiance[0, 0] == pytest.approx((1.5, 0.75, 0.375), rel=1e-5)
    assert fresh == [1]  # only the check's own render: no bake for a constant


def test_world_without_a_surface_shader_is_black_as_in_cycles(fresh):
    world, _ = new_world()
    world.color = (0.3, 0.3, 0.3)
    world.node_tree.nodes.clear()  # Blender 5 worlds always have a tree; this one is empty
    assert extract().world is None
    assert cycles_view((1, 0, 0)) == pytest.approx((0, 0, 0), abs=1e-6)


def test_black_world_and_switched_off_world_cost_nothing(fresh):
    _, bg = new_world()
    bg.inputs["Strength"].default_value = 0.0
    assert extract().world is None
    bg.inputs["Strength"].default_value = 1.0
    bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    assert extract().world is None
    bpy.context.scene.world = None
    assert extract().world is None
    assert fresh == []


# -------------------------------------------------------------------- environment texture


def _env_world(pixels: np.ndarray, float_buffer: bool, mapping_z_deg: float | None = None):
    h, w = pixels.shape[:2]
    img = bpy.data.images.new("env", w, h, alpha=True, float_buffer=float_buffer)
    if not float_buffer:
        img.colorspace_settings.name = "sRGB"
    rgba = np.concatenate([pixels, np.ones((h, w, 1))], -1).astype(np.float32)
    img.pixels.foreach_set(rgba.ravel())
    world, bg = new_world()
    tree = world.node_tree
    env = tree.nodes.new("ShaderNodeTexEnvironment")
    env.image = img
    env.interpolation = "Closest"
    tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 2.0
    if mapping_z_deg is not None:
        mp = tree.nodes.new("ShaderNodeMapping")
        mp.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(mapping_z_deg))
        tc = tree.nodes.new("ShaderNodeTexCoord")
        tree.links.new(tc.outputs["Generated"], mp.inputs["Vector"])
        tree.links.new(mp.outputs["Vector"], env.inputs["Vector"])
    return world


def _texels(w=8, h=4):
    rng = np.random.default_rng(3)
    return rng.uniform(0.05, 1.0, (h, w, 3))


@pytest.mark.parametrize("float_buffer", [True, False])
def test_environment_map_orientation_and_colour_space_match_cycles(fresh, float_buffer):
    """Texels of an 8x4 image (rows bottom-first, as Blender stores them) land where Cycles
    looks them up; a byte sRGB image is linearised, a float one read as is."""
    px = _texels()
    _env_world(px, float_buffer)
    s = extract()
    assert s.world.radiance.shape == (4, 8, 3)
    for c, r in ((1, 1), (5, 2), (6, 3), (3, 0)):
        seen = cycles_view(texel_direction(c, r, 8, 4))
        assert s.world.radiance[r, c] == pytest.approx(seen, rel=0.02, abs=2e-3), (c, r)
    if float_buffer:
        assert s.world.radiance == pytest.approx(2.0 * px, rel=1e-5)


def test_environment_mapping_rotation_about_z_matches_cycles(fresh):
    _env_world(_texels(16, 8), True, mapping_z_deg=90.0)
    s = extract()
    h, w = s.world.radiance.shape[:2]
    for c, r in ((2, 3), (9, 5), (13, 4)):
        d = texel_direction(c, r, w, h)
        seen = cycles_view(d)
        # Our map is bilinear between the source's texels: compare where the rotation maps
        # texel centres onto texel centres (90 deg = a quarter of the columns).
        assert s.world.radiance[r, c] == pytest.approx(seen, rel=0.03, abs=3e-3), (c, r)


def test_mirror_ball_projection_matches_cycles(fresh):
    """A smooth 16x16 mirror-ball image, bilinear in both: the map's texels along their
    directions are what Cycles shows there."""
    u = (np.arange(16) + 0.5) / 16
    px = np.stack([np.add.outer(u, 0 * u), np.add.outer(0 * u, u), np.full((16, 16), 0.5)], -1)
    world = _env_world(px, True)
    env = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeTexEnvironment")
    env.projection, env.interpolation = "MIRROR_BALL", "Linear"
    s = extract()
    h, w = s.world.radiance.shape[:2]
    for c, r in ((3, 2), (8, 5), (12, 4), (1, 6)):
        seen = cycles_view(texel_direction(c, r, w, h))
        assert s.world.radiance[r, c] == pytest.approx(seen, rel=0.03, abs=3e-3), (c, r)


def test_missing_image_is_magenta_and_reported(fresh):
    world, bg = new_world()
    env = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    world.node_tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    s = extract()
    assert s.world.radiance[0, 0] == pytest.approx((1.0, 0.0, 1.0))
    assert cycles_view((0, 1, 0)) == pytest.approx((1.0, 0.0, 1.0), abs=1e-3)
    assert any("has no image" in line for line in s.approximated)
    lines = ui.warning_lines({"info": {"approximated": s.approximated}})
    assert any("approximated: World 'W'" in line for line in lines)


# ---------------------------------------------------------------------------- sky texture


def _sky_world(sky_type=None, disc=False, elevation=35.0, rotation=60.0):
    world, bg = new_world("Sky")
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    if sky_type:
        sky.sky_type = sky_type
    if hasattr(sky, "sun_disc"):
        sky.sun_disc = disc
    sky.sun_elevation = math.radians(elevation)
    sky.sun_rotation = math.radians(rotation)
    world.node_tree.links.new(sky.outputs["Color"], bg.inputs["Color"])
    return world, sky


def _snapshot():
    sc = bpy.context.scene
    world = sc.world
    nodes = [(n.name, n.bl_idname, tuple(
        (s.identifier, tuple(s.default_value) if hasattr(s.default_value, "__len__")
         else s.default_value) for s in n.inputs if hasattr(s, "default_value")))
        for n in world.node_tree.nodes]
    sky = [(n.sky_type, n.sun_disc, n.sun_size, n.sun_elevation, n.sun_rotation)
           for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeTexSky"]
    return (sorted(s.name for s in bpy.data.scenes), sorted(w.name for w in bpy.data.worlds),
            sorted(c.name for c in bpy.data.cameras), sorted(o.name for o in bpy.data.objects),
            sc.world.name, sc.camera, sc.render.engine, sc.render.resolution_x,
            sc.render.filepath, sc.frame_current, world.users, nodes, sky,
            len(world.node_tree.links))


def test_every_sky_type_is_baked_once_and_the_user_data_is_untouched(fresh):
    types = [i.identifier for i in bpy.types.ShaderNodeTexSky.bl_rna.properties["sky_type"]
             .enum_items]
    _, sky = _sky_world()
    for kind in types:
        sky.sky_type = kind
        before = _snapshot()
        n0 = len(fresh)
        s = extract()
        assert len(fresh) > n0, kind  # baked by Cycles
        assert _snapshot() == before, kind
        m = s.world.radiance
        assert m.shape == (W.BAKE_SIZE[1], W.BAKE_SIZE[0], 3) and np.isfinite(m).all()
        # The sky is bright above the horizon and the map's zenith row agrees with Cycles.
        assert m[-8:].mean() > 0, kind
        up = cycles_view((0.0, 0.3, 1.0))
        d = np.array([0.0, 0.3, 1.0]) / math.hypot(0.3, 1.0)
        col = int((0.5 - math.atan2(d[1], d[0]) / (2 * math.pi)) * W.BAKE_SIZE[0])
        row = int((0.5 + math.asin(d[2]) / math.pi) * W.BAKE_SIZE[1])
        assert m[row, col] == pytest.approx(up, rel=0.1), kind
        # Cached: the same world again renders nothing, from memory or from disk.
        n1 = len(fresh)
        extract()
        W._MEMORY.clear()
        again = extract()
        assert len(fresh) == n1, kind
        assert np.array_equal(again.world.radiance, m)
    sky.sun_elevation += 0.1  # a change bakes again
    n2 = len(fresh)
    extract()
    assert len(fresh) > n2


def test_sun_disc_is_a_sun_lamp_with_cycles_irradiance(fresh):
    """The disc's irradiance: a white plane facing the returned sun direction and a
    horizontal one, rendered by Cycles with and without the disc; their Diffuse Direct
    difference x pi is the lamp's normal irradiance x cos."""
    world, sky = _sky_world(disc=True, elevation=40.0, rotation=60.0)
    s = extract()
    suns = [lt for lt in s.lights if lt.type == "SUN"]
    assert len(suns) == 1 and suns[0].angle == pytest.approx(sky.sun_size)
    sun = suns[0]
    to_sun = -sun.direction
    e = sun.power * np.asarray(sun.color, np.float64)
    assert to_sun[2] == pytest.approx(math.sin(math.radians(40.0)), abs=1e-6)
    for normal in (to_sun, np.array([0.0, 0.0, 1.0])):
        plane = bpy.data.meshes.new("plane")
        plane.from_pydata([(-50, -50, 0), (50, -50, 0), (50, 50, 0), (-50, 50, 0)], [],
                          [(0, 1, 2, 3)])
        sc = bpy.data.scenes.new("plane")
        ob = bpy.data.objects.new("plane", plane)
        ob.rotation_euler = Vector(normal).to_track_quat("Z", "Y").to_euler()
        cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        cam.data.type = "ORTHO"
        cam.data.ortho_scale = 1.0
        cam.location = Vector(normal) * 1.0
        cam.rotation_euler = Vector(normal).to_track_quat("Z", "Y").to_euler()
        for o in (ob, cam):
            sc.collection.objects.link(o)
        sc.camera, sc.world = cam, world
        direct = []
        for disc in (True, False):
            sky.sun_disc = disc
            direct.append(_render(sc, 8, 256, passes=True)["Diffuse Direct"][..., :3]
                          .mean(axis=(0, 1)).astype(np.float64))
        sky.sun_disc = True
        measured = (direct[0] - direct[1]) * math.pi
        cos = float(np.dot(normal, to_sun))
        assert measured == pytest.approx(e * cos, rel=0.03), (normal, measured, e * cos)
        bpy.data.scenes.remove(sc)
    # The map itself has no disc: its brightest texel is far below the disc's radiance.
    disc_radiance = e.max() / (math.pi * (sky.sun_size / 2) ** 2)
    assert s.world.radiance.max() < 1e-2 * disc_radiance


def test_bake_inside_a_render_engine_render(fresh):
    """Headless, a render engine's own render may render the world (Blender runs it on the
    same thread); the result is the same map."""
    _sky_world()
    out = {}

    class Probe(bpy.types.RenderEngine):
        bl_idname = "LPV_TEST_PROBE"
        bl_label = "probe"

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)

        def render(self, depsgraph):
            scene = depsgraph.scene_eval
            out["map"] = W.world_from_blender(scene.world, scene)[0].radiance

    bpy.utils.register_class(Probe)
    try:
        sc = bpy.context.scene
        sc.render.engine = "LPV_TEST_PROBE"
        sc.render.resolution_x = sc.render.resolution_y = 4
        cam = bpy.data.objects.new("c", bpy.data.cameras.new("c"))
        sc.collection.objects.link(cam)
        sc.camera = cam
        bpy.ops.render.render(scene=sc.name)
    finally:
        bpy.utils.unregister_class(Probe)
    assert out["map"].shape == (W.BAKE_SIZE[1], W.BAKE_SIZE[0], 3)  # baked, not a fallback
    W._MEMORY.clear()
    assert np.array_equal(out["map"], extract().world.radiance)


# ------------------------------------------------------------------------- artist controls


def test_scene_panel_switch_and_intensity_reach_the_world(fresh):
    _, bg = new_world()
    bg.inputs["Color"].default_value = (0.5, 0.5, 0.5, 1.0)
    props = bpy.context.scene.lpv
    assert props.world_gi and props.world_gi_intensity == 1.0
    s = extract()
    assert s.world.enabled and s.world.gi_intensity == 1.0
    props.world_gi_intensity = 0.3
    assert extract().world.gi_intensity == pytest.approx(0.3)
    props.world_gi_intensity = 0.0
    props.keyframe_insert("world_gi_intensity", frame=1)
    props.world_gi_intensity = 2.0
    props.keyframe_insert("world_gi_intensity", frame=11)
    bpy.context.scene.frame_set(6)
    assert extract().world.gi_intensity == pytest.approx(1.0, abs=1e-3)
    props.world_gi = False
    off = extract()
    assert off.world is not None and off.world.enabled is False
    assert not off.world.radiance.any()  # nothing read
