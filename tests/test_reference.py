"""Cycles references: scenes, pass layout, settings restore, caching and Cycles' light units.

The radiometric tests pin what the LPV calibration relies on, measured on a large white
diffuse plane (albedo 0.8) seen by an orthographic camera from above, one light, black world:
Diffuse Direct = irradiance / pi (independent of albedo; Diffuse Color holds the albedo);
point light of power P: intensity P / (4 pi) W/sr; spot: the same on its axis times
smoothstep((cos t - cos(size / 2)) / ((1 - cos(size / 2)) blend)), no extra cosine; sun of
strength S: irradiance S cos(t); area light of power P and area A: radiance P / (pi A)
(normalize on), P / pi (normalize off).
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from lpv_addon.render import cycles
from lpv_core.render import exr
from tools import scene_hash, scenes

pytestmark = pytest.mark.bpy

ROOT = Path(__file__).resolve().parents[1]
N = 16  # pixels across the radiometry images
WIDTH = 4.0  # metres the orthographic camera sees across
SS = 8  # supersamples per pixel axis for the predictions (box filter = pixel average)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------


def _settings_snapshot(scene) -> str:
    vl = scene.view_layers[0]
    return json.dumps(
        [scene_hash._rna(scene.render, 1), scene_hash._rna(scene.cycles, 0),
         scene_hash._rna(vl, 0), scene.render.filepath],
        sort_keys=True, default=repr,
    )


def _plane_scene(albedo: float = 0.8, y_min: float = -20.0):
    """A 40 m white diffuse plane at z = 0, ortho camera 5 m above looking down (+Y up)."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    mesh = bpy.data.meshes.new("Plane")
    mesh.from_pydata([(-20, y_min, 0), (20, y_min, 0), (20, 20, 0), (-20, 20, 0)], [],
                     [(0, 1, 2, 3)])
    mesh.materials.append(scenes.diffuse_material("White", (albedo,) * 3, "DIFFUSE"))
    ob = bpy.data.objects.new("Plane", mesh)
    scene.collection.objects.link(ob)
    cam = bpy.data.cameras.new("Cam")
    cam.type = "ORTHO"
    cam.ortho_scale = WIDTH
    cam.sensor_fit = "HORIZONTAL"
    cam_ob = bpy.data.objects.new("Cam", cam)
    cam_ob.location = (0, 0, 5)
    scene.collection.objects.link(cam_ob)
    scene.camera = cam_ob
    scene.render.engine = "CYCLES"
    return scene


def _add_light(scene, kind, energy, location=(0, 0, 1), rotation=(0, 0, 0), **settings):
    light = bpy.data.lights.new("L", kind)
    light.energy = energy
    if kind == "SUN":
        light.angle = 0.0
    else:
        light.shadow_soft_size = 0.0
    for k, v in settings.items():
        setattr(light, k, v)
    ob = bpy.data.objects.new("L", light)
    ob.location = location
    ob.rotation_euler = rotation
    scene.collection.objects.link(ob)
    return light


def _render(tmp_path, samples, name="r.exr", resolution=(N, N)):
    info = cycles.render_cycles_passes(tmp_path / name, samples=samples, resolution=resolution)
    return exr.read_multilayer(info["path"])


def _grid():
    """World (x, y) of the supersamples of the N x N image, row 0 = top (+Y)."""
    u = (np.arange(N * SS) + 0.5) / (N * SS) * WIDTH - WIDTH / 2
    return u[None, :], -u[:, None]


def _pixavg(f):
    return np.broadcast_to(f, (N * SS, N * SS)).reshape(N, SS, N, SS).mean(axis=(1, 3))


def _centre(a):
    return a[N // 2 - 1 : N // 2 + 1, N // 2 - 1 : N // 2 + 1].mean()


def _point_dd(power, h):
    """Predicted Diffuse Direct of a point light (intensity P / 4 pi) at height h: E / pi."""
    x, y = _grid()
    r = np.sqrt(x * x + y * y + h * h)
    return power / (4 * math.pi) * h / r**3 / math.pi, np.arccos(h / r)


# ---------------------------------------------------------------------------------------------
# Cornell box reference: passes, identity, restore
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    facts = scenes.cornell_box("AREA", resolution=(32, 32))
    scene = bpy.context.scene
    before = _settings_snapshot(scene)
    out = tmp_path_factory.mktemp("cornell") / "cornell.exr"
    info = cycles.render_cycles_passes(out, samples=16)
    after = _settings_snapshot(scene)
    return {"facts": facts, "info": info, "before": before, "after": after,
            "passes": exr.read_multilayer(out)}


def test_cornell_passes_present_and_finite(cornell):
    p = cornell["passes"]
    assert set(cycles.PASSES) <= set(p)
    assert p["Combined"].shape == (32, 32, 4)
    for name in ("Diffuse Direct", "Diffuse Indirect", "Diffuse Color"):
        assert p[name].shape == (32, 32, 3)
    for arr in p.values():
        assert np.isfinite(arr).all()
    assert p["Diffuse Direct"].max() > 0 and p["Diffuse Indirect"].max() > 0
    assert cornell["info"]["resolution"] == (32, 32)
    assert cornell["info"]["seconds"] > 0


def test_cornell_combined_is_diffuse_light_times_colour(cornell):
    # Cycles divides each light pass by the colour pass summed over the same samples, so
    # (DiffDir + DiffInd) x DiffCol reproduces the samples' mean diffuse light exactly - the
    # Monte Carlo noise cancels. With only diffuse materials, no visible emitter and a black
    # world nothing else enters Combined, so only float32 rounding remains: 1e-4 relative.
    p = cornell["passes"]
    pred = (p["Diffuse Direct"] + p["Diffuse Indirect"]) * p["Diffuse Color"]
    comb = p["Combined"][..., :3]
    lit = pred > 1e-3 * pred.max()
    assert lit.mean() > 0.5
    np.testing.assert_allclose(comb[lit], pred[lit], rtol=1e-4)
    assert np.abs(comb - pred).max() <= 1e-4 * comb.max()


def test_cornell_settings_restored(cornell):
    assert cornell["before"] == cornell["after"]


def test_channel_names_equal_our_writer(cornell, tmp_path):
    p = cornell["passes"]
    ours = tmp_path / "ours.exr"
    exr.write_multilayer(ours, {k: p[k] for k in cycles.PASSES})
    assert exr.channel_names(ours) == exr.channel_names(cornell["info"]["path"])
    assert "ViewLayer.Diffuse Indirect.R" in exr.channel_names(ours)


def test_settings_restored_on_error(tmp_path, monkeypatch):
    scenes.cornell_box("POINT", resolution=(8, 8))
    scene = bpy.context.scene
    scene.render.image_settings.file_format = "PNG"
    scene.cycles.samples = 7
    before = _settings_snapshot(scene)

    def boom(src, dst):
        raise OSError("simulated failure after the render")

    monkeypatch.setattr(cycles.os, "replace", boom)
    with pytest.raises(OSError, match="simulated"):
        cycles.render_cycles_passes(tmp_path / "x.exr", samples=1)
    monkeypatch.undo()
    assert _settings_snapshot(scene) == before
    assert list(tmp_path.iterdir()) == []  # no temporary render left behind


def test_render_other_scene_is_reproducible(tmp_path):
    # Same content renders bit-identically whether it is the context scene of a fresh file
    # or a second scene created with bpy.data.scenes.new (whose Cycles defaults differ).
    scenes.cornell_box("POINT", resolution=(12, 12))
    h = scene_hash.scene_hash()
    first = _render(tmp_path, 2, "first.exr", resolution=None)
    scenes.cornell_box("SPOT", resolution=(12, 12))
    facts = scenes.cornell_box("POINT", resolution=(12, 12), new_file=False)
    other = bpy.data.scenes[facts["scene"]]
    if bpy.context.window is not None:
        bpy.context.window.scene = bpy.data.scenes["cornell_spot"]
    assert bpy.context.scene != other
    assert scene_hash.scene_hash(other) == h
    info = cycles.render_cycles_passes(tmp_path / "second.exr", samples=2, scene=other)
    second = exr.read_multilayer(info["path"])
    for name in cycles.PASSES:
        np.testing.assert_array_equal(second[name], first[name])


def test_rows_top_first(tmp_path):
    _plane_scene(y_min=0.0)  # plane only where y > 0: the top half of the image
    _add_light(bpy.context.scene, "SUN", 3.0)
    dd = _render(tmp_path, 1, resolution=(8, 8))["Diffuse Direct"][..., 0]
    assert (dd[:4] > 0.5).all() and (dd[4:] == 0).all()


# ---------------------------------------------------------------------------------------------
# Scenes, hash and cache paths
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(set(scenes.SCENES) - set(scenes.LIGHT_SOURCE_SCENES)))
def test_scene_builders(name):
    facts = scenes.build(name, resolution=(40, 30))
    scene = bpy.context.scene
    assert facts["scene"] == scene.name
    assert scene.camera.name == facts["camera"]
    assert scene.camera.data.sensor_fit == "HORIZONTAL"
    assert (scene.render.resolution_x, scene.render.resolution_y) == (40, 30)
    assert facts["lights"] and facts["objects"]
    for light_name in facts["lights"]:
        light = bpy.data.objects[light_name].data
        assert light.use_shadow
        if light.type == "SUN":
            assert light.angle == 0.0
        else:
            assert light.shadow_soft_size == 0.0
    for mat in bpy.data.materials:
        kinds = {n.bl_idname for n in mat.node_tree.nodes}
        assert kinds <= {"ShaderNodeOutputMaterial", "ShaderNodeBsdfDiffuse"}
    world = scene.world.node_tree.nodes["Background"]
    assert world.inputs["Strength"].default_value == 0.0


def _emitting(mat) -> bool:
    for n in mat.node_tree.nodes:
        if n.bl_idname == "ShaderNodeEmission" and n.inputs["Strength"].default_value > 0:
            return True
        if (n.bl_idname == "ShaderNodeBsdfPrincipled"
                and n.inputs["Emission Strength"].default_value > 0):
            return True
    return False


@pytest.mark.parametrize("name", scenes.LIGHT_SOURCE_SCENES)
def test_light_source_scene_builders(name):
    """Each acceptance scene is lit by what it is named for and by nothing else."""
    facts = scenes.build(name, resolution=(40, 30))
    scene = bpy.context.scene
    assert (scene.render.resolution_x, scene.render.resolution_y) == (40, 30)
    assert facts["objects"] and scene.camera is not None
    world = scene.world.node_tree.nodes
    strength = world["Background"].inputs["Strength"].default_value
    emitting = [m.name for m in bpy.data.materials if m.users and _emitting(m)]
    lamps = {bpy.data.objects[n].data.type: bpy.data.objects[n].data for n in facts["lights"]}
    if name.startswith(("sky_", "window_room")):
        assert strength > 0 and not lamps and not emitting
        uniform = name.startswith("sky_room")
        assert ("ShaderNodeTexSky" in {n.bl_idname for n in world}) == (not uniform)
        if name.startswith("sky_room_thin"):  # the quick way: single quads, normals in
            roof, walls = bpy.data.objects["Roof"].data, bpy.data.objects["Walls"].data
            assert len(walls.polygons) == 4 and len(roof.polygons) == 4
            assert all(p.normal.z < -0.99 for p in roof.polygons)
            floor = bpy.data.objects["FloorSlab"]
            assert floor.dimensions.x == pytest.approx(30.0 if "ground" in name else 5.0)
    elif name == "panel_room":
        assert strength == 0 and not lamps and len(emitting) >= 2
    else:
        assert strength == 0 and not emitting and set(lamps) == {"AREA", "POINT"}
        assert lamps["AREA"].size == pytest.approx(1.0)
        assert lamps["POINT"].shadow_soft_size == pytest.approx(0.25)


def test_cornell_normals_face_the_room():
    scenes.cornell_box("SUN")
    objs = bpy.data.objects
    assert objs["Floor"].data.polygons[0].normal.z > 0.99
    assert all(p.normal.z < -0.99 for p in objs["Ceiling"].data.polygons)
    assert objs["LeftWall"].data.polygons[0].normal.x > 0.99
    assert objs["RightWall"].data.polygons[0].normal.x < -0.99
    assert objs["BackWall"].data.polygons[0].normal.y < -0.99
    block = objs["TallBlock"].data
    centre = sum((v.co for v in block.vertices), block.vertices[0].co * 0) / len(block.vertices)
    assert all((p.center - centre).dot(p.normal) > 0 for p in block.polygons)  # outward


def test_principled_variant_and_save_scene(tmp_path):
    facts = scenes.save_scene("cornell_point", tmp_path / "c.blend", shader="PRINCIPLED")
    assert Path(facts["path"]).is_file()
    assert bpy.data.filepath == ""  # saved as a copy: the session's file is unchanged
    bsdf = bpy.data.materials["Red"].node_tree.nodes["Principled BSDF"]
    assert bsdf.inputs["Specular IOR Level"].default_value == 0.0
    assert bsdf.inputs["Roughness"].default_value == 1.0


def test_scene_hash_follows_content():
    scenes.cornell_box("SPOT", resolution=(32, 32))
    h = scene_hash.scene_hash()
    assert h == scene_hash.scene_hash()
    scenes.cornell_box("SPOT", resolution=(32, 32))
    assert scene_hash.scene_hash() == h  # rebuilt: same content, same hash
    bpy.data.objects["TallBlock"].name = "Renamed"
    assert scene_hash.scene_hash() == h  # names are not content
    changes = [
        lambda: setattr(bpy.data.lights["Spot"], "energy", 301.0),
        lambda: setattr(bpy.data.objects["ShortBlock"], "location", (0.3, -0.3, 0.0)),
        lambda: bpy.data.materials["Red"].node_tree.nodes["Diffuse BSDF"]
        .inputs["Color"].__setattr__("default_value", (0.5, 0.1, 0.1, 1.0)),
        lambda: setattr(bpy.data.cameras["Camera"], "lens", 35.0),
        lambda: setattr(bpy.context.scene.render, "resolution_x", 33),
        lambda: bpy.data.objects["Floor"].data.vertices[0].co.__setattr__("z", 0.01),
    ]
    for change in changes:
        scenes.cornell_box("SPOT", resolution=(32, 32))
        change()
        assert scene_hash.scene_hash() != h


def test_reference_path():
    h = "ab" * 32
    p = scene_hash.reference_path("/cache", h, 64, 1)
    assert p == Path("/cache") / f"ref_{h[:20]}_s64_b1.exr"
    with pytest.raises(ValueError):
        scene_hash.reference_path("/cache", "scene.blend", 64, 1)


def _tool():
    spec = importlib.util.spec_from_file_location("make_references",
                                                  ROOT / "tools" / "make_references.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_cli_plain_mode(tmp_path):
    tool = _tool()
    assert tool.main(["--out", str(tmp_path), "--scenes", "cornell_sun", "--samples", "1",
                      "--resolution", "16x12"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cornell_sun.blend",
                                                          "cornell_sun_ref_b1.exr"]
    p = exr.read_multilayer(tmp_path / "cornell_sun_ref_b1.exr")
    assert p["Combined"].shape == (12, 16, 4)


@pytest.mark.slow
def test_ensure_reference_caches(tmp_path, monkeypatch):
    tool = _tool()
    blend, ref = tool.ensure_reference("cornell_point", tmp_path, samples=2, bounces=1,
                                       resolution=(16, 16))
    assert blend.is_file() and ref.is_file()
    assert exr.read_multilayer(ref)["Diffuse Direct"].shape == (16, 16, 3)
    stamp = ref.stat().st_mtime_ns

    # Warm cache: answered from the manifest, no child process.
    def no_child(*a, **k):
        raise AssertionError("cache hit must not start a subprocess")

    monkeypatch.setattr(tool.subprocess, "run", no_child)
    assert tool.ensure_reference("cornell_point", tmp_path, 2, 1, (16, 16)) == (blend, ref)
    monkeypatch.undo()

    # Without the manifest the child rebuilds and hashes the scene, finds the content-keyed
    # reference and does not render again.
    (tmp_path / tool.MANIFEST).unlink()
    assert tool.ensure_reference("cornell_point", tmp_path, 2, 1, (16, 16)) == (blend, ref)
    assert ref.stat().st_mtime_ns == stamp


# ---------------------------------------------------------------------------------------------
# Cycles' units, hand-derived (see the module docstring)
# ---------------------------------------------------------------------------------------------


def test_point_light_units(tmp_path):
    power, h = 100.0, 1.0
    scene = _plane_scene()
    _add_light(scene, "POINT", power, (0, 0, h))
    p = _render(tmp_path, 4)
    pred = _pixavg(_point_dd(power, h)[0])
    dd = p["Diffuse Direct"][..., 0]
    # Delta light: no light-sampling noise, only the sub-pixel jitter of 4 samples.
    assert _centre(dd) / _centre(pred) == pytest.approx(1.0, abs=5e-3)
    assert np.mean(dd / pred) == pytest.approx(1.0, abs=2e-3)
    np.testing.assert_allclose(p["Diffuse Color"], 0.8, rtol=1e-5)
    np.testing.assert_allclose(p["Combined"][..., 0], 0.8 * dd, rtol=1e-4)
    assert p["Diffuse Indirect"].max() == 0.0  # a single plane: nothing to bounce off


@pytest.mark.parametrize("tilt_deg", [0.0, 60.0])
def test_sun_units(tmp_path, tilt_deg):
    strength = 3.0
    scene = _plane_scene()
    _add_light(scene, "SUN", strength, (0, 0, 3), (math.radians(tilt_deg), 0, 0))
    dd = _render(tmp_path, 1)["Diffuse Direct"][..., 0]
    np.testing.assert_allclose(dd, strength * math.cos(math.radians(tilt_deg)) / math.pi,
                               rtol=1e-4)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


@pytest.mark.parametrize("size_deg, blend", [(90.0, 0.0), (90.0, 0.5), (120.0, 1.0)])
def test_spot_light_units_and_cone(tmp_path, size_deg, blend):
    power, h = 100.0, 1.0
    scene = _plane_scene()
    _add_light(scene, "SPOT", power, (0, 0, h), spot_size=math.radians(size_deg),
               spot_blend=blend)
    dd = _render(tmp_path, 32)["Diffuse Direct"][..., 0]
    point, theta = _point_dd(power, h)
    cos_half = math.cos(math.radians(size_deg) / 2)
    if blend > 0:
        cone = _smoothstep((np.cos(theta) - cos_half) / ((1 - cos_half) * blend))
    else:
        cone = (np.cos(theta) > cos_half).astype(float)
    pred = _pixavg(point * cone)
    # On the axis a spot is exactly a point light of the same power ("as if a point").
    assert _centre(dd) / _centre(pred) == pytest.approx(1.0, abs=5e-3)
    # The cone law holds everywhere; the residual is the sampling jitter of 32 samples in
    # pixels a steep cone edge crosses (a hard edge: coverage of such a pixel is a binomial
    # estimate, so those pixels are checked in sum). The law with an extra cos(t) factor
    # (Cycles before 4.0) would be off by more than 5 % of the peak.
    cover = _pixavg(cone)
    edge = (cover > 0) & (cover < 1) if blend == 0 else np.zeros_like(cover, bool)
    assert np.abs(dd - pred)[~edge].max() < 0.02 * pred.max()
    if edge.any():
        assert dd[edge].sum() / pred[edge].sum() == pytest.approx(1.0, abs=0.03)
    old_law = _pixavg(point * cone * np.cos(theta))
    assert np.abs(dd - old_law).max() > 0.05 * pred.max()


@pytest.mark.parametrize("normalize", [True, False])
def test_area_light_units(tmp_path, normalize):
    power, h, a = 100.0, 1.0, 0.5
    scene = _plane_scene()
    light = _add_light(scene, "AREA", power, (0, 0, h), shape="SQUARE", size=a)
    light.normalize = normalize
    dd = _render(tmp_path, 64)["Diffuse Direct"][..., 0]
    # Irradiance from a unit-radiance square facing down (cos cos / r^2 over the emitter, by
    # numerical integration), averaged over each pixel like the box filter does.
    k = 32
    s = (np.arange(k) + 0.5) / k * a - a / 2
    ex, ey = (g.ravel() for g in np.meshgrid(s, s))
    x, y = _grid()
    e_sub = np.empty((N * SS, N * SS))
    for j in range(N * SS):
        r2 = (x[0, :, None] - ex) ** 2 + (y[j, 0] - ey) ** 2 + h * h
        e_sub[j] = (h * h / r2**2).sum(-1) * (a / k) ** 2
    radiance = dd * math.pi / _pixavg(e_sub)
    expected = power / (math.pi * a * a) if normalize else power / math.pi
    # Area lights are sampled: 64 samples over 256 pixels average to well under 1 % noise
    # (measured with 1024 samples on 32 x 32 pixels: 1.00005).
    assert radiance.mean() / expected == pytest.approx(1.0, abs=0.01)
    assert _centre(radiance) / expected == pytest.approx(1.0, abs=0.03)
