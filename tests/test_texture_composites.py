"""Several images through one UV map, combined per texel as Cycles combines them: a Metallic
or Transmission map scales a Principled's base colour, a factor image blends two images (Mix
Color) or two shaders (Mix Shader), two images multiply. Against Cycles' Diffuse Color pass of
a tiny render, texel by texel; an image through another UV map still takes its mean, reported."""

import numpy as np
import pytest

pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

N = 8  # the base images' texels per side; the factor images have N / 2
PX = 3  # pixels per base texel


def _image(bpy, name, rgb):
    h, w = rgb.shape[:2]
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(np.concatenate([rgb, np.ones((h, w, 1))], 2).astype(
        np.float32).ravel())
    return img


def _images():
    """(base checker, second colour image, factor image of N/2 texels), rows bottom-first."""
    rng = np.random.default_rng(3)
    ii, jj = np.meshgrid(np.arange(N), np.arange(N))
    base = np.where(((ii + jj) % 2 == 0)[..., None], [0.8, 0.2, 0.1], [0.1, 0.6, 0.3])
    other = rng.uniform(0.05, 0.95, (N, N, 3))
    fac = np.repeat(rng.uniform(0.0, 1.0, (N // 2, N // 2))[..., None], 3, axis=2)
    fac[0, 0], fac[1, 1] = 0.0, 1.0
    return base, other, fac


def _scene(tmp_path):
    """Five 1 x 1 m planes side by side, each a material of base and factor images; an
    orthographic camera straight down; Cycles' Diffuse Color and ours."""
    import bpy

    from lpv_addon.render import cycles
    from lpv_addon.scene_io import extract
    from lpv_core import engine
    from lpv_core.render import deferred, exr

    bpy.ops.wm.read_homefile(use_empty=True)
    sc = bpy.context.scene
    base, other, fac = _images()
    img_base, img_other, img_fac = (_image(bpy, n, a) for n, a in
                                    (("base", base), ("other", other), ("fac", fac)))

    def tex(nt, img):
        node = nt.nodes.new("ShaderNodeTexImage")
        node.image, node.interpolation = img, "Closest"
        return node.outputs["Color"]

    def material(k):
        mat = bpy.data.materials.new(f"m{k}")
        nt = mat.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        link = nt.links.new
        if k in (0, 1):  # Principled: Metallic map, Transmission map
            p = nt.nodes.new("ShaderNodeBsdfPrincipled")
            link(tex(nt, img_base), p.inputs["Base Color"])
            link(tex(nt, img_fac), p.inputs["Metallic" if k == 0 else "Transmission Weight"])
            shader = p.outputs["BSDF"]
        elif k == 2:  # Mix Color, a factor image between two images
            mix = nt.nodes.new("ShaderNodeMix")
            mix.data_type = "RGBA"
            link(tex(nt, img_fac), mix.inputs["Factor"])
            link(tex(nt, img_base), mix.inputs["A"])
            link(tex(nt, img_other), mix.inputs["B"])
            d = nt.nodes.new("ShaderNodeBsdfDiffuse")
            link(mix.outputs["Result"], d.inputs["Color"])
            shader = d.outputs["BSDF"]
        elif k == 3:  # Mix Shader, a factor image between an image and a constant
            mix = nt.nodes.new("ShaderNodeMixShader")
            a, b = nt.nodes.new("ShaderNodeBsdfDiffuse"), nt.nodes.new("ShaderNodeBsdfDiffuse")
            link(tex(nt, img_base), a.inputs["Color"])
            b.inputs["Color"].default_value = (0.1, 0.2, 0.9, 1.0)
            link(tex(nt, img_fac), mix.inputs["Fac"])
            link(a.outputs["BSDF"], mix.inputs[1])
            link(b.outputs["BSDF"], mix.inputs[2])
            shader = mix.outputs["Shader"]
        else:  # Mix Color Multiply, factor 1: the two images' product
            mix = nt.nodes.new("ShaderNodeMix")
            mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
            mix.inputs["Factor"].default_value = 1.0
            link(tex(nt, img_base), mix.inputs["A"])
            link(tex(nt, img_other), mix.inputs["B"])
            d = nt.nodes.new("ShaderNodeBsdfDiffuse")
            link(mix.outputs["Result"], d.inputs["Color"])
            shader = d.outputs["BSDF"]
        link(shader, out.inputs["Surface"])
        return mat

    for k in range(5):
        me = bpy.data.meshes.new(f"p{k}")
        x0 = k - 2.5
        me.from_pydata([(x0, -0.5, 0), (x0 + 1, -0.5, 0), (x0 + 1, 0.5, 0), (x0, 0.5, 0)], [],
                       [(0, 1, 2, 3)])
        me.uv_layers.new(name="UVMap").data.foreach_set("uv", [0, 0, 1, 0, 1, 1, 0, 1])
        me.materials.append(material(k))
        sc.collection.objects.link(bpy.data.objects.new(f"p{k}", me))
    cam = bpy.data.cameras.new("cam")
    cam.type, cam.ortho_scale = "ORTHO", 5.0
    cam_ob = bpy.data.objects.new("cam", cam)
    cam_ob.location = (0.0, 0.0, 5.0)
    sc.collection.objects.link(cam_ob)
    sc.camera, sc.world = cam_ob, None
    w, h = 5 * N * PX, N * PX
    sc.render.resolution_x, sc.render.resolution_y = w, h
    sc.render.resolution_percentage = 100
    sc.cycles.pixel_filter_type, sc.cycles.filter_width = "BOX", 0.01
    cycles.render_cycles_passes(tmp_path / "ref.exr", samples=16, resolution=(w, h))
    ref = exr.read_multilayer(tmp_path / "ref.exr")["Diffuse Color"][..., :3]
    core = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), sc,
                                 settings_overrides={"antialias": 1})
    eng = engine.Engine()
    ours = deferred.render(eng, core, eng.update(core))["Diffuse Color"]
    notes = [line for line in core.approximated]
    return np.asarray(ours, np.float64), np.asarray(ref, np.float64), notes


def _texel_centres(a: np.ndarray, k: int) -> np.ndarray:
    """(N, N, 3) plane k's pixels at its texels' centres, rows bottom-first."""
    plane = a[:, k * N * PX:(k + 1) * N * PX][::-1]
    return plane[PX // 2::PX, PX // 2::PX]


def test_maps_and_factor_images_combine_per_texel_as_in_cycles(tmp_path):
    ours, ref, notes = _scene(tmp_path)
    base, other, fac = _images()
    f = np.repeat(np.repeat(fac, 2, axis=0), 2, axis=1)  # the factor on the base's texels
    for k, name in enumerate(("metallic map", "transmission map", "mix colour", "mix shader",
                              "multiply")):
        got, want = _texel_centres(ours, k), _texel_centres(ref, k)
        err = np.abs(got - want).max()
        assert err < 0.01 * max(want.max(), 1e-3), (name, err)
    # the hand-derived values where the material is plain Diffuse: texel by texel
    np.testing.assert_allclose(_texel_centres(ours, 2), base + f * (other - base), atol=2e-3)
    np.testing.assert_allclose(_texel_centres(ours, 3),
                               base + f * (np.float64([0.1, 0.2, 0.9]) - base), atol=2e-3)
    np.testing.assert_allclose(_texel_centres(ours, 4), base * other, atol=2e-3)
    # where the factor is 1 the metal has no diffuse colour, where 0 the full base's share
    metal = _texel_centres(ours, 0)
    assert metal[2:4, 2:4].max() == 0.0 and metal[0:2, 0:2].min() > 0.05
    # the means left are reported for what they are used for: none for the Diffuse Color
    means = [line for line in notes if "mean" in line]
    assert means and all(" for the " in line or "the metal colour" in line for line in means), \
        notes


def test_images_through_different_uv_maps_take_the_mean_and_say_so():
    """Two images mixed through two UV maps cannot be combined texel by texel: the second
    image's mean colour is mixed in, and the note names both images."""
    import bpy

    from lpv_addon.scene_io.materials import material_info

    bpy.ops.wm.read_homefile(use_empty=True)
    base, other, _ = _images()
    mat = bpy.data.materials.new("two_uvs")
    nt = mat.node_tree
    nt.nodes.clear()
    texs = []
    for name, rgb, uv_name in (("a", base, "UVMap"), ("b", other, "Second")):
        node = nt.nodes.new("ShaderNodeTexImage")
        node.image, node.interpolation = _image(bpy, name, rgb), "Closest"
        uv = nt.nodes.new("ShaderNodeUVMap")
        uv.uv_map = uv_name
        nt.links.new(uv.outputs["UV"], node.inputs["Vector"])
        texs.append(node.outputs["Color"])
    mix = nt.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.inputs["Factor"].default_value = 0.25
    nt.links.new(texs[0], mix.inputs["A"])
    nt.links.new(texs[1], mix.inputs["B"])
    d = nt.nodes.new("ShaderNodeBsdfDiffuse")
    nt.links.new(mix.outputs["Result"], d.inputs["Color"])
    nt.links.new(d.outputs["BSDF"], nt.nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
    info = material_info(mat)
    m = info.material
    want = 0.75 * base + 0.25 * other.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(m.albedo * m.texture.pixels, want, atol=1e-5)
    assert info.uv_map == "UVMap"
    assert any("'a', 'b'" in line and "different UV maps" in line for line in info.notes), \
        info.notes
