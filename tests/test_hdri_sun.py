"""An image World's sun (lpv_core sky.split_sun, lpv_addon/scene_io/world.py): a compact, very
bright region of an equirect map split off as a SUN lamp. Analytic maps (a disc of known
radiance, direction and size on a sky; smooth and uniform maps without a sun) and a generated
HDR Environment Texture whose lamp's Diffuse Direct is checked against Cycles'."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
from conftest import CACHE

from lpv_core import sky

TEXEL = math.pi / 512  # one texel of the 1024 x 512 maps below (rad)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def disc_map(w: int, h: int, to_sun, diameter: float, radiance, background, ss: int = 8):
    """``background`` (H, W, 3) plus a disc of ``radiance`` around ``to_sun``, each texel
    holding the disc's share of its area (ss x ss samples), as an image's pixels would."""
    dirs, _ = sky.map_directions(h * ss, w * ss)
    cover = (dirs @ _unit(to_sun) > math.cos(diameter / 2)).reshape(h, ss, w, ss).mean((1, 3))
    return (background + cover[..., None] * np.asarray(radiance)).astype(np.float32)


def light(m: np.ndarray) -> np.ndarray:
    """A map's radiance integrated over the sphere, per channel (sum of L x solid angle)."""
    return (m.astype(np.float64) * sky.map_directions(*m.shape[:2])[1][..., None]).sum((0, 1))


def test_a_disc_on_a_uniform_sky_is_a_sun_of_its_direction_irradiance_and_size():
    d, size, lum = _unit((0.3, -0.5, 0.6)), math.radians(2.0), np.array([3e4, 2e4, 1e4])
    blue = np.broadcast_to(np.float32((0.3, 0.4, 0.6)), (512, 1024, 3))
    out, sun = sky.split_sun(disc_map(1024, 512, d, size, lum, blue))
    assert sun is not None
    e, to_sun, diameter = sun
    assert math.acos(min(1.0, float(to_sun @ d))) < TEXEL
    assert e == pytest.approx(lum * 2 * math.pi * (1 - math.cos(size / 2)), rel=0.01)
    assert diameter == pytest.approx(size, abs=TEXEL)
    assert out == pytest.approx(blue, rel=1e-6)  # no peak left: the sky's level throughout


def test_light_is_conserved_exactly_also_across_the_seam_and_at_the_pole():
    rng = np.random.default_rng(7)
    dirs, _ = sky.map_directions(256, 512)
    ground = (0.2 + 0.5 * np.maximum(dirs[..., 2:], 0) * np.array([0.6, 0.8, 1.0])
              + rng.uniform(0, 0.05, (256, 512, 3)))
    for d in ((-1.0, 0.01, 0.2), (0.05, 0.0, 1.0)):  # on the u = 0 / 1 seam; by the zenith
        m = disc_map(512, 256, d, math.radians(1.5), (4e4, 3e4, 2e4), ground, ss=4)
        out, sun = sky.split_sun(m)
        assert sun is not None and math.acos(min(1.0, float(sun[1] @ _unit(d)))) < 2 * TEXEL
        assert light(out) + sun[0] == pytest.approx(light(m), rel=1e-6)
        assert np.isfinite(out).all() and out.min() >= 0 and (sun[0] > 0).all()
        assert out.max() < 1.01 * ground.max()


@pytest.mark.parametrize("kind", ["uniform", "one texel", "gradient", "glow", "noise",
                                  "coarse", "clipped clouds"])
def test_a_map_without_a_compact_bright_region_gives_no_sun(kind):
    rng = np.random.default_rng(1)
    dirs, _ = sky.map_directions(256, 512)
    z = np.maximum(dirs[..., 2:], 0.0)
    glow = np.arccos(np.clip(dirs @ _unit((0.5, 0.2, 0.8)), -1, 1))[..., None]
    m = {"uniform": np.full((256, 512, 3), 0.7), "one texel": np.full((1, 1, 3), 5.0),
         "gradient": 0.1 + 2 * z ** 0.5 * (0.5, 0.7, 1.0),
         # an overcast sky's bright patch: 10 deg wide, 50x its surroundings
         "glow": 0.3 + 15 * np.exp(-(glow / math.radians(10)) ** 2) * (1.0, 0.9, 0.8),
         "noise": rng.uniform(0.05, 1.0, (256, 512, 3)),
         "coarse": rng.uniform(0.05, 1.0, (4, 8, 3)),  # a texel wider than any sun
         "clipped clouds": np.minimum(1.0, 0.3 + 2 * np.exp(-(glow / 0.3) ** 2))}[kind]
    m = np.ascontiguousarray(np.broadcast_to(m, np.broadcast_shapes(m.shape, (1, 1, 3))))
    out, sun = sky.split_sun(m)
    assert sun is None and np.array_equal(out, m.astype(np.float32))


# ------------------------------------------------------------- Blender and Cycles (bpy)


SUN_TO = _unit((0.4, -0.6, 0.55))  # before the Mapping node's rotation
SUN_E = np.array([20.0, 17.0, 13.0])  # W/m^2 normal to the sun, before Strength
STRENGTH, TURN = 1.5, math.radians(30.0)


def _images(bpy):
    """A 512 x 256 float image of a sky over a dark ground with a 1 deg sun, and the same
    without the sun (the sky Cycles sees around the lamp)."""
    dirs, _ = sky.map_directions(256, 512)
    ground = np.where(dirs[..., 2:] > 0, (0.4, 0.5, 0.7), (0.1, 0.1, 0.1))
    size = math.radians(1.0)
    lum = SUN_E / (2 * math.pi * (1 - math.cos(size / 2)))
    out = []
    for name, px in (("sunny", disc_map(512, 256, SUN_TO, size, lum, ground, ss=4)),
                     ("sky", ground.astype(np.float32))):
        img = bpy.data.images.new(name, 512, 256, alpha=True, float_buffer=True)
        img.pixels.foreach_set(np.concatenate([px, np.ones((256, 512, 1))], -1)
                               .astype(np.float32).ravel())
        out.append(img)
    return out


def _cycles_direct(bpy, world, env, images, normals) -> np.ndarray:
    """Diffuse Direct x pi (irradiance) on a 100 m plane per normal (rows) and image
    (columns), Cycles at 256 spp; cached under .cache/tests/hdri_sun."""
    from mathutils import Vector
    from test_world import _render

    px = np.empty(512 * 256 * 4, np.float32)
    key = hashlib.sha256(b"".join(im.pixels.foreach_get(px) or px.tobytes() for im in images)
                         + np.asarray(normals).tobytes()
                         + f"{STRENGTH}{TURN}{bpy.app.version}".encode()).hexdigest()[:16]
    path = CACHE / "hdri_sun" / f"{key}.json"
    if path.exists():
        return np.array(json.loads(path.read_text()))
    out = np.zeros((len(normals), len(images), 3))
    for i, normal in enumerate(normals):
        plane = bpy.data.meshes.new("plane")
        plane.from_pydata([(-50, -50, 0), (50, -50, 0), (50, 50, 0), (-50, 50, 0)], [],
                          [(0, 1, 2, 3)])
        sc = bpy.data.scenes.new("plane")
        ob = bpy.data.objects.new("plane", plane)
        cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        cam.data.type, cam.data.ortho_scale = "ORTHO", 1.0
        cam.location = Vector(normal)
        for o in (ob, cam):
            o.rotation_euler = Vector(normal).to_track_quat("Z", "Y").to_euler()
            sc.collection.objects.link(o)
        sc.camera, sc.world = cam, world
        for j, img in enumerate(images):
            env.image = img
            out[i, j] = _render(sc, 8, 256, passes=True)["Diffuse Direct"][..., :3] \
                .mean(axis=(0, 1)) * math.pi
        env.image = images[0]
        bpy.data.scenes.remove(sc)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out.tolist()))
    return out


@pytest.mark.bpy
def test_an_environment_texture_sun_is_one_sun_lamp_lighting_a_plane_as_cycles(registered_addon):
    """A generated HDR image behind a Mapping rotation, times Strength: one SUN lamp, along
    the rotated sun, whose Diffuse Direct on an open plane (facing it, and horizontal) is what
    Cycles renders with the sun less what it renders without it; with the map's own light the
    plane's total is Cycles' too."""
    bpy = pytest.importorskip("bpy")
    from test_world import new_world

    from lpv_addon.scene_io import world as W
    from lpv_addon.scene_io.extract import extract_scene

    bpy.ops.wm.read_homefile(use_empty=True)
    W._MEMORY.clear()
    images = _images(bpy)
    world, bg = new_world()
    tree = world.node_tree
    env, mp = tree.nodes.new("ShaderNodeTexEnvironment"), tree.nodes.new("ShaderNodeMapping")
    env.image = images[0]
    mp.inputs["Rotation"].default_value = (0.0, 0.0, TURN)
    tree.links.new(tree.nodes.new("ShaderNodeTexCoord").outputs["Generated"],
                   mp.inputs["Vector"])
    tree.links.new(mp.outputs["Vector"], env.inputs["Vector"])
    tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = STRENGTH
    s = extract_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene,
                      require_camera=False)
    suns = [lt for lt in s.lights if lt.type == "SUN"]
    assert len(suns) == 1 and suns[0].name == "W sun"
    assert any("SUN lamp 'W sun'" in line for line in s.approximated)
    to_sun, e = -suns[0].direction, suns[0].power * np.asarray(suns[0].color, np.float64)
    c, sn = math.cos(TURN), math.sin(TURN)
    # Cycles' svm_mapping looks the image up along R d: the sun shows along R^T SUN_TO
    turned = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]).T @ SUN_TO
    assert math.degrees(math.acos(min(1.0, float(to_sun @ turned)))) < 0.5
    normals = np.array([turned, (0.0, 0.0, 1.0)])
    seen = _cycles_direct(bpy, world, env, images, normals)
    dirs, sa = sky.map_directions(*s.world.radiance.shape[:2])
    for i, n in enumerate(normals):
        lamp = e * float(n @ to_sun)
        assert lamp == pytest.approx(seen[i, 0] - seen[i, 1], rel=0.03), (n, lamp, seen[i])
        rest = (s.world.radiance * (sa * np.maximum(dirs @ n, 0))[..., None]).sum((0, 1))
        assert lamp + rest == pytest.approx(seen[i, 0], rel=0.03), (n, lamp + rest, seen[i])
