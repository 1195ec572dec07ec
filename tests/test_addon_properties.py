"""Scene/Light/Object/Material.lpv in a real headless Blender: every property set, saved in the
.blend, reloaded, undone, keyframed, and carried by extraction into the core scene."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from lpv_addon import properties
from lpv_addon.scene_io import extract
from tools import scenes

pytestmark = pytest.mark.bpy

# Every property of ours with a non-default value to set.
SCENE_VALUES = {
    "enabled": True, "intensity": 2.5, "quality": "HIGH", "grid_resolution": 24,
    "cascades": 2, "cascades_auto": False, "rsm_resolution": 128, "occlusion": True, "bounces": 2,
    "backend": "gl", "antialias": 3, "contact_light": False, "live_update": False,
    "refresh_interval": 0.5, "fade_time": 1.25,
    "show_overlay": False, "overlay_mode": "PROBES", "overlay_exposure": -1.5,
    "batch_directory": "//frames_out/", "compare_resolution": 48, "compare_samples": 16,
    "compare_summary": "x", "active_light_index": 2, "active_area_index": 1,
    "world_gi": False, "world_gi_intensity": 0.5,
}
LIGHT_VALUES = {"gi_intensity": -0.75, "gi_color": (0.2, 0.4, 0.9)}
OBJECT_VALUES = {"gi_caster": False, "gi_occluder": False, "gi_receiver": False,
                 "area_type": "TRANSITION", "area_falloff": 0.8, "area_intensity": 3.0,
                 "area_tint": (1.0, 0.5, 0.25)}
MATERIAL_VALUES = {"use_bleed_color": True, "bleed_color": (0.1, 0.7, 0.1),
                   "bleed_intensity": 1.5, "emission_gi_intensity": 0.5}


@pytest.fixture(scope="module", autouse=True)
def addon(registered_addon):
    """Every test here runs with the add-on registered (conftest.registered_addon)."""


@pytest.fixture()
def box():
    scenes.cornell_box("SPOT", resolution=(32, 32))
    return bpy.context.scene


def _set_all(scene):
    # quality last-but-one: setting a preset overwrites grid/RSM settings, so set it first.
    props = scene.lpv
    props.quality = SCENE_VALUES["quality"]
    for k, v in SCENE_VALUES.items():
        if k != "quality":
            setattr(props, k, v)
    light = bpy.data.lights["Spot"]
    for k, v in LIGHT_VALUES.items():
        setattr(light.lpv, k, v)
    ob = bpy.data.objects["TallBlock"]
    for k, v in OBJECT_VALUES.items():
        setattr(ob.lpv, k, v)
    mat = bpy.data.materials["White"]
    for k, v in MATERIAL_VALUES.items():
        setattr(mat.lpv, k, v)


def _check_all(scene):
    def same(a, b):
        if isinstance(b, tuple):
            return np.allclose(tuple(a), b, atol=1e-6)
        if isinstance(b, float):
            return math.isclose(a, b, abs_tol=1e-6)
        return a == b

    expect = dict(SCENE_VALUES, quality="CUSTOM")  # hand-edited settings left the preset
    for owner, values in ((scene.lpv, expect), (bpy.data.lights["Spot"].lpv, LIGHT_VALUES),
                          (bpy.data.objects["TallBlock"].lpv, OBJECT_VALUES),
                          (bpy.data.materials["White"].lpv, MATERIAL_VALUES)):
        for k, v in values.items():
            assert same(getattr(owner, k), v), (k, getattr(owner, k), v)


def test_every_property_exists_with_the_issue_names():
    for owner, names in ((bpy.types.Scene, SCENE_VALUES), (bpy.types.Light, LIGHT_VALUES),
                         (bpy.types.Object, OBJECT_VALUES),
                         (bpy.types.Material, MATERIAL_VALUES)):
        rna = owner.bl_rna.properties["lpv"].fixed_type.properties
        for name in names:
            assert name in rna, (owner.__name__, name)
    # Every property we define is covered by the values above (nothing left untested).
    for owner, names in ((properties.LPVSceneSettings, SCENE_VALUES),
                         (properties.LPVLightSettings, LIGHT_VALUES),
                         (properties.LPVObjectSettings, OBJECT_VALUES),
                         (properties.LPVMaterialSettings, MATERIAL_VALUES)):
        ours = {p.identifier for p in owner.bl_rna.properties} - {"rna_type", "name"}
        assert ours == set(names), (owner.__name__, ours ^ set(names))


def test_every_property_is_saved_in_the_blend(box, tmp_path):
    _set_all(box)
    _check_all(box)
    path = tmp_path / "props.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True)
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.context.scene.lpv.intensity == 1.0
    bpy.ops.wm.open_mainfile(filepath=str(path))
    _check_all(bpy.context.scene)


def test_properties_survive_undo(box):
    bpy.ops.ed.undo_push(message="before")
    box.lpv.intensity = 3.0
    bpy.data.lights["Spot"].lpv.gi_intensity = 0.25
    bpy.data.objects["Floor"].lpv.gi_receiver = False
    bpy.ops.ed.undo_push(message="after")
    bpy.ops.ed.undo()
    scene = bpy.context.scene
    assert scene.lpv.intensity == 1.0
    assert bpy.data.lights["Spot"].lpv.gi_intensity == 1.0
    assert bpy.data.objects["Floor"].lpv.gi_receiver
    bpy.ops.ed.redo()
    assert bpy.context.scene.lpv.intensity == 3.0
    assert bpy.data.lights["Spot"].lpv.gi_intensity == 0.25
    assert not bpy.data.objects["Floor"].lpv.gi_receiver


def test_quality_presets_set_the_settings(box):
    props = box.lpv
    for name, (_, _, values) in properties.PRESETS.items():
        props.quality = name
        assert {k: getattr(props, k) for k in values} == values
        assert props.quality == name
    props.rsm_resolution = 333
    assert props.quality == "CUSTOM"


def test_art_direction_properties_are_animatable(box):
    light = bpy.data.lights["Spot"]
    mat = bpy.data.materials["White"]
    empty = bpy.data.objects.new("Area", None)
    box.collection.objects.link(empty)
    keyed = [(box.lpv, "intensity", 0.5, 2.0), (light.lpv, "gi_intensity", 1.0, -1.0),
             (mat.lpv, "bleed_intensity", 1.0, 3.0), (empty.lpv, "area_intensity", 1.0, 4.0),
             (empty.lpv, "area_falloff", 0.5, 2.0)]
    for owner, name, a, b in keyed:
        setattr(owner, name, a)
        assert owner.keyframe_insert(name, frame=1)
        setattr(owner, name, b)
        assert owner.keyframe_insert(name, frame=11)
    for owner, name in ((light.lpv, "gi_color"), (mat.lpv, "bleed_color"),
                        (empty.lpv, "area_tint")):
        assert owner.keyframe_insert(name, frame=1)
    for owner, name, a, b in keyed:
        assert owner.bl_rna.properties[name].is_animatable
    box.frame_set(11)
    for owner, name, _a, b in keyed:
        assert getattr(owner, name) == pytest.approx(b)
    box.frame_set(1)
    for owner, name, a, _b in keyed:
        assert getattr(owner, name) == pytest.approx(a)


def _core(scene):
    return extract.extract_scene(bpy.context.evaluated_depsgraph_get(), scene,
                                 require_camera=False)


def test_extraction_carries_object_flags(box):
    plain = _core(box)
    assert plain.caster is None and plain.occluder is None and plain.receiver is None
    bpy.data.objects["TallBlock"].lpv.gi_caster = False
    bpy.data.objects["Floor"].lpv.gi_receiver = False
    bpy.data.objects["ShortBlock"].lpv.gi_occluder = False
    s = _core(box)
    names = np.array(s.object_names)[s.object_index]
    np.testing.assert_array_equal(s.flag("caster"), names != "TallBlock")
    np.testing.assert_array_equal(s.flag("receiver"), names != "Floor")
    np.testing.assert_array_equal(s.flag("occluder"), names != "ShortBlock")
    # Non-casters reflect nothing into GI; their albedo (shading) is unchanged.
    refl = s.reflectance_per_triangle()
    assert refl[names == "TallBlock"].max() == 0 and refl[names != "TallBlock"].min() > 0
    np.testing.assert_array_equal(s.albedo_per_triangle(), plain.albedo_per_triangle())


def test_extraction_carries_material_bleed_and_light_tint(box):
    green = bpy.data.materials["Green"]
    green.lpv.use_bleed_color = True
    green.lpv.bleed_color = (0.9, 0.1, 0.2)
    green.lpv.bleed_intensity = 2.0
    green.lpv.emission_gi_intensity = 0.25
    bpy.data.materials["Red"].lpv.bleed_intensity = 0.5  # no bleed colour: scales albedo
    light = bpy.data.lights["Spot"]
    light.lpv.gi_intensity = -0.5
    light.lpv.gi_color = (1.0, 0.5, 0.0)
    s = _core(box)
    mats = {m.name: m for m in s.materials}
    np.testing.assert_allclose(mats["Green"].gi_reflectance(), [1.8, 0.2, 0.4], rtol=1e-6)
    np.testing.assert_allclose(mats["Red"].gi_reflectance(),
                               0.5 * np.array(scenes.RED, np.float32), rtol=1e-5)
    assert mats["White"].bleed_color is None
    assert mats["Green"].emission_gi_intensity == 0.25 and mats["Red"].emission_gi_intensity == 1
    (lamp,) = s.lights
    assert lamp.gi_intensity == -0.5
    np.testing.assert_allclose(lamp.gi_color, [1.0, 0.5, 0.0])


def test_extraction_reads_areas_from_empties(box):
    def empty(name, kind, loc, size, display="CUBE", hide=False):
        ob = bpy.data.objects.new(name, None)
        ob.empty_display_type = display
        ob.empty_display_size = size
        ob.location = loc
        ob.rotation_euler = (0.0, 0.0, math.radians(30))
        ob.scale = (2.0, 1.0, 0.5)
        ob.lpv.area_type = kind
        ob.hide_render = hide
        box.collection.objects.link(ob)
        return ob

    clip = empty("Clip", "CLIP", (0.5, 0.0, 1.0), 0.5)
    clip.lpv.area_falloff = 0.3
    tr = empty("Glow", "TRANSITION", (-0.5, 0.2, 0.4), 1.5)
    tr.lpv.area_intensity, tr.lpv.area_falloff, tr.lpv.area_tint = 2.0, 0.7, (1, 0.5, 0.5)
    empty("Plain", "NONE", (0, 0, 0), 1.0)
    empty("Hidden", "CLIP", (0, 0, 0), 1.0, hide=True)
    s = _core(box)
    got = {a.name: a for a in s.areas}
    assert set(got) == {"Clip", "Glow"}
    assert got["Clip"].type == "CLIP" and got["Glow"].type == "TRANSITION"
    g = got["Glow"]
    assert (g.falloff, g.intensity) == (pytest.approx(0.7), pytest.approx(2.0))
    np.testing.assert_allclose(g.tint, [1, 0.5, 0.5])
    # The box is the Empty's cube display: corner (1,1,1) maps to matrix_world @ (size,...).
    expect = np.array(tr.matrix_world) @ np.array([1.5, 1.5, 1.5, 1.0])
    np.testing.assert_allclose(g.matrix @ np.array([1, 1, 1, 1.0]), expect, atol=1e-6)
    from lpv_core import areas

    assert areas.inside(got["Clip"], [(0.5, 0.0, 1.0)])[0]
    assert not areas.inside(got["Clip"], [(0.5, 0.0, 1.3)])[0]  # z half-size 0.25


def test_keyframed_intensity_is_read_per_frame_from_the_original_scene(box):
    box.lpv.intensity = 1.0
    box.lpv.keyframe_insert("intensity", frame=1)
    box.lpv.intensity = 5.0
    box.lpv.keyframe_insert("intensity", frame=5)
    for frame, want in ((1, 1.0), (5, 5.0)):
        box.frame_set(frame)
        s = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), box)
        assert s.settings.intensity == pytest.approx(want)


def test_every_panel_draws_existing_properties(box):
    """Each panel's real draw() code against the demo scene's data. Blender cannot draw UI
    without a window, so the layout is the guide tool's recorder (it looks every drawn
    property up in RNA and reads its value; a misspelt name raises)."""
    from tools.make_user_guide_images import panel_records, panels_text

    records = panel_records(box)
    text = panels_text(records)
    where = [w for w, _ in records]
    assert sum(w.startswith("3D Viewport > Sidebar > LPV") for w in where) == 6
    for label in ("Properties > Light (Object Data)", "Properties > Object",
                  "Properties > Material"):
        assert label in where
    for needle in ("Intensity", "GI Intensity", "Caster", "Occluder", "Receiver",
                   "Use Bleed Color", "Bleed Intensity", "GI Area", "Falloff",
                   "[ Render Batch ]", "[ Compare with Cycles ]", "[ Update LPV ]",
                   "| Spot", "| LPV Clip Area"):
        assert needle in text, needle


# --------------------------------------------------------------------------------------------
# Artist-facing polish (issue 20.5): tooltips, names, ranges, off by default
# --------------------------------------------------------------------------------------------

GROUPS = (properties.LPVSceneSettings, properties.LPVLightSettings,
          properties.LPVObjectSettings, properties.LPVMaterialSettings)
INTERNAL = re.compile(r"numpy|moderngl|lpv_core|GISettings|Engine|LPVResult|\w+_\w+|"
                      r"\b[a-z]+[A-Z]\w*|[A-Z][a-z]+[A-Z]\w*")  # code names, snake/camel case


def _ours(cls):
    return [p for p in cls.bl_rna.properties if p.identifier not in ("rna_type", "name")]


def _tooltips():
    """(where, text) of every tooltip: our properties, their enum items, our operators."""
    from lpv_addon import operators

    out = []
    for cls in GROUPS:
        for p in _ours(cls):
            out.append((f"{cls.__name__}.{p.identifier}", p.description))
            if p.type == "ENUM":
                out += [(f"{cls.__name__}.{p.identifier}:{i.identifier}", i.description)
                        for i in p.enum_items]
    for op in operators.CLASSES:  # the tooltip Blender shows (from the class docstring)
        group, name = op.bl_idname.split(".")
        out.append((op.bl_idname, getattr(getattr(bpy.ops, group), name).get_rna_type()
                    .description))
    return out


def test_every_property_and_operator_has_a_one_line_tooltip_in_artist_language():
    tips = _tooltips()
    assert len(tips) > 50
    for where, text in tips:
        assert text and text == text.strip() and "\n" not in text and "  " not in text, where
        assert len(text) <= 100, (where, len(text))
        assert not INTERNAL.search(text), (where, INTERNAL.search(text).group())


def test_no_two_of_our_settings_share_a_name():
    names = [p.name for cls in GROUPS for p in _ours(cls)]
    assert len(names) == len(set(names)), sorted(n for n in names if names.count(n) > 1)
    assert "Intensity" not in names


def test_preset_tooltips_quote_only_figures_the_report_measured():
    report = (Path(__file__).resolve().parents[1] / "docs/report/README.md").read_text()
    for name, (_, tip, _) in properties.PRESETS.items():
        for figure in re.findall(r"\d+\.\d+", tip):
            assert re.search(rf"(?<![\d.]){re.escape(figure)}(?![\d])", report), (name, figure)


def test_ui_ranges_are_the_core_setting_ranges():
    """What the UI offers runs: each GI setting's property has the core's range (the largest
    grid is the largest the memory guard admits), each choice is a known one."""
    from lpv_core.scene import model

    rna = properties.LPVSceneSettings.bl_rna.properties
    checked = 0
    for key in model.SETTING_RANGES:
        if key not in rna:
            continue
        allowed, p = model.setting_range(key), rna[key]
        if p.type == "ENUM":
            assert {i.identifier for i in p.enum_items} == set(allowed), key
        elif allowed is not None:
            assert (p.hard_min, p.hard_max) == pytest.approx(allowed), key
        checked += 1
    assert checked >= 8
    assert rna["grid_resolution"].hard_max == model.max_grid_resolution()


def test_lpv_gi_is_off_in_a_new_file(box):
    bpy.ops.wm.read_homefile(use_empty=True)
    assert bpy.context.scene.lpv.enabled is False
    assert bpy.data.scenes.new("Another").lpv.enabled is False
