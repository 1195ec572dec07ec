"""Materials from real Blender files: the diffuse albedo against Cycles' own Diffuse Color pass,
image textures, UVs, colour attributes, missing images and bad values.

One Cycles render (an orthographic camera over a row of unit patches, each its own material,
4 x 4 pixels a patch, 16 samples: about 2 s) is the reference for every shader case.
"""

from __future__ import annotations

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from lpv_addon.render import cycles
from lpv_addon.scene_io import extract, materials
from lpv_core.render import exr

pytestmark = pytest.mark.bpy

BASE = (0.8, 0.5, 0.2, 1.0)
P = 4  # pixels per patch side
COLS = 8


# ------------------------------------------------------------------------------ builders


def new_material(name):
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5: node trees are opt-in
        mat.use_nodes = True
    nt = mat.node_tree
    for node in list(nt.nodes):
        if node.bl_idname != "ShaderNodeOutputMaterial":
            nt.nodes.remove(node)
    return mat, nt, next(n for n in nt.nodes if n.bl_idname == "ShaderNodeOutputMaterial")


def principled(nt, **inputs):
    p = nt.nodes.new("ShaderNodeBsdfPrincipled")
    p.inputs["Base Color"].default_value = BASE
    for key, value in inputs.items():
        p.inputs[key.replace("_", " ")].default_value = value
    return p


def sock(sockets, identifier):
    return next(s for s in sockets if s.identifier == identifier)


def to_surface(nt, out, node):
    nt.links.new(node.outputs[0], out.inputs["Surface"])


def image_material(name, image, **inputs):
    """A Principled material (``inputs`` set on it) whose Base Color is ``image`` through the
    render UV map: (the material, its Image Texture node)."""
    mat, nt, out = new_material(name)
    p = principled(nt, **inputs)
    t = nt.nodes.new("ShaderNodeTexImage")
    t.image = image
    nt.links.new(t.outputs["Color"], p.inputs["Base Color"])
    to_surface(nt, out, p)
    return mat, t


def shader(kind, **inputs):
    def build(nt, out):
        node = nt.nodes.new(kind)
        if "Color" in node.inputs:
            node.inputs["Color"].default_value = BASE
        for key, value in inputs.items():
            node.inputs[key].default_value = value
        to_surface(nt, out, node)
    return build


def pr(**inputs):
    return lambda nt, out: to_surface(nt, out, principled(nt, **inputs))


def mix_shader(fac, linked=False, muted=False):
    def build(nt, out):
        m = nt.nodes.new("ShaderNodeMixShader")
        a = nt.nodes.new("ShaderNodeBsdfDiffuse")
        a.inputs["Color"].default_value = (1, 0, 0, 1)
        b = principled(nt, Base_Color=(0, 0, 1, 1))
        nt.links.new(a.outputs[0], m.inputs[1])
        nt.links.new(b.outputs[0], m.inputs[2])
        if linked:
            v = nt.nodes.new("ShaderNodeValue")
            v.outputs[0].default_value = fac
            nt.links.new(v.outputs[0], m.inputs[0])
        else:
            m.inputs[0].default_value = fac
        m.mute = muted
        to_surface(nt, out, m)
    return build


def add_shader(second):
    def build(nt, out):
        m = nt.nodes.new("ShaderNodeAddShader")
        a = nt.nodes.new("ShaderNodeBsdfDiffuse")
        a.inputs["Color"].default_value = (0.3, 0.1, 0.0, 1)
        b = nt.nodes.new(second)
        if second == "ShaderNodeBsdfDiffuse":
            b.inputs["Color"].default_value = (0.4, 0.2, 0.1, 1)
        nt.links.new(a.outputs[0], m.inputs[0])
        nt.links.new(b.outputs[0], m.inputs[1])
        to_surface(nt, out, m)
    return build


def group(nt, out):
    g = bpy.data.node_groups.new("metal half", "ShaderNodeTree")
    g.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    g.interface.new_socket("Color", in_out="INPUT", socket_type="NodeSocketColor")
    gi, go = g.nodes.new("NodeGroupInput"), g.nodes.new("NodeGroupOutput")
    p = g.nodes.new("ShaderNodeBsdfPrincipled")
    p.inputs["Metallic"].default_value = 0.5
    g.links.new(gi.outputs[0], p.inputs["Base Color"])
    g.links.new(p.outputs[0], go.inputs[0])
    node = nt.nodes.new("ShaderNodeGroup")
    node.node_tree = g
    node.inputs[0].default_value = BASE
    to_surface(nt, out, node)


def reroute(nt, out):
    p, r = principled(nt), nt.nodes.new("NodeReroute")
    nt.links.new(p.outputs[0], r.inputs[0])
    nt.links.new(r.outputs[0], out.inputs["Surface"])


def muted_principled(nt, out):
    p = principled(nt)
    p.mute = True
    to_surface(nt, out, p)


def missing_image(name):
    img = bpy.data.images.new(name, 4, 4)
    img.source = "FILE"
    img.filepath = f"//missing/{name}.png"
    img.reload()
    return img


def missing_on(socket):
    def build(nt, out):
        p = principled(nt)
        t = nt.nodes.new("ShaderNodeTexImage")
        t.image = missing_image(f"gone {socket}")
        nt.links.new(t.outputs["Color"], p.inputs[socket])
        to_surface(nt, out, p)
    return build


def attribute(name, mix=None):
    """Principled whose Base Color is a Color Attribute (through a Mix Color MULTIPLY with a
    constant when ``mix``)."""
    def build(nt, out):
        p = principled(nt)
        a = nt.nodes.new("ShaderNodeVertexColor")
        a.layer_name = name
        src = a.outputs["Color"]
        if mix is not None:
            m = nt.nodes.new("ShaderNodeMix")
            m.data_type, m.blend_type = "RGBA", "MULTIPLY"
            sock(m.inputs, "Factor_Float").default_value = 1.0
            sock(m.inputs, "B_Color").default_value = mix
            nt.links.new(src, sock(m.inputs, "A_Color"))
            src = sock(m.outputs, "Result_Color")
        nt.links.new(src, p.inputs["Base Color"])
        to_surface(nt, out, p)
    return build


def rgb_mix(blend, fac, b):
    """Diffuse whose Color is Mix Color (``blend``, ``fac``) of BASE and constant ``b`` via an
    RGB node."""
    def build(nt, out):
        d = nt.nodes.new("ShaderNodeBsdfDiffuse")
        m = nt.nodes.new("ShaderNodeMix")
        m.data_type, m.blend_type = "RGBA", blend
        sock(m.inputs, "Factor_Float").default_value = fac
        sock(m.inputs, "A_Color").default_value = BASE
        rgb = nt.nodes.new("ShaderNodeRGB")
        rgb.outputs[0].default_value = b
        nt.links.new(rgb.outputs[0], sock(m.inputs, "B_Color"))
        nt.links.new(sock(m.outputs, "Result_Color"), d.inputs["Color"])
        to_surface(nt, out, d)
    return build


# 2 x 2 test images, rows bottom-first as Image.pixels; Closest interpolation so that each
# texel covers one quadrant (2 x 2 pixels) of its patch exactly.
TEXELS = np.array([[[0.9, 0.1, 0.2, 1.0], [0.2, 0.7, 0.1, 1.0]],
                   [[0.1, 0.3, 0.9, 1.0], [0.5, 0.5, 0.5, 1.0]]], np.float32)


def image_patch(colorspace="sRGB", is_float=False, mapping=False, alpha=None, mixed=False):
    def build(nt, out):
        img = bpy.data.images.new(f"img {colorspace} {is_float} {mapping} {alpha}", 2, 2,
                                  float_buffer=is_float)
        img.colorspace_settings.name = colorspace
        px = TEXELS.copy()
        if alpha is not None:
            px[..., 3] = alpha
        img.pixels.foreach_set(px.ravel())
        p = principled(nt)
        t = nt.nodes.new("ShaderNodeTexImage")
        t.image, t.interpolation = img, "Closest"
        if mapping:  # u -> 1 - u, v -> v + 0.5: quadrants swap left-right and top-bottom
            m = nt.nodes.new("ShaderNodeMapping")
            m.inputs["Location"].default_value = (1.0, 0.5, 0.0)
            m.inputs["Scale"].default_value = (-1.0, 1.0, 1.0)
            uv = nt.nodes.new("ShaderNodeUVMap")
            uv.uv_map = "UVMap"
            nt.links.new(uv.outputs["UV"], m.inputs["Vector"])
            nt.links.new(m.outputs["Vector"], t.inputs["Vector"])
        nt.links.new(t.outputs["Color"], p.inputs["Base Color"])
        if not mixed:
            to_surface(nt, out, p)
            return
        # The same image node also colours a Diffuse BSDF, mixed 0.3 with the Principled.
        d, m = nt.nodes.new("ShaderNodeBsdfDiffuse"), nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(t.outputs["Color"], d.inputs["Color"])
        m.inputs[0].default_value = 0.3
        nt.links.new(p.outputs[0], m.inputs[1])
        nt.links.new(d.outputs[0], m.inputs[2])
        to_surface(nt, out, m)
    return build


SHADER_CASES = {
    "diffuse": shader("ShaderNodeBsdfDiffuse"),
    "principled": pr(),
    "metallic 0.5": pr(Metallic=0.5), "metallic 1": pr(Metallic=1.0),
    "transmission 0.5": pr(Transmission_Weight=0.5), "transmission 1": pr(Transmission_Weight=1.0),
    "metallic 0.5 transmission 0.5": pr(Metallic=0.5, Transmission_Weight=0.5),
    "coat 1": pr(Coat_Weight=1.0), "coat 0.5": pr(Coat_Weight=0.5),
    "coat tint": pr(Coat_Weight=1.0, Coat_Tint=(0.5, 1.0, 0.25, 1.0)),
    "sheen 1": pr(Sheen_Weight=1.0),
    "sheen rough metallic": pr(Sheen_Weight=1.0, Sheen_Roughness=1.0, Metallic=0.5),
    "subsurface 1": pr(Subsurface_Weight=1.0),
    "specular level 0": pr(Specular_IOR_Level=0.0), "specular level 1": pr(Specular_IOR_Level=1.0),
    "ior 1.33": pr(IOR=1.33), "roughness 0.3 ior 1.6": pr(Roughness=0.3, IOR=1.6), "roughness 0": pr(Roughness=0.0), "roughness 1": pr(Roughness=1.0),
    "alpha 0.5": pr(Alpha=0.5),
    "mix 0.3": mix_shader(0.3), "mix linked 0.7": mix_shader(0.7, linked=True),
    "mix muted": mix_shader(0.5, muted=True),
    "add diffuse glossy": add_shader("ShaderNodeBsdfGlossy"),
    "add diffuse diffuse": add_shader("ShaderNodeBsdfDiffuse"),
    "emission": shader("ShaderNodeEmission"), "glossy": shader("ShaderNodeBsdfGlossy"),
    "glass": shader("ShaderNodeBsdfGlass"), "transparent": shader("ShaderNodeBsdfTransparent"),
    "refraction": shader("ShaderNodeBsdfRefraction"),
    "translucent": shader("ShaderNodeBsdfTranslucent"),
    "subsurface node": shader("ShaderNodeSubsurfaceScattering"),
    "toon": shader("ShaderNodeBsdfToon"), "sheen node": shader("ShaderNodeBsdfSheen"),
    "diffuse roughness 1": pr(Diffuse_Roughness=1.0),
    "group": group, "reroute": reroute, "muted principled": muted_principled,
    "missing base color": missing_on("Base Color"), "missing metallic": missing_on("Metallic"),
    "color attribute": attribute("Col"),
    "color attribute x constant": attribute("Col", mix=(0.5, 1.0, 0.25, 1.0)),
    "color attribute missing": attribute("nothing"),
    "mix color mix": rgb_mix("MIX", 0.25, (0.0, 0.2, 1.0, 1.0)),
    "mix color multiply": rgb_mix("MULTIPLY", 0.5, (0.5, 1.0, 0.0, 1.0)),
    "no material": None,  # no material slot: Cycles' default surface
}
TEXTURE_CASES = {
    "texture sRGB": image_patch("sRGB"),
    "texture Non-Color": image_patch("Non-Color"),
    "texture float": image_patch("Linear Rec.709", is_float=True),
    "texture mapping": image_patch("sRGB", mapping=True),
    "texture alpha 0.5": image_patch("sRGB", alpha=0.5),
    "texture in both mixed shaders": image_patch("sRGB", mixed=True),
}
CORNER_COLOR = (0.2, 0.6, 0.4, 1.0)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """(Cycles' Diffuse Color (H, W, 3) top-first, the extracted core Scene, patch names)."""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    names = list(SHADER_CASES) + list(TEXTURE_CASES)
    rows = -(-len(names) // COLS)
    for i, name in enumerate(names):
        build = (SHADER_CASES | TEXTURE_CASES)[name]
        if build is not None:
            mat, nt, out = new_material(name)
            build(nt, out)
        x, y = i % COLS, i // COLS
        me = bpy.data.meshes.new(name)
        me.from_pydata([(x, -y, 0), (x + 1, -y, 0), (x + 1, -y - 1, 0), (x, -y - 1, 0)], [],
                       [(0, 3, 2, 1)])
        uv = me.uv_layers.new(name="UVMap")
        uv.uv.foreach_set("vector", [0, 1, 0, 0, 1, 0, 1, 1])  # vertices 0, 3, 2, 1
        col = me.color_attributes.new("Col", "FLOAT_COLOR", "CORNER")
        col.data.foreach_set("color", CORNER_COLOR * 4)
        if build is not None:
            me.materials.append(mat)
        scene.collection.objects.link(bpy.data.objects.new(name, me))
    cam = bpy.data.cameras.new("cam")
    cam.type, cam.ortho_scale = "ORTHO", COLS
    ob = bpy.data.objects.new("cam", cam)
    ob.location = (COLS / 2, -rows / 2, 5)
    scene.collection.objects.link(ob)
    scene.camera = ob
    path = tmp_path_factory.mktemp("materials") / "diffuse_color.exr"
    cycles.render_cycles_passes(path, samples=16, resolution=(COLS * P, rows * P))
    color = exr.read_multilayer(path)["Diffuse Color"]
    s = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), require_camera=False)
    return color, s, names


def patch(reference, name):
    color, _, names = reference
    i = names.index(name)
    x, y = i % COLS, i // COLS
    return color[y * P:(y + 1) * P, x * P:(x + 1) * P]


def triangles(s, name):
    return np.flatnonzero(s.object_index == s.object_names.index(name))


@pytest.mark.parametrize("case", list(SHADER_CASES))
def test_albedo_matches_cycles_diffuse_color(reference, case):
    """Each shader and node chain's albedo (x its corner colours) is Cycles' Diffuse Color."""
    _, s, _ = reference
    cycles_value = patch(reference, case).reshape(-1, 3)
    assert cycles_value.std(axis=0).max() < 1e-4  # a constant per patch
    tri = triangles(s, case)
    mat = s.materials[s.material_index[tri[0]]]
    assert mat.texture is None
    # the covered part's colour x the coverage (hashed alpha): over nothing, the pass's mean
    ours = mat.albedo.astype(np.float64) * mat.alpha
    if s.corner_colors is not None:
        ours = ours * s.corner_colors[tri].reshape(-1, 3).mean(axis=0)
    assert np.allclose(ours, cycles_value.mean(axis=0), atol=5e-4), (
        case, ours, cycles_value.mean(axis=0))


@pytest.mark.parametrize("case", list(TEXTURE_CASES))
def test_image_texture_matches_cycles_per_texel(reference, case):
    """Texture x albedo at each quadrant's UV (Closest, REPEAT, read by hand from the
    extracted pixels and UVs) is Cycles' Diffuse Color there: colour space, alpha, row order
    and the Mapping node as Cycles applies them."""
    _, s, _ = reference
    block = patch(reference, case)
    tri = triangles(s, case)
    mat = s.materials[s.material_index[tri[0]]]
    tex = mat.texture
    assert tex is not None and tex.pixels.shape == (2, 2, 3) and tex.interpolation == "Closest"
    # The patch's UVs are affine in position: fit uv = A (x, y, 1) from the triangle corners.
    pos = s.positions[tri].reshape(-1, 3)
    uv = s.uvs[tri].reshape(-1, 2).astype(np.float64)
    design = np.c_[pos[:, :2], np.ones(len(pos))]
    fit, *_ = np.linalg.lstsq(design, uv, rcond=None)
    x0, y0 = pos[:, 0].min(), pos[:, 1].max()
    for r in range(2):  # image rows top-first
        for c in range(2):
            centre = np.array([x0 + 0.25 + 0.5 * c, y0 - 0.25 - 0.5 * r, 1.0])
            u, v = centre @ fit
            texel = tex.pixels[int(np.floor(v * 2)) % 2, int(np.floor(u * 2)) % 2]
            ours = mat.albedo * texel
            theirs = block[2 * r:2 * r + 2, 2 * c:2 * c + 2].reshape(-1, 3).mean(axis=0)
            assert np.allclose(ours, theirs, atol=1e-4), (case, r, c, ours, theirs)


# ------------------------------------------------------------ the view angle's share

VIEW_COS = (1.0, 0.65, 0.36, 0.12)  # off the measured grid but 1: the interpolation too
VIEW_CASES = {"principled": {}, "roughness 0.2 ior 2": {"Roughness": 0.2, "IOR": 2.0},
              "specular tint": {"Specular Tint": (1.0, 0.4, 0.2, 1.0), "IOR": 1.8},
              "coat 1": {"Coat Weight": 1.0},
              "coat rough ior 2": {"Coat Weight": 0.7, "Coat Roughness": 0.4, "Coat IOR": 2.0},
              "coat tint": {"Coat Weight": 1.0, "Coat Tint": (0.5, 1.0, 0.25, 1.0)},
              "sheen 1": {"Sheen Weight": 1.0},
              "sheen rough": {"Sheen Weight": 1.0, "Sheen Roughness": 1.0},
              "mix 0.3": mix_shader(0.3)}  # a Mix Shader of a Diffuse and a Principled
VP = 8  # pixels per patch side


@pytest.fixture(scope="module")
def view_reference(tmp_path_factory):
    """(Cycles' Diffuse Color, ours) (H, W, 3) of Principled patches (one row per
    VIEW_CASES: Principled inputs, or a builder) tilted to an orthographic camera so that each column is seen at VIEW_COS
    (each patch 1 / cos long, projecting to 1 x 1)."""
    from lpv_core import engine
    from lpv_core.render import deferred

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    for row, (name, inputs) in enumerate(VIEW_CASES.items()):
        mat, nt, out = new_material(f"view {name}")
        if callable(inputs):
            inputs(nt, out)
        else:
            p = principled(nt)
            for key, value in inputs.items():
                p.inputs[key].default_value = value
            to_surface(nt, out, p)
        for c, mu in enumerate(VIEW_COS):
            rise = float(np.sqrt(1.0 - mu * mu)) / mu  # normal (0, -sin, cos)
            me = bpy.data.meshes.new(f"{name} {mu}")
            me.from_pydata([(c, -row - 1, 0), (c + 1, -row - 1, 0), (c + 1, -row, rise),
                            (c, -row, rise)], [], [(0, 1, 2, 3)])
            me.materials.append(mat)
            scene.collection.objects.link(bpy.data.objects.new(me.name, me))
    cam = bpy.data.cameras.new("cam")
    # (the orthographic scale spans the image's longer side)
    cam.type, cam.ortho_scale = "ORTHO", max(len(VIEW_COS), len(VIEW_CASES))
    cam.clip_end = 100.0
    ob = bpy.data.objects.new("cam", cam)
    ob.location = (len(VIEW_COS) / 2, -len(VIEW_CASES) / 2, 50)
    scene.collection.objects.link(ob)
    scene.camera = ob
    res = (len(VIEW_COS) * VP, len(VIEW_CASES) * VP)
    path = tmp_path_factory.mktemp("view") / "diffuse_color.exr"
    cycles.render_cycles_passes(path, samples=16, resolution=res)
    core_scene = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), scene, res)
    eng = engine.Engine()
    ours = deferred.render(eng, core_scene, eng.update(core_scene))["Diffuse Color"]
    return exr.read_multilayer(path)["Diffuse Color"][..., :3], ours[..., :3], core_scene


@pytest.mark.parametrize("case", list(VIEW_CASES))
def test_diffuse_color_follows_the_view_angle_like_cycles(view_reference, case):
    """Each patch's Diffuse Color (its inner pixels) is Cycles' at its view angle: the
    Principled's specular and coat layers take more towards grazing, its sheen more, the coat
    tint absorbs more; the change from head-on is well beyond the tolerance, so one value per
    material fails."""
    theirs, ours, s = view_reference
    row = list(VIEW_CASES).index(case)
    inner = slice(2, VP - 2)
    for c in range(len(VIEW_COS)):
        t = theirs[row * VP:(row + 1) * VP, c * VP:(c + 1) * VP][inner, inner].reshape(-1, 3)
        o = ours[row * VP:(row + 1) * VP, c * VP:(c + 1) * VP][inner, inner].reshape(-1, 3)
        assert t.std(axis=0).max() < 1e-4
        # linear in the measured table (16 cosines x 9 roughnesses x 10 IORs): under 0.7 %
        assert np.allclose(o, t.mean(axis=0), rtol=7e-3, atol=1e-4), (case, VIEW_COS[c], o[0],
                                                                       t[0])
    head_on = theirs[row * VP + 4, 4]
    grazing = theirs[row * VP + 4, (len(VIEW_COS) - 1) * VP + 4]
    assert np.abs(head_on - grazing).max() > 0.02  # the effect the table carries
    mat = next(m for m in s.materials if m.name == f"view {case}")
    assert mat.diffuse_share is not None and mat.diffuse_share.shape == (16, 3)


# ------------------------------------------------------------------- extraction by hand


@pytest.fixture
def empty_file():
    bpy.ops.wm.read_homefile(use_empty=True)
    yield


def quad(name, mat=None):
    me = bpy.data.meshes.new(name)
    me.from_pydata([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], [], [(0, 1, 2, 3)])
    if mat is not None:
        me.materials.append(mat)
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def run():
    return extract.extract_scene(bpy.context.evaluated_depsgraph_get(), require_camera=False)


def test_color_attributes_give_per_corner_colours(empty_file):
    mat, nt, out = new_material("vc")
    attribute("bytes")(nt, out)
    ob = quad("q", mat)
    me = ob.data
    stored = np.array([[0.2, 0.4, 0.6, 1], [1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 1]], np.float32)
    byte = me.color_attributes.new("bytes", "BYTE_COLOR", "CORNER")
    byte.data.foreach_set("color_srgb", stored.ravel())  # bytes hold sRGB
    read = np.empty(16, np.float32)
    byte.data.foreach_get("color_srgb", read)
    srgb = read.reshape(4, 4)[:, :3].astype(np.float64)
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    s = run()
    loops = [[0, 1, 2], [0, 2, 3]]  # the quad's split (corner = loop = vertex here)
    got = s.corner_colors.reshape(-1, 3, 3)
    tri_loops = np.array(loops) if np.allclose(s.positions[0, 1, :2], [1, 0]) else None
    assert tri_loops is not None
    assert np.allclose(got, linear[tri_loops], atol=1e-5)
    # A POINT-domain float attribute, by name.
    pts = me.color_attributes.new("points", "FLOAT_COLOR", "POINT")
    pts.data.foreach_set("color", stored.ravel())
    bpy.data.materials["vc"].node_tree.nodes["Color Attribute"].layer_name = "points"
    assert np.allclose(run().corner_colors, stored[tri_loops, :3], atol=1e-6)
    # An untextured material: no per-corner arrays at all.
    ob.data.materials[0] = bpy.data.materials.new("plain")
    s = run()
    assert s.uvs is None and s.corner_colors is None


def test_image_texture_pixels_colour_space_and_mapping(empty_file):
    img = bpy.data.images.new("written", 3, 2)  # byte, sRGB
    values = np.arange(24, dtype=np.float32).reshape(2, 3, 4) / 23.0
    values[..., 3] = 1.0  # opaque: alpha is the Cycles comparison's
    img.pixels.foreach_set(values.ravel())
    stored = np.array(img.pixels[:], np.float64).reshape(2, 3, 4)[..., :3]
    mat, t = image_material("tex", img, Base_Color=(1, 1, 1, 1), Specular_IOR_Level=0.0)
    t.extension = "EXTEND"
    nt = mat.node_tree
    ob = quad("q", mat)
    ob.data.uv_layers.new(name="UVMap").uv.foreach_set("vector", [0, 0, 1, 0, 1, 1, 0, 1])
    s = run()
    tex = s.materials[0].texture
    srgb = np.where(stored <= 0.04045, stored / 12.92, ((stored + 0.055) / 1.055) ** 2.4)
    assert tex.pixels.shape == (2, 3, 3) and tex.extension == "EXTEND"
    assert np.allclose(tex.pixels, srgb, atol=1e-6)
    assert np.allclose(s.materials[0].albedo, 1.0)
    assert np.allclose(s.uvs[:, :, 0], s.positions[:, :, 0]) and np.allclose(
        s.uvs[:, :, 1], s.positions[:, :, 1])
    img.colorspace_settings.name = "Non-Color"  # regenerates a generated image: refill it
    img.pixels.foreach_set(values.ravel())
    assert np.allclose(run().materials[0].texture.pixels, stored, atol=1e-6)
    # A Mapping node (POINT): uv' = R(90 deg about Z) (scale x uv) + location.
    m = nt.nodes.new("ShaderNodeMapping")
    m.inputs["Location"].default_value = (0.5, 0.25, 0.0)
    m.inputs["Rotation"].default_value = (0.0, 0.0, np.pi / 2)
    m.inputs["Scale"].default_value = (2.0, 3.0, 1.0)
    nt.links.new(m.outputs["Vector"], t.inputs["Vector"])
    s = run()
    u, v = s.positions[..., 0], s.positions[..., 1]  # uv = xy on this quad
    assert np.allclose(s.uvs[..., 0], 0.5 - 3.0 * v, atol=1e-6)
    assert np.allclose(s.uvs[..., 1], 0.25 + 2.0 * u, atol=1e-6)


def test_missing_image_is_magenta_and_reported(empty_file, capfd):
    mat, _ = image_material("brick", missing_image("bricks"), Specular_IOR_Level=0.0)
    quad("wall", mat)
    s = run()
    assert np.allclose(s.materials[0].albedo, materials.MAGENTA) and s.materials[0].texture is None
    line = next(a for a in s.approximated if "bricks" in a)
    assert line.startswith("material 'brick': image 'bricks' is missing (")
    assert line.endswith("): magenta, as Cycles shows it") and "missing/bricks.png" in line
    assert "LPV GI: material 'brick': image 'bricks' is missing" in capfd.readouterr().err


def test_an_image_sequence_is_named_not_called_missing(empty_file, tmp_path):
    """An image sequence whose frames exist but are not loaded (Blender holds no pixels for
    it in a background process) is named as a sequence, not as a missing file."""
    still = bpy.data.images.new("frame", 2, 2)
    still.filepath_raw = str(tmp_path / "seq.0001.png")
    still.file_format = "PNG"
    still.save()
    bpy.data.images.remove(still)
    seq = bpy.data.images.load(str(tmp_path / "seq.0001.png"))
    seq.source = "SEQUENCE"
    mat, _ = image_material("screen", seq)
    quad("tv", mat)
    s = run()
    lines = [a for a in s.approximated if "seq.0001.png" in a]
    assert not seq.has_data  # Blender loads no frame of it here
    assert lines and "is an image sequence, whose frames are not read" in lines[0]
    assert "missing" not in lines[0]


def test_non_finite_node_values_are_counted_and_repaired(empty_file):
    mat, nt, out = new_material("nan")
    p = principled(nt)
    p.inputs["Base Color"].default_value = (float("nan"), 0.5, 0.5, 1.0)
    p.inputs["Emission Strength"].default_value = float("inf")
    p.inputs["Emission Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    to_surface(nt, out, p)
    quad("q", mat)
    s = run()
    m = s.materials[0]
    assert np.isfinite(m.albedo).all() and np.isfinite(m.emission).all()
    assert s.dropped["materials_with_invalid_values_defaulted"] == 1
    # A float image with a NaN and a negative texel, a colour attribute with a NaN corner.
    img = bpy.data.images.new("bad texels", 2, 1, float_buffer=True)
    img.pixels.foreach_set([np.nan, 0.5, 0.5, 1.0, -1.0, 0.25, 0.5, 1.0])
    tex_mat, _ = image_material("bad image", img)
    quad("t", tex_mat).data.uv_layers.new(name="UVMap")
    vc, nt, out = new_material("bad colours")
    attribute("Col")(nt, out)
    col = quad("c", vc).data.color_attributes.new("Col", "FLOAT_COLOR", "CORNER")
    col.data.foreach_set("color", [np.nan, 0, 0, 1] + [0.5, 0.5, 0.5, 1] * 3)
    s = run()
    tex = next(m for m in s.materials if m.name == "bad image").texture
    assert np.array_equal(tex.pixels.reshape(2, 3), [[0, 0.5, 0.5], [0, 0.25, 0.5]])
    assert s.dropped["texels_nonfinite_or_negative_defaulted"] == 2
    assert s.dropped["corner_colors_nonfinite_or_negative_defaulted"] == 1
    assert np.isfinite(s.corner_colors).all() and (s.corner_colors >= 0).all()
    assert any("'bad texels': 2 non-finite or negative texels" in a for a in s.approximated)


def test_texture_cache_rereads_only_the_changed_image(empty_file, tmp_path):
    images = []
    for k in range(3):
        img = bpy.data.images.new(f"im{k}", 8, 8)
        img.generated_color = (0.1 * k, 0.5, 0.5, 1.0)
        img.filepath_raw = str(tmp_path / f"im{k}.png")
        img.file_format = "PNG"
        img.save()
        images.append(img)
        mat, _ = image_material(f"m{k}", img)
        quad(f"q{k}", mat).data.uv_layers.new(name="UVMap")
    first = {m.name: m.texture for m in run().materials}
    again = {m.name: m.texture for m in run().materials}
    assert all(np.shares_memory(first[k].pixels, again[k].pixels) for k in first)
    images[1].scale(4, 4)  # changes the content (and marks it dirty)
    third = {m.name: m.texture for m in run().materials}
    assert np.shares_memory(first["m0"].pixels, third["m0"].pixels)
    assert np.shares_memory(first["m2"].pixels, third["m2"].pixels)
    assert third["m1"].pixels.shape == (4, 4, 3) and third["m1"].digest != first["m1"].digest


def test_large_images_are_resampled_to_the_budget():
    px = np.random.default_rng(1).random((2048, 1536, 4)).astype(np.float32)
    out = materials.resample_to_budget(px, materials.TEXTURE_BUDGET)
    assert out.shape == (1024, 768, 4)
    assert np.allclose(out[3, 5], px[6:8, 10:12].mean(axis=(0, 1)), atol=1e-6)
    assert materials.resample_to_budget(px[:1024, :1024], materials.TEXTURE_BUDGET).shape == (
        1024, 1024, 4)


def test_uvs_follow_the_corners_of_mirrored_instances(empty_file):
    """A mirrored object's corners are swapped to keep its winding: its UVs and colours move
    with them (uv = the local xy of each corner here)."""
    img = bpy.data.images.new("grid", 2, 2)
    mat, _ = image_material("tex", img)
    plain = quad("plain", mat)
    plain.data.uv_layers.new(name="UVMap").uv.foreach_set("vector", [0, 0, 1, 0, 1, 1, 0, 1])
    mirrored = bpy.data.objects.new("mirrored", plain.data)
    mirrored.scale = (-1.0, 1.0, 1.0)
    mirrored.location = (0.0, 0.0, 2.0)
    bpy.context.scene.collection.objects.link(mirrored)
    s = run()
    for name, sign in (("plain", 1.0), ("mirrored", -1.0)):
        tri = triangles(s, name)
        assert np.allclose(s.uvs[tri, :, 0], sign * s.positions[tri, :, 0], atol=1e-6), name
        assert np.allclose(s.uvs[tri, :, 1], s.positions[tri, :, 1], atol=1e-6), name
