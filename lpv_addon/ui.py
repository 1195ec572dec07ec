"""Panels: the "LPV" sidebar tab of the 3D viewport, GI sub-panels in the Light, Object and
Material properties, and the LPV GI engine's Render properties. With the engine picked,
Blender's engine-neutral panels and EEVEE's material, light and world panels show too."""

from __future__ import annotations

import textwrap

import bpy

from .render.frames import approximation_warnings
from .viewport import live

ENGINE = "LPV_GI"
# EEVEE's panels that also describe what LPV GI reads (surface nodes, light settings, world).
EEVEE_PANELS = ("EEVEE_MATERIAL_PT_context_material", "EEVEE_MATERIAL_PT_surface",
                "DATA_PT_EEVEE_light", "EEVEE_WORLD_PT_surface")


def compat_panels() -> list:
    """Blender's panels shown for LPV GI: those for every engine (BLENDER_RENDER in their
    COMPAT_ENGINES, as Cycles picks them) and ``EEVEE_PANELS``."""
    return [p for p in bpy.types.Panel.__subclasses__() if p.__name__ in EEVEE_PANELS
            or "BLENDER_RENDER" in getattr(p, "COMPAT_ENGINES", ())]


def warning_lines(stats: dict) -> list[str]:
    """What the LPV left out or approximated, one line each: dropped input (counts), light
    sources, shaders and images approximated (named), surfaces outside the LPV, spaces too
    small for its cells."""
    dropped = stats.get("dropped", {})
    lines = [f"left out: {n} {key.replace('_', ' ')}" for key, n in sorted(dropped.items()) if n]
    lines += approximation_warnings(stats.get("info", {}).get("approximated", []))
    return lines + [f"{s['what']}: {s['reason']}" for s in stats.get("skipped", [])
                    if s["stage"] in ("lpv", "resolution")]


def _props(context):
    scene = getattr(context, "scene", None)
    return getattr(scene, "lpv", None) if scene is not None else None


class LPV_UL_lights(bpy.types.UIList):
    """Lights of the scene with their GI intensity and tint."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname,
                  index=0, flt_flag=0):
        light = item.data
        row = layout.row(align=True)
        row.label(text=item.name, icon="LIGHT_" + light.type if light.type in
                  ("POINT", "SUN", "SPOT", "AREA") else "LIGHT")
        row.prop(light.lpv, "gi_intensity", text="")
        row.prop(light.lpv, "gi_color", text="")

    def filter_items(self, context, data, propname):
        items = getattr(data, propname)
        flags = [self.bitflag_filter_item if ob.type == "LIGHT" else 0 for ob in items]
        return flags, []


class LPV_UL_areas(bpy.types.UIList):
    """Empties used as GI areas."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname,
                  index=0, flt_flag=0):
        row = layout.row(align=True)
        row.label(text=item.name, icon="CUBE")
        row.prop(item.lpv, "area_type", text="")

    def filter_items(self, context, data, propname):
        items = getattr(data, propname)
        flags = [self.bitflag_filter_item
                 if ob.type == "EMPTY" and ob.lpv.area_type != "NONE" else 0 for ob in items]
        return flags, []


class _Sidebar:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "LPV"

    @classmethod
    def poll(cls, context):
        return _props(context) is not None


class LPV_PT_main(_Sidebar, bpy.types.Panel):
    bl_label = "LPV GI"

    def draw_header(self, context):
        self.layout.prop(_props(context), "enabled", text="")

    def draw(self, context):
        props = _props(context)
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = True  # keyframe dots: intensity is animatable
        layout.active = props.enabled
        layout.prop(props, "intensity")
        layout.prop(props, "world_gi")
        row = layout.row()
        row.active = props.world_gi
        row.prop(props, "world_gi_intensity")
        layout.prop(props, "quality")
        layout.prop(props, "show_overlay")
        col = layout.column()
        col.active = props.show_overlay
        col.prop(props, "overlay_mode")
        col.prop(props, "overlay_exposure")
        layout.prop(props, "live_update")
        layout.operator("lpv.update", icon="FILE_REFRESH")
        col = layout.column(align=True)
        for line in warning_lines(live.STATE.current.stats if live.STATE.current else {}):
            for i, part in enumerate(textwrap.wrap(line, 40)):
                col.label(text=part, icon="ERROR" if i == 0 else "BLANK1")


class LPV_PT_quality(_Sidebar, bpy.types.Panel):
    bl_label = "Quality"
    bl_parent_id = "LPV_PT_main"
    bl_options = {"DEFAULT_CLOSED"}  # noqa: RUF012 - Blender reads a set

    def draw(self, context):
        props = _props(context)
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        for name in ("grid_resolution", "cascades", "cascades_auto", "rsm_resolution",
                     "occlusion", "bounces", "backend", "antialias", "contact_light",
                     "refresh_interval",
                     "fade_time"):
            layout.prop(props, name)


class LPV_PT_lights(_Sidebar, bpy.types.Panel):
    bl_label = "Lights"
    bl_parent_id = "LPV_PT_main"

    def draw(self, context):
        scene = context.scene
        self.layout.template_list("LPV_UL_lights", "", scene, "objects", scene.lpv,
                                  "active_light_index", rows=3)


class LPV_PT_areas(_Sidebar, bpy.types.Panel):
    bl_label = "Areas"
    bl_parent_id = "LPV_PT_main"

    def draw(self, context):
        scene = context.scene
        layout = self.layout
        row = layout.row(align=True)
        row.operator("lpv.add_area", text="Clip", icon="ADD").type = "CLIP"
        row.operator("lpv.add_area", text="Transition", icon="ADD").type = "TRANSITION"
        layout.template_list("LPV_UL_areas", "", scene, "objects", scene.lpv,
                             "active_area_index", rows=2)
        index = scene.lpv.active_area_index
        if 0 <= index < len(scene.objects):
            ob = scene.objects[index]
            if ob.type == "EMPTY" and ob.lpv.area_type != "NONE":
                draw_area(layout, ob)


class LPV_PT_stats(_Sidebar, bpy.types.Panel):
    bl_label = "Statistics"
    bl_parent_id = "LPV_PT_main"
    bl_options = {"DEFAULT_CLOSED"}  # noqa: RUF012 - Blender reads a set

    def draw(self, context):
        col = self.layout.column(align=True)
        for line in live.stats_lines():
            col.label(text=line)


class LPV_PT_output(_Sidebar, bpy.types.Panel):
    bl_label = "Batch and Comparison"
    bl_parent_id = "LPV_PT_main"

    def draw(self, context):
        props = _props(context)
        layout = self.layout
        layout.prop(props, "batch_directory")
        row = layout.row(align=True)
        row.operator("lpv.render_batch", icon="RENDER_STILL")
        row.operator("lpv.render_batch", text="Animation",
                     icon="RENDER_ANIMATION").frames = "ANIMATION"
        row = layout.row(align=True)
        row.prop(props, "compare_resolution", text="Size")
        row.prop(props, "compare_samples", text="Samples")
        layout.operator("lpv.compare_cycles", icon="IMAGE_DATA")
        if props.compare_summary:
            layout.label(text=props.compare_summary)


class LPV_PT_render(bpy.types.Panel):
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    bl_label = "LPV GI"
    COMPAT_ENGINES = {ENGINE}  # noqa: RUF012 - Blender's panels read a set

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES and _props(context) is not None

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(_props(context), "quality")
        layout.prop(_props(context), "intensity")
        layout.prop(context.scene.render, "film_transparent")
        col = layout.column(heading="Passes")
        for name in ("direct", "indirect", "color"):
            col.prop(context.view_layer, f"use_pass_diffuse_{name}", text=f"Diffuse {name.title()}")


def draw_area(layout, ob) -> None:
    col = layout.column()
    col.use_property_split = True
    col.prop(ob.lpv, "area_type")
    sub = col.column()
    sub.active = ob.lpv.area_type == "TRANSITION"
    sub.prop(ob.lpv, "area_falloff")
    sub.prop(ob.lpv, "area_intensity")
    sub.prop(ob.lpv, "area_tint")


class _Properties:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_label = "LPV GI"


class LPV_PT_light(_Properties, bpy.types.Panel):
    bl_context = "data"

    @classmethod
    def poll(cls, context):
        return getattr(context, "light", None) is not None and hasattr(context.light, "lpv")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(context.light.lpv, "gi_intensity")
        layout.prop(context.light.lpv, "gi_color")


class LPV_PT_object(_Properties, bpy.types.Panel):
    bl_context = "object"

    @classmethod
    def poll(cls, context):
        ob = getattr(context, "object", None)
        return ob is not None and hasattr(ob, "lpv")

    def draw(self, context):
        ob = context.object
        layout = self.layout
        if ob.type == "EMPTY":
            draw_area(layout, ob)
            return
        layout.use_property_split = True
        col = layout.column(heading="GI")
        col.prop(ob.lpv, "gi_caster")
        col.prop(ob.lpv, "gi_occluder")
        col.prop(ob.lpv, "gi_receiver")


class LPV_PT_material(_Properties, bpy.types.Panel):
    bl_context = "material"

    @classmethod
    def poll(cls, context):
        mat = getattr(context, "material", None)
        return mat is not None and hasattr(mat, "lpv")

    def draw(self, context):
        props = context.material.lpv
        layout = self.layout
        layout.use_property_split = True
        layout.prop(props, "use_bleed_color")
        sub = layout.column()
        sub.active = props.use_bleed_color
        sub.prop(props, "bleed_color")
        layout.prop(props, "bleed_intensity")
        layout.prop(props, "emission_gi_intensity")


CLASSES = (
    LPV_UL_lights, LPV_UL_areas,
    LPV_PT_main, LPV_PT_quality, LPV_PT_lights, LPV_PT_areas, LPV_PT_stats, LPV_PT_output,
    LPV_PT_light, LPV_PT_object, LPV_PT_material, LPV_PT_render,
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for panel in compat_panels():
        panel.COMPAT_ENGINES.add(ENGINE)


def unregister() -> None:
    for panel in compat_panels():
        panel.COMPAT_ENGINES.discard(ENGINE)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
