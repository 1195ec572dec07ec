"""Panels: the "LPV" sidebar tab of the 3D viewport and GI sub-panels in the Light, Object and
Material properties."""

from __future__ import annotations

import bpy

from .viewport import live


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
        layout.prop(props, "quality")
        layout.prop(props, "show_overlay")
        col = layout.column()
        col.active = props.show_overlay
        col.prop(props, "overlay_mode")
        col.prop(props, "overlay_exposure")
        layout.prop(props, "live_update")
        layout.operator("lpv.update", icon="FILE_REFRESH")


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
                     "occlusion", "bounces", "backend", "antialias", "refresh_interval",
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
        layout.operator("lpv.render_batch", icon="RENDER_ANIMATION")
        row = layout.row(align=True)
        row.prop(props, "compare_resolution", text="Size")
        row.prop(props, "compare_samples", text="Samples")
        layout.operator("lpv.compare_cycles", icon="IMAGE_DATA")
        if props.compare_summary:
            layout.label(text=props.compare_summary)


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


CLASSES = (
    LPV_UL_lights, LPV_UL_areas,
    LPV_PT_main, LPV_PT_quality, LPV_PT_lights, LPV_PT_areas, LPV_PT_stats, LPV_PT_output,
    LPV_PT_light, LPV_PT_object, LPV_PT_material,
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
