"""Image textures: sampled as Cycles' Image Texture node samples (hand-derived values and a
tiny Cycles render), fitted to the texture budget, per pixel in the G-buffer, per texel in the
RSM, carried by the worker's scene files once per digest; untextured scenes take none of it."""

import dataclasses
import os

import numpy as np
import pytest

from lpv_core import engine
from lpv_core.render import deferred
from lpv_core.scene import GISettings, Light, Material, make_scene
from lpv_core.scene import textures as tx
from lpv_core.scene.model import Camera
from lpv_core.scene.textures import Texture
from tools import core_scenes as demo

# value v of texel (row j from the bottom, column i) = 10 j + i + 1; channels v, 2v, 3v
RAMP = np.array([[1.0, 2.0, 3.0], [11.0, 12.0, 13.0]], np.float32)[..., None] * np.float32(
    [1.0, 2.0, 3.0])


def at(interpolation, extension, u, v):
    got = tx.sample(Texture("ramp", RAMP, interpolation, extension), [(u, v)])[0]
    assert got.dtype == np.float32
    return float(got[0]), got


# (u, v) -> value per extension (REPEAT, EXTEND, CLIP, MIRROR), derived by hand from Cycles'
# kernel rules: x = u W, Closest texel floor(x), Linear/Cubic taps around floor(x - 0.5)
CASES = {
    "Closest": [((0.1, 0.2), (1, 1, 1, 1)), ((0.7, 0.8), (13, 13, 13, 13)),
                ((1.1, 0.2), (1, 3, 0, 3)), ((-0.1, 0.6), (13, 11, 0, 11)),
                ((-0.7, 0.2), (1, 1, 0, 3))],
    "Linear": [((0.5, 0.25), (2, 2, 2, 2)), ((2 / 3, 0.5), (7.5, 7.5, 7.5, 7.5)),
               ((0.0, 0.25), (2, 1, 0.5, 1)), ((1.0, 1.0), (7, 13, 3.25, 13)),
               ((1.25, 0.25), (1.25, 3, 0, 2.75))],
    # texel (1, 0)'s centre: B-spline weights (1/6, 2/3, 1/6) over columns 0..2 give 2 and
    # 12 per row; rows -1, 0, 1 then wrap to row 1 / clamp / read 0 / mirror to row 0
    "Cubic": [((0.5, 0.25), (32 / 6, 22 / 6, 20 / 6, 22 / 6))],
}


@pytest.mark.parametrize("interpolation", ["Closest", "Linear", "Cubic", "Smart"])
def test_sampling_hand_derived(interpolation):
    for (u, v), expected in CASES["Cubic" if interpolation == "Smart" else interpolation]:
        for extension, value in zip(tx.EXTENSIONS, expected):
            got, rgb = at(interpolation, extension, u, v)
            assert got == pytest.approx(value, abs=1e-5), (interpolation, extension, u, v)
            np.testing.assert_allclose(rgb, np.float32([1, 2, 3]) * value, atol=1e-4)


def test_sampling_bad_input_is_named_and_finite():
    with pytest.raises(ValueError, match="'ramp'.*interpolation"):
        tx.sample(Texture("ramp", RAMP, "Bilinear"), [(0.5, 0.5)])
    with pytest.raises(ValueError, match="'ramp'.*extension"):
        tx.sample(Texture("ramp", RAMP, "Linear", "WRAP"), [(0.5, 0.5)])
    got = tx.sample(Texture("ramp", RAMP), [(np.nan, np.inf), (1e30, -1e30)])
    assert np.isfinite(got).all()


def test_bad_pixels_and_corner_colours_reach_no_stage():
    """NaN, Inf and negative texels and corner colours: 0 texels, corner colour 1 / 0."""
    bad = np.float32([[[np.nan, np.inf, -1.0], [0.5, 0.5, 0.5]]])
    mats = [Material("m", np.ones(3, np.float32), texture=Texture("bad", bad, "Closest"))]
    cc = np.ones((1, 3, 3), np.float32)
    cc[0, :, 0], cc[0, :, 1] = np.nan, -2.0
    lay = tx.layout(mats, np.zeros(1, np.int32), np.full((1, 3, 2), 0.25, np.float32), cc)
    got = tx.Surface(lay, tx.Store()).factor(np.zeros(2, np.int64), np.full((2, 2), 0.2))
    np.testing.assert_array_equal(got, np.zeros((2, 3)))  # texel (0, 0) cleaned to 0
    lay.uvs[:] = 0.75
    got = tx.Surface(lay, tx.Store()).factor(np.zeros(1, np.int64), np.full((1, 2), 0.2))
    np.testing.assert_array_equal(got, [[0.5, 0.0, 0.5]])  # colour (1, 0, 1) x texel 0.5
    with pytest.raises(ValueError, match="'flat'.*pixels"):
        tx.Store().fitted(tx.layout([Material("m", texture=Texture("flat", np.ones((4, 4))))],
                                    np.zeros(1, np.int32)))


def test_budget_fits_and_box_filters():
    limit = tx.BUDGET_BYTES // tx.TEXEL_BYTES
    assert tx.fitted_shapes([(8192, 8192)]) == [(4096, 4096)]  # 768 MiB -> 192 MiB
    assert tx.fitted_shapes([(1024, 1024)] * 20) == [(1024, 1024)] * 20  # 240 MiB fits
    shapes = tx.fitted_shapes([(1024, 1024)] * 30 + [(3, 5)])
    assert sum(h * w for h, w in shapes) <= limit
    assert set(shapes) == {(1024, 1024), (512, 512), (3, 5)}
    px = np.arange(16, dtype=np.float32).reshape(4, 4, 1).repeat(3, axis=2)
    np.testing.assert_allclose(tx.resampled(px, (2, 2))[..., 0], [[2.5, 4.5], [10.5, 12.5]])
    a, b, c = 1.0, 4.0, 10.0  # 3 texels onto 2: each new one covers 1.5 old ones
    row = np.array([[[a] * 3, [b] * 3, [c] * 3]], np.float32)
    np.testing.assert_allclose(tx.resampled(row, (1, 2))[0, :, 0],
                               [(a + 0.5 * b) / 1.5, (0.5 * b + c) / 1.5], rtol=1e-6)


def test_store_prepares_each_digest_once():
    store = tx.Store(budget=80 * tx.TEXEL_BYTES)  # 80 texels
    mats = [Material("a", texture=Texture("a", np.ones((8, 8, 3), np.float32), digest="A"))]
    first = tx.Surface(tx.layout(mats, np.zeros(1, np.int32)), store)
    again = tx.Surface(tx.layout(mats, np.zeros(1, np.int32)), store)
    assert store.prepared == 1 and again.textures[0] is first.textures[0]
    mats.append(Material("b", texture=Texture("b", np.ones((8, 8, 3), np.float32),
                                              digest="B")))
    both = tx.Surface(tx.layout(mats, np.array([0, 1], np.int32)), store)
    # 128 texels for 80: the first (largest, first of equals) is halved, so it is prepared anew
    assert [t.pixels.shape[:2] for t in both.textures] == [(4, 4), (8, 8)]
    assert both.info["resampled"] == ["a"] and store.prepared == 3


# --------------------------------------------------------------------- core scene


RED, GREEN = np.float32([0.8, 0.05, 0.05]), np.float32([0.05, 0.8, 0.05])


def checker_room(texture: Texture | None, antialias: int = 1, resolution=(48, 40)):
    """A 2 m floor (z = 0, UV = ((x + 1) / 2, (y + 1) / 2)) whose left half (x < 0) the
    2 x 1 texture makes red and right half green, a white back wall (y = 1), and a 30 degree
    spot 1.5 m above the red half that lights no green and none of the wall."""
    floor = demo.quad((-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0))
    wall = demo.quad((-1, 1, 0), (1, 1, 0), (1, 1, 2), (-1, 1, 2))
    pos = np.concatenate([floor, wall])
    uvs = np.stack([(pos[..., 0] + 1) / 2, (pos[..., 1] + 1) / 2], -1)
    floor_mat = Material("floor", np.ones(3, np.float32), texture=texture)
    if texture is None:
        floor_mat.albedo = 0.5 * (RED + GREEN)
    spot = Light("Spot", "SPOT", demo.light_matrix((-0.55, 0.0, 1.5), (0, 0, -1)),
                 power=200.0, spot_size=np.radians(30), spot_blend=0.0)
    cam = Camera.look_at((0.0, -3.0, 2.2), (0.0, 0.4, 0.5), resolution=resolution)
    return make_scene(pos, material_index=np.array([0, 0, 1, 1]),
                      materials=[floor_mat, Material("white")], lights=[spot], camera=cam,
                      settings=GISettings(antialias=antialias, cascades=1),
                      uvs=uvs if texture is not None else None)


CHECKER = Texture("checker", np.stack([RED, GREEN])[None], "Closest", "REPEAT", "checker-1")


def test_diffuse_color_per_pixel_is_the_checker():
    """Diffuse Color at every pixel is red where the G-buffer's point has x < 0 on the floor,
    green where x > 0, the wall's 0.8 on the wall (pixels next to another class left out)."""
    scene = checker_room(CHECKER)
    eng = engine.Engine()
    passes = deferred.render(eng, scene, eng.update(scene))
    mask, pos, _, _, _ = eng.raster.gbuffer(scene.camera.view, scene.camera.projection, 48, 40)
    cls = np.full(mask.shape, -1)
    on_floor = pos[:, 2] < 1e-4
    cls[mask] = np.where(on_floor, np.where(pos[:, 0] < 0, 0, 1), 2)
    pad = np.pad(cls, 1, mode="edge")
    inner = np.ones(cls.shape, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inner &= pad[1 + dy:41 + dy, 1 + dx:49 + dx] == cls
    expected = np.array([RED, GREEN, np.full(3, 0.8, np.float32)])
    color = passes["Diffuse Color"]
    for k in range(3):
        sel = inner & (cls == k)
        assert sel.sum() > 40
        np.testing.assert_allclose(color[sel], np.broadcast_to(expected[k], (sel.sum(), 3)),
                                   atol=1e-6)
    assert eng.raster.surface is not None and "textures" in eng.update(scene).stats.info


def wall_indirect(texture):
    scene = checker_room(texture)
    eng = engine.Engine()
    passes = deferred.render(eng, scene, eng.update(scene))
    mask, pos, _, _, _ = eng.raster.gbuffer(scene.camera.view, scene.camera.projection, 48, 40)
    wall = np.zeros(mask.shape, bool)
    wall[mask] = (pos[:, 1] > 1 - 1e-4) & (pos[:, 2] > 0.2)
    return passes["Diffuse Indirect"][wall].mean(axis=0), passes["Diffuse Direct"][wall].max()


def test_rsm_bleeds_the_texture_where_the_light_falls():
    """The spot lights only the red half: the white wall's indirect light is red (per-texel
    reflectance), not the mean colour's yellow an untextured floor of the mean bleeds."""
    red, direct = wall_indirect(CHECKER)
    assert direct == 0.0 and red[0] > 0
    assert red[0] > 8 * red[1]  # 0.8 / 0.05 = 16 for a floor lit on its red half only
    mean, _ = wall_indirect(None)
    assert 0.8 < mean[0] / mean[1] < 1.25
    assert abs(red.sum() - mean.sum()) > 0  # a texture change recomputed the light


def test_bleed_colour_replaces_the_texture_in_gi_only():
    scene = checker_room(dataclasses.replace(CHECKER))
    scene.materials[0].bleed_color = np.float32([0.1, 0.1, 0.9])
    eng = engine.Engine()
    passes = deferred.render(eng, scene, eng.update(scene))
    mask, pos, _, _, _ = eng.raster.gbuffer(scene.camera.view, scene.camera.projection, 48, 40)
    wall = np.zeros(mask.shape, bool)
    wall[mask] = (pos[:, 1] > 1 - 1e-4) & (pos[:, 2] > 0.2)
    e = passes["Diffuse Indirect"][wall].mean(axis=0)
    assert e[2] > 8 * e[0]  # blue bleed, not the red texture
    assert (passes["Diffuse Color"][..., 0] > 0.7).sum() > 40  # the red is still seen


def test_texture_change_recomputes_and_same_texture_reuses():
    scene = checker_room(CHECKER)
    eng = engine.Engine()
    eng.update(scene)
    stats = engine.Stats()
    eng.update(checker_room(CHECKER), stats)
    assert "propagation" not in stats.ms and eng.raster.texture_store.prepared == 1
    swapped = Texture("checker", np.stack([GREEN, RED])[None], "Closest", "REPEAT", "checker-2")
    stats = engine.Stats()
    green = eng.update(checker_room(swapped), stats)
    assert "rsm" in stats.ms and eng.raster.texture_store.prepared == 2
    assert green.values is not None


def test_corner_colours_multiply_the_albedo_per_point():
    """A Color Attribute: the wall's corners coloured (1, 0.5, 0.25) at z = 2 and 1 at
    z = 0: Diffuse Color on the wall is 0.8 x the colour interpolated at the point's height."""
    base = checker_room(None)
    cc = np.ones(base.positions.shape, np.float32)
    top = base.positions[..., 2] > 1
    cc[top] = (1.0, 0.5, 0.25)
    cc[:2] = 1.0
    scene = dataclasses.replace(base, corner_colors=cc)
    eng = engine.Engine()
    passes = deferred.render(eng, scene, eng.update(scene))
    mask, pos, _, _, _ = eng.raster.gbuffer(scene.camera.view, scene.camera.projection, 48, 40)
    wall = (pos[:, 1] > 1 - 1e-4) & (pos[:, 2] > 0.1) & (pos[:, 2] < 1.9)
    h = pos[wall, 2:3] / 2.0
    expected = 0.8 * ((1 - h) * 1.0 + h * np.array([1.0, 0.5, 0.25]))
    got = passes["Diffuse Color"][mask][wall]
    np.testing.assert_allclose(got, expected, atol=2e-5)


def test_untextured_scene_takes_no_textured_path():
    """No texture, no corner colours: no Surface, no textured programs, no extra targets."""
    scene = demo.cornell_box("SPOT", (16, 16), GISettings())
    eng = engine.Engine()
    deferred.render(eng, scene, eng.update(scene))
    assert eng.raster.surface is None and eng.raster._textured == {}
    assert set(eng.raster._fbos) <= {(k[0], k[1], n) for k in eng.raster._fbos for n in (1, 2, 4)}


@pytest.mark.parametrize("bounces", [1, 2])
def test_white_texture_gives_the_untextured_passes(bounces):
    """A texture of ones (and corner colours of ones) on every material takes the textured
    path (RSM texels, G-buffer, later bounces' surfels) and gives the untextured render's
    passes (float32 rounding apart)."""
    plain = demo.cornell_box("SPOT", (24, 24), GISettings(antialias=1, bounces=bounces))
    white = Texture("white", np.ones((2, 2, 3), np.float32), "Linear", "REPEAT", "ones")
    mats = [dataclasses.replace(m, texture=white) for m in plain.materials]
    textured = dataclasses.replace(plain, materials=mats,
                                   uvs=np.zeros(plain.positions.shape[:2] + (2,), np.float32),
                                   corner_colors=np.ones(plain.positions.shape, np.float32))
    out = []
    for scene in (plain, textured):
        eng = engine.Engine()
        out.append(deferred.render(eng, scene, eng.update(scene)))
    assert eng.raster.surface is not None
    for name in deferred.PASS_NAMES:
        ref = out[0][name]
        np.testing.assert_allclose(out[1][name], ref, atol=1e-5 * max(ref.max(), 1e-6),
                                   err_msg=name)


# --------------------------------------------------------------------------- worker


def test_worker_round_trip_keeps_textures_and_writes_pixels_once(tmp_path):
    from lpv_core import worker

    scene = checker_room(CHECKER)
    scene.corner_colors = np.full(scene.positions.shape, 0.5, np.float32)
    path = str(tmp_path / "scene.npz")
    worker.save_scene(path, scene)
    file = tmp_path / worker.TEXTURE_FOLDER / "checker-1.npy"
    first = file.stat()
    back = worker.load_scene(path)
    tex = back.materials[0].texture
    assert back.materials[1].texture is None
    assert (tex.name, tex.interpolation, tex.extension, tex.digest) == (
        "checker", "Closest", "REPEAT", "checker-1")
    np.testing.assert_array_equal(tex.pixels, CHECKER.pixels)
    np.testing.assert_array_equal(back.uvs, scene.uvs)
    np.testing.assert_array_equal(back.corner_colors, scene.corner_colors)
    np.save(file, np.zeros((1, 1, 3), np.float32))  # a marker in place of the pixels
    worker.save_scene(path, scene)  # the same digest: the pixels file is not rewritten
    assert file.stat().st_ino == first.st_ino
    assert worker.load_scene(path).materials[0].texture.pixels.shape == (1, 1, 3)
    np.save(file, CHECKER.pixels)
    for k in range(3):  # a texture painted on: a file per change, the old ones pruned
        scene.materials[0].texture = Texture("paint", np.full((64, 64, 3), k, np.float32),
                                             digest=f"paint-{k}")
        worker.save_scene(path, scene)
    assert worker.load_scene(path).materials[0].texture.digest == "paint-2"
    old = worker.TEXTURE_FILES_BYTES
    try:
        worker.TEXTURE_FILES_BYTES = 2 * 64 * 64 * 12 + 1000  # room for two of them
        worker.save_scene(path, scene)
    finally:
        worker.TEXTURE_FILES_BYTES = old
    left = sorted(f.name for f in (tmp_path / worker.TEXTURE_FOLDER).iterdir())
    assert "paint-2.npy" in left and len(left) == 2  # the oldest unused ones went first
    held: dict = {}
    one = worker.load_scene(path, held)
    two = worker.load_scene(path, held)  # the worker keeps the textures it holds
    assert two.materials[0].texture.pixels is one.materials[0].texture.pixels
    assert list(held) == ["paint-2"]


# ---------------------------------------------------------------------------- Cycles


@pytest.mark.bpy
def test_sampling_matches_cycles_diffuse_color(tmp_path):
    """A 4 x 4 image on 16 planes (one per interpolation and extension), UVs from -0.25 to
    1.25, seen by an orthographic camera at 24 px per plane: Cycles' Diffuse Color at each
    pixel centre (a 0.01 px box filter) equals sample() at that centre's UV. Cycles 5.0
    interpolates stochastically (one texel per sample, drawn with the filter's weights): 256
    samples leave a mean error of 1e-4 (Linear) and 1e-3 (Cubic); the modes differ from each
    other by 0.03 to 0.1 on this image. Closest is exact."""
    bpy = pytest.importorskip("bpy")
    from lpv_core.render import exr

    rng = np.random.default_rng(7)
    pixels = rng.uniform(0.05, 0.95, (4, 4, 3)).astype(np.float32)
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    img = bpy.data.images.new("tex4", 4, 4, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"
    rgba = np.concatenate([pixels, np.ones((4, 4, 1), np.float32)], axis=2)
    img.pixels.foreach_set(rgba.ravel())
    combos = [(i, e) for i in tx.INTERPOLATIONS for e in tx.EXTENSIONS]
    for k, (interp, ext) in enumerate(combos):
        gx, gy = k % 4, k // 4
        mesh = bpy.data.meshes.new(f"p{k}")
        x0, y0 = gx - 2.0, gy - 2.0
        mesh.from_pydata([(x0, y0, 0), (x0 + 1, y0, 0), (x0 + 1, y0 + 1, 0), (x0, y0 + 1, 0)],
                         [], [(0, 1, 2, 3)])
        uv = mesh.uv_layers.new(name="UVMap")
        uv.data.foreach_set("uv", [-0.25, -0.25, 1.25, -0.25, 1.25, 1.25, -0.25, 1.25])
        mat = bpy.data.materials.new(f"m{k}")
        mat.use_nodes = True
        nodes = mat.node_tree.nodes
        nodes.clear()
        node = nodes.new("ShaderNodeTexImage")
        node.image, node.interpolation, node.extension = img, interp, ext
        bsdf = nodes.new("ShaderNodeBsdfDiffuse")
        out = nodes.new("ShaderNodeOutputMaterial")
        mat.node_tree.links.new(node.outputs["Color"], bsdf.inputs["Color"])
        mat.node_tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        mesh.materials.append(mat)
        ob = bpy.data.objects.new(f"p{k}", mesh)
        scene.collection.objects.link(ob)
    cam = bpy.data.cameras.new("cam")
    cam.type, cam.ortho_scale = "ORTHO", 4.0
    cam_ob = bpy.data.objects.new("cam", cam)
    cam_ob.location = (0.0, 0.0, 5.0)
    scene.collection.objects.link(cam_ob)
    scene.camera = cam_ob
    r = scene.render
    r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage = "CYCLES", 96, 96, 100
    scene.cycles.device, scene.cycles.samples = "CPU", 256
    scene.cycles.use_denoising = scene.cycles.use_adaptive_sampling = False
    scene.cycles.pixel_filter_type, scene.cycles.filter_width = "BOX", 0.01
    scene.view_layers[0].use_pass_diffuse_color = True
    r.image_settings.media_type = "MULTI_LAYER_IMAGE"
    r.image_settings.color_depth = "32"
    r.filepath = str(tmp_path / "tex.exr")
    bpy.ops.render.render(write_still=True)
    color = exr.read_multilayer(tmp_path / "tex.exr")["Diffuse Color"][..., :3]
    centre = -0.25 + 1.5 * (np.arange(24) + 0.5) / 24  # UV at each pixel centre of a plane
    for k, (interp, ext) in enumerate(combos):
        gx, gy = k % 4, k // 4
        rows = slice(96 - 24 * (gy + 1), 96 - 24 * gy)  # rows top-first: high y first
        got = color[rows, 24 * gx:24 * (gx + 1)][::-1]  # now row 0 = lowest v
        u, v = np.meshgrid(centre, centre)
        want = tx.sample(Texture("tex4", pixels, interp, ext),
                         np.stack([u.ravel(), v.ravel()], 1)).reshape(24, 24, 3)
        err = np.abs(got - want)
        assert err.mean() < 2e-3 and err.max() < 1e-2, (interp, ext, err.mean(), err.max())


@pytest.mark.bpy
def test_checker_floor_from_blender_matches_cycles_diffuse_color(tmp_path):
    """An 8 x 8 checker image (Closest) on a 4 m floor through its UV map, a Diffuse BSDF,
    beside a metallic Principled block, extracted from Blender and rendered: Diffuse Color
    equals Cycles' (relative RMSE under 0.01) on the floor pixels a single texel covers (our
    4 x 4 samples see one colour), and is 0 on the metallic block like Cycles'."""
    bpy = pytest.importorskip("bpy")
    import mathutils

    from lpv_addon.render import cycles
    from lpv_addon.scene_io import extract
    from lpv_core.render import exr

    bpy.ops.wm.read_homefile(use_empty=True)
    sc = bpy.context.scene
    img = bpy.data.images.new("checker", 8, 8, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"
    ii, jj = np.meshgrid(np.arange(8), np.arange(8))
    rgba = np.where(((ii + jj) % 2 == 0)[..., None], [0.8, 0.1, 0.1, 1.0], [0.1, 0.7, 0.1, 1.0])
    img.pixels.foreach_set(rgba.astype(np.float32).ravel())

    def add(name, verts, faces, mat, uvs=None):
        me = bpy.data.meshes.new(name)
        me.from_pydata(verts, [], faces)
        if uvs is not None:
            me.uv_layers.new(name="UVMap").data.foreach_set("uv", uvs)
        me.materials.append(mat)
        sc.collection.objects.link(bpy.data.objects.new(name, me))

    floor = bpy.data.materials.new("floor")
    floor.use_nodes = True
    nt = floor.node_tree
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image, tex.interpolation = img, "Closest"
    diffuse = nt.nodes.new("ShaderNodeBsdfDiffuse")
    nt.links.new(tex.outputs["Color"], diffuse.inputs["Color"])
    nt.links.new(diffuse.outputs["BSDF"], nt.nodes["Material Output"].inputs["Surface"])
    add("floor", [(-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0)], [(0, 1, 2, 3)], floor,
        [0, 0, 1, 0, 1, 1, 0, 1])
    metal = bpy.data.materials.new("metal")
    metal.use_nodes = True
    metal.node_tree.nodes["Principled BSDF"].inputs["Metallic"].default_value = 1.0
    lo, hi = (0.4, -0.2, 0.0), (1.2, 0.6, 0.8)
    add("metal", [(x, y, z) for z in (lo[2], hi[2]) for y in (lo[1], hi[1])
                  for x in (lo[0], hi[0])],
        [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)],
        metal)
    light = bpy.data.objects.new("L", bpy.data.lights.new("L", "POINT"))
    light.data.energy, light.location = 300.0, (0.3, -0.6, 2.2)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.location = (0.0, -4.2, 3.0)
    cam.rotation_euler = (mathutils.Vector((0, 0.2, 0.3)) - cam.location).to_track_quat(
        "-Z", "Y").to_euler()
    for ob in (light, cam):
        sc.collection.objects.link(ob)
    sc.camera, sc.world = cam, None
    sc.render.resolution_x = sc.render.resolution_y = 48
    sc.render.resolution_percentage = 100
    cycles.render_cycles_passes(tmp_path / "ref.exr", samples=64, resolution=(48, 48))
    ref = exr.read_multilayer(tmp_path / "ref.exr")["Diffuse Color"][..., :3]
    core = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), sc,
                                 settings_overrides={"antialias": 4})
    eng = engine.Engine()
    color = deferred.render(eng, core, eng.update(core))["Diffuse Color"]
    texels = np.float32([[0.8, 0.1, 0.1], [0.1, 0.7, 0.1]])
    one = (np.abs(color[:, :, None] - texels).max(-1) < 1e-5).any(-1)  # one texel seen
    assert one.sum() > 400
    err = np.sqrt(((color[one] - ref[one]) ** 2).mean() / (ref[one] ** 2).mean())
    assert err < 0.01, err
    mask, pos, _, _, _ = eng.raster.gbuffer(core.camera.view, core.camera.projection, 48, 48)
    box = np.zeros(mask.shape, bool)  # the block's surface, then its pixels' interiors
    box[mask] = (np.abs(pos - 0.5 * np.add(lo, hi)) <= 0.5 * np.subtract(hi, lo) + 1e-3).all(
        -1) & (pos[:, 2] > 1e-3)
    pad = np.pad(box, 1)
    on_metal = box.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            on_metal &= pad[1 + dy:49 + dy, 1 + dx:49 + dx]
    assert on_metal.sum() > 20
    assert color[on_metal].max() == 0.0 and ref[on_metal].max() < 1e-3


OVERLAY_SCRIPT = r"""
import sys
import bpy, gpu
import numpy as np
import lpv_addon
from lpv_addon.viewport import live, overlay
from lpv_core.grid import Grid
from lpv_core.scene import GISettings, textures as tx

W = H = 64
lpv_addon.register()
r = bpy.context.scene.render
r.engine, r.resolution_x, r.resolution_y = "BLENDER_WORKBENCH", 8, 8
bpy.ops.render.render(write_still=False)  # Blender's GPU context, headless
rng = np.random.default_rng(3)
pixels = rng.uniform(0.05, 0.95, (4, 4, 3)).astype(np.float32)
grid = Grid((-1.2, -1.2, -1.2), 0.3, 8)
values = np.zeros((8, 8, 8, 3, 9), np.float32)
values[..., 0] = 1.0  # uniform light: the same irradiance at every pixel
combos = [(i, e) for i in tx.INTERPOLATIONS for e in tx.EXTENSIONS]
tris, uvs, ids = [], [], []
for k in range(16):  # a 4 x 4 grid of quads on z = 0, UVs -0.25 .. 1.25, one mode each
    x0, y0 = -1.0 + 0.5 * (k % 4), -1.0 + 0.5 * (k // 4)
    x1, y1 = x0 + 0.5, y0 + 0.5
    tris += [[(x0, y0, 0), (x1, y0, 0), (x1, y1, 0)], [(x0, y0, 0), (x1, y1, 0), (x0, y1, 0)]]
    a, b = -0.25, 1.25
    uvs += [[(a, a), (b, a), (b, b)], [(a, a), (b, b), (a, b)]]
    ids += [k, k]
t = len(tris)

def shot(textured):
    geometry = {"positions": np.array(tris, np.float32),
                "normals": np.tile(np.float32([0, 0, 1]), (t, 3, 1)),
                "albedo": np.ones((t, 3), np.float32), "receiver": np.ones(t, bool)}
    if textured:
        geometry.update(texture=np.array(ids), uvs=np.array(uvs, np.float32), textures=[
            tx.Texture("p", pixels, i, e, f"p-{i}-{e}") for i, e in combos])
    live.STATE.serial += 1
    result = live.LiveResult(serial=live.STATE.serial, grid=grid, values=values, per_light={},
                             lights=[], settings=GISettings(), areas=[], geometry=geometry,
                             visibility=None, gaps={grid: None})
    view = np.eye(4)
    view[2, 3] = -5.0
    proj = np.diag([1.0, 1.0, -0.2, 1.0])
    proj[2, 3] = -1.0
    off = gpu.types.GPUOffScreen(W, H, format="RGBA32F")
    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0, 0, 0, 0), depth=1.0)
        overlay.draw(view, proj, mode="INDIRECT", depth_prepass=True, current=result,
                     previous=None)
        buf = fb.read_color(0, 0, W, H, 4, 0, "FLOAT")
    off.free()
    buf.dimensions = W * H * 4
    return np.array(buf.to_list(), np.float32).reshape(H, W, 4)[::-1, :, :3]

plain = shot(False)
textured = shot(True)
shot(True)  # the next result, the same textures: not uploaded again
held = (len(overlay._TEXTURES), overlay.UPLOADS[0])
# what the live viewport hands the overlay for a core scene: textures per triangle, UVs,
# albedo x corner colours per corner, the textures fitted once per digest
from lpv_core.scene import Material, make_scene
quad = np.array([[(0, 0, 0), (1, 0, 0), (1, 1, 0)], [(0, 0, 0), (1, 1, 0), (0, 1, 0)]])
mats = [Material("t", np.float32([0.5, 0.5, 0.5]), texture=tx.Texture("p", pixels, digest="P")),
        Material("plain")]
core_scene = make_scene(quad, material_index=np.array([0, 1]), materials=mats,
                        uvs=quad[..., :2], corner_colors=np.full((2, 3, 3), 0.5))
geo, again = live._geometry(core_scene), live._geometry(core_scene)
live_ok = (geo["texture"].tolist() == [0, -1] and geo["uvs"].shape == (2, 3, 2)
           and np.allclose(geo["albedo"], [[[0.25] * 3] * 3, [[0.4] * 3] * 3])
           and again["textures"][0] is geo["textures"][0]
           and np.array_equal(geo["textures"][0].pixels, pixels))
np.savez(sys.argv[1], plain=plain, textured=textured, pixels=pixels, held=held,
         live_ok=live_ok)
"""


@pytest.mark.bpy
def test_overlay_reads_the_textures_as_the_render_does(tmp_path):
    """The overlay on other engines, drawn by Blender's gpu module (a child Blender process):
    16 quads, one per interpolation and extension, UVs -0.25 .. 1.25, under uniform LPV light:
    the textured image over the untextured one is textures.sample's mean over each pixel's
    footprint (the render's footprint_factor rule; RGBA16F texels: within 2e-3 where the
    texture is constant over the pixel), each texture uploaded once."""
    import subprocess
    import sys

    pytest.importorskip("bpy")
    from conftest import ROOT

    out = tmp_path / "overlay.npz"
    proc = subprocess.run([sys.executable, "-c", OVERLAY_SCRIPT, str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300, check=False,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = np.load(out)
    plain, textured = res["plain"], res["textured"]
    assert plain.min() > 0 and res["held"].tolist() == [16, 16] and bool(res["live_ok"])
    ratio = textured / plain
    k = 32  # points a pixel side of the footprint's reference mean
    fine = -0.25 + 1.5 * (np.arange(16 * k) + 0.5) / (16 * k)
    u, v = np.meshgrid(fine, fine)
    for n, (interp, ext) in enumerate((i, e) for i in tx.INTERPOLATIONS for e in tx.EXTENSIONS):
        gx, gy = n % 4, n // 4
        got = ratio[64 - 16 * (gy + 1):64 - 16 * gy, 16 * gx:16 * (gx + 1)][::-1]
        at = tx.sample(Texture("p", res["pixels"], interp, ext),
                       np.stack([u.ravel(), v.ravel()], 1)).reshape(16, k, 16, k, 3)
        want, spread = at.mean(axis=(1, 3)), np.ptp(at, axis=(1, 3)).max(axis=-1)
        err = np.abs(got - want).max(axis=-1)
        # where the texture is constant over the pixel: its value (RGBA16F texels: 2e-3)
        assert err[spread < 1e-6].max(initial=0.0) < 2e-3, (interp, ext)
        # elsewhere its mean over the pixel, to the sub-points' resolution: an edge is off by
        # at most 1/(2 FOOTPRINT_SPLIT) of the step per axis (smooth modes: far less)
        bound = (1 / tx.FOOTPRINT_SPLIT if interp == "Closest" else 0.01) * spread + 2e-3
        assert (err <= bound).all(), (interp, ext, err.max())


# ------------------------------------------------------------- the pixel footprint


def _area_fraction(cells: int, texels: int, checker: np.ndarray) -> np.ndarray:
    """(cells, cells) exact mean of a Closest ``checker`` (texels, texels) (rows bottom-first)
    over a grid of square cells covering the unit UV square, rows top-first: the texel
    overlaps of a cell's u and v ranges, multiplied (hand-derived, separable)."""
    edges = np.arange(cells + 1) / cells
    t = np.arange(texels + 1) / texels
    over = np.clip(np.minimum(edges[1:, None], t[None, 1:])
                   - np.maximum(edges[:-1, None], t[None, :-1]), 0, None) * cells
    return (over @ checker @ over.T)[::-1]  # rows: v from the top


def _checker_view(interpolation: str, extension: str, digest: str, **settings):
    """A 5 x 5 checker (0 / 1) texture on a 2 m square seen head-on by an orthographic camera
    whose 16 x 16 pixels cover the square: (checker, texture, the render's Diffuse Color)."""
    from lpv_core.scene.model import look_at_matrix, orthographic_matrix

    n, res = 5, 16
    checker = (np.add.outer(np.arange(n), np.arange(n)) % 2).astype(np.float32)
    tex = Texture("chk", np.repeat(checker[..., None], 3, axis=2), interpolation, extension,
                  digest)
    pos = demo.quad((-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0))
    uvs = np.stack([(pos[..., 0] + 1) / 2, (pos[..., 1] + 1) / 2], -1)
    cam = Camera(look_at_matrix((0, 0, 3), (0, 0, 0), (0, 1, 0)),
                 orthographic_matrix(1.0, 1.0, 0.1, 10.0), (res, res))
    scene = make_scene(pos, material_index=np.zeros(2, np.int32),
                       materials=[Material("chk", np.ones(3, np.float32), texture=tex)],
                       lights=[], camera=cam, uvs=uvs, settings=GISettings(**settings))
    eng = engine.Engine()
    return checker, tex, deferred.render(eng, scene, eng.update(scene))["Diffuse Color"][..., 0]


@pytest.mark.parametrize("antialias", [1, 2])
def test_diffuse_color_is_the_area_fraction_of_a_closest_checker(antialias):
    """A 5 x 5 Closest checker (0 / 1) on a 2 m square seen head-on by an orthographic camera
    whose 16 x 16 pixels cover the square: each pixel's Diffuse Color is the exact share of
    the 1-texels in it (texel edges cross pixels at fifths of sixteenths), within the
    FOOTPRINT_SPLIT x antialias sub-points' resolution: an axis-aligned edge is off by at
    most half a sub-point's width per axis. One point per sample is off by up to 1/2."""
    checker, _, color = _checker_view("Closest", "REPEAT", "chk5", antialias=antialias,
                                      cascades=1)
    expected = _area_fraction(16, 5, checker)
    err = np.abs(color - expected)
    bound = 1.0 / (tx.FOOTPRINT_SPLIT * antialias)  # 1/(2k) per axis, two axes
    assert err.max() <= bound + 1e-6, (err.max(), bound)
    assert err.mean() <= bound / 4  # edges at fifths: most pixels far better than the bound
    assert (err > 0.1).sum() == 0 and ((expected > 0.05) & (expected < 0.95)).sum() > 80


@pytest.mark.parametrize("interpolation", ["Linear", "Cubic"])
def test_footprint_follows_the_textures_interpolation(interpolation):
    """The same view of a Linear / Cubic checker: each pixel is the texture's mean over the
    pixel (sample's own interpolation, 48^2 points a pixel), within the refinement threshold
    and the sub-points' resolution; the pixel's centre alone is off by 3 times more."""
    res, k = 16, 48
    _, tex, color = _checker_view(interpolation, "EXTEND", "chk5" + interpolation, antialias=1)
    g = (np.arange(res * k) + 0.5) / (res * k)
    u, v = np.meshgrid(g, g[::-1])
    fine = tx.sample(tex, np.stack([u.ravel(), v.ravel()], 1))[:, 0].reshape(res * k, res * k)
    expected = fine.reshape(res, k, res, k).mean(axis=(1, 3))
    c = (np.arange(res) + 0.5) / res
    cu, cv = np.meshgrid(c, c[::-1])
    centre = tx.sample(tex, np.stack([cu.ravel(), cv.ravel()], 1))[:, 0].reshape(res, res)
    err, off = np.abs(color - expected).max(), np.abs(centre - expected).max()
    assert err < 0.01 and err < off / 3, (err, off)


# ------------------------------------------------------------------ the view share


def test_view_share_per_pixel_carried_and_validated(tmp_path):
    """A material's diffuse_share scales its Diffuse Color per pixel at the cosine between the
    normal and the direction to the camera (hand-derived here for a floor seen from a known
    eye, the share linear in the cosine), untextured scenes included; a scene without one
    stays bit-identical; the worker carries it; make_scene drops a non-finite one."""
    from lpv_core import worker
    from lpv_core.scene.textures import SHARE_COS

    plain = checker_room(None)
    base = deferred.render(e := engine.Engine(), plain, e.update(plain))["Diffuse Color"]
    share = np.repeat(np.asarray(SHARE_COS, np.float32)[:, None], 3, axis=1)  # share = cos
    shared = dataclasses.replace(plain, materials=[
        dataclasses.replace(plain.materials[0], diffuse_share=share), plain.materials[1]])
    eng = engine.Engine()
    color = deferred.render(eng, shared, eng.update(shared))["Diffuse Color"]
    mask, pos, _, _, _ = eng.raster.gbuffer(shared.camera.view, shared.camera.projection, 48, 40)
    floor = np.zeros(mask.shape, bool)
    floor[mask] = pos[:, 2] < 1e-4
    inner = floor & np.roll(floor, 1, 0) & np.roll(floor, -1, 0) & np.roll(floor, 1, 1) \
        & np.roll(floor, -1, 1)
    p = np.full(mask.shape + (3,), np.nan)
    p[mask] = pos
    to_eye = np.array([0.0, -3.0, 2.2]) - p[inner]
    cos = to_eye[:, 2] / np.linalg.norm(to_eye, axis=1)  # the floor's normal is +z
    # a pixel averages 4 samples over its footprint: cos varies by < 1e-3 across a pixel
    np.testing.assert_allclose(color[inner], base[inner] * cos[:, None], rtol=2e-3)
    wall = mask & ~floor
    # no table: the triangle's albedo (exact, where the colour target interpolates it)
    np.testing.assert_allclose(color[wall], base[wall], atol=2e-7)
    again = deferred.render(e2 := engine.Engine(), plain, e2.update(plain))["Diffuse Color"]
    np.testing.assert_array_equal(again, base)  # no table anywhere: the untextured path
    assert e2.raster.shares is None and e2.raster.corners is None
    path = str(tmp_path / "scene.npz")
    worker.save_scene(path, shared)
    back = worker.load_scene(path).materials[0].diffuse_share
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, share)
    bad = share.copy()
    bad[3, 1] = np.nan
    repaired = make_scene(plain.positions, material_index=plain.material_index, materials=[
        Material("bad", diffuse_share=bad), Material("neg", diffuse_share=-share)])
    assert repaired.materials[0].diffuse_share is None
    assert repaired.materials[1].diffuse_share.min() == 0
    assert repaired.dropped["materials_with_invalid_values_defaulted"] == 2
