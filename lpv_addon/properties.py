"""Our Blender properties: Scene.lpv, Light.lpv, Object.lpv and Material.lpv.

The names are stable (scripts, tests and the batch CLI rely on them). Everything lives in
PropertyGroups on IDs, so it is saved in the .blend, survives undo, and every float, colour and
bool is animatable (keyframes, drivers). The batch renderer reads animated values per frame.
Edits through the UI or Python call ``live.mark_dirty`` so the live viewport refreshes.
"""

import bpy
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from ._core import core
from .presets import SETTINGS as PRESET_SETTINGS
from .viewport import live

# Quality presets: name -> (label, description, settings).
PRESETS = {
    "DRAFT": ("Draft", "12^3 grid, 128^2 RSM: fastest (Cornell box indirect error 0.17)",
        PRESET_SETTINGS["DRAFT"]),
    "PREVIEW": ("Preview", "16^3 grid, 256^2 RSM: the default (Cornell box indirect error 0.19)",
        PRESET_SETTINGS["PREVIEW"]),
    "HIGH": ("High", ("24^3 grid, 512^2 RSM: 3-5x Preview's time; finer cells, less error "
                      "(point-lit room 0.11, sunlit room 0.34)"),
        PRESET_SETTINGS["HIGH"]),
}
_APPLYING_PRESET = [False]
# Defaults follow the core's GISettings, so the add-on and scripts start from the same place.
_CORE = core.scene.GISettings()
_DEFAULT_QUALITY = next((k for k, v in PRESETS.items()
                         if all(getattr(_CORE, n) == x for n, x in v[2].items())), "CUSTOM")
# Blender 4.5+ warns about "//" in path properties unless they declare support for it.
PATH_OPTIONS = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 5, 0) else set()

OVERLAY_MODES = [
    ("ADD", "Add Indirect", "Add the LPV's indirect light on top of the viewport shading", 0),
    ("INDIRECT", "Indirect Only", "Show only the indirect light (black where there is none)", 1),
    ("CASCADES", "Cascade Bounds", "Debug: the LPV grid bounds of each cascade", 2),
    ("VPLS", "VPLs", "Debug: a sample of the virtual point lights, coloured by flux", 3),
    ("PROBES", "SH Probes", "Debug: the LPV cells' intensity as spherical-harmonics glyphs", 4),
    ("OCCLUSION", "Occlusion Volume", "Debug: the geometry volume's blocking potential", 5),
]

AREA_TYPES = [
    ("NONE", "None", "Not a GI area", 0),
    ("CLIP", "Clip", "Light does not propagate across this box's boundary", 1),
    ("TRANSITION", "Transition",
     "GI inside this box is scaled and tinted, blending into its surroundings", 2),
]


def _changed(self, context) -> None:
    """Any LPV property changed through the UI or Python: refresh the live viewport."""
    live.mark_dirty(f"{type(self).__name__}")


def _quality_changed(self, context) -> None:
    preset = PRESETS.get(self.quality)
    if preset is not None:
        _APPLYING_PRESET[0] = True
        try:
            for key, value in preset[2].items():
                setattr(self, key, value)
        finally:
            _APPLYING_PRESET[0] = False
    _changed(self, context)


def _setting_changed(self, context) -> None:
    """A quality setting edited by hand: the preset becomes Custom unless it still matches."""
    preset = PRESETS.get(self.quality)
    if not _APPLYING_PRESET[0] and preset is not None \
            and any(getattr(self, k) != v for k, v in preset[2].items()):
        self.quality = "CUSTOM"
    _changed(self, context)


class LPVSceneSettings(bpy.types.PropertyGroup):
    """Scene-wide LPV GI settings."""

    enabled: BoolProperty(
        name="Enabled", default=True, update=_changed,
        description="Compute LPV GI (live viewport, batch and comparison)",
    )
    intensity: FloatProperty(
        name="Intensity", default=1.0, min=0.0, soft_max=4.0, update=_changed,
        description="Global GI multiplier (keyframable: the batch reads it per frame)",
    )
    quality: EnumProperty(
        name="Quality", update=_quality_changed, default=_DEFAULT_QUALITY,
        items=[(k, v[0], v[1]) for k, v in PRESETS.items()]
        + [("CUSTOM", "Custom", "Settings edited by hand")],
        description="Quality preset: sets grid and RSM resolution",
    )
    grid_resolution: IntProperty(name="Grid Resolution", default=_CORE.grid_resolution, min=4,
                                 max=128,
                                 update=_setting_changed,
                                 description="Cells per side of each LPV cascade")
    cascades: IntProperty(name="Cascades", default=_CORE.cascades, min=1, max=4,
                          update=_setting_changed,
                          description=("Nested LPV grids, cell size doubling: at most this many "
                                       "with Auto Cascades, else exactly"))
    cascades_auto: BoolProperty(
        name="Auto Cascades", default=_CORE.cascades_auto, update=_setting_changed,
        description=("Use as many cascades as the view needs: one when the camera is inside a "
                     "closed space, more when it sees open ground stretching far from it"))
    rsm_resolution: IntProperty(name="RSM Resolution", default=_CORE.rsm_resolution, min=16,
                                max=2048,
                                update=_setting_changed,
                                description="Reflective shadow map size per light view")
    antialias: IntProperty(
        name="Anti-Aliasing", default=_CORE.antialias, min=1, max=4, update=_changed,
        description=("Samples per pixel side of a rendered frame (batch and compare renders): "
                     "each pass averages the pixel's area, as Cycles' pixel filter does"))
    occlusion: BoolProperty(name="Occlusion", default=_CORE.occlusion, update=_changed,
                            description="Block propagation with the geometry volume")
    bounces: IntProperty(name="Bounces", default=_CORE.bounces, min=1, max=8, update=_changed,
                         description="Indirect bounces")
    backend: EnumProperty(
        name="Backend", update=_changed,
        items=[("auto", "Auto", "The faster backend per stage, measured on this machine"),
               ("numpy", "NumPy", "CPU arrays"), ("gl", "OpenGL", "moderngl compute shaders")],
        default=_CORE.backend if _CORE.backend in ("auto", "numpy", "gl") else "numpy",
    )
    # Live viewport
    live_update: BoolProperty(name="Live Update", default=True, update=_changed,
                              description="Recompute the LPV while you edit the scene")
    refresh_interval: FloatProperty(
        name="Refresh Interval", default=0.25, min=0.02, max=10.0, subtype="TIME_ABSOLUTE",
        unit="TIME_ABSOLUTE", description="Seconds between live LPV updates",
    )
    fade_time: FloatProperty(
        name="Fade-in Time", default=0.3, min=0.0, max=10.0, subtype="TIME_ABSOLUTE",
        unit="TIME_ABSOLUTE", description="Seconds over which a new LPV result fades in",
    )
    show_overlay: BoolProperty(name="Show Overlay", default=True, update=_changed,
                               description="Draw LPV GI in the 3D viewport")
    overlay_mode: EnumProperty(name="Overlay", items=OVERLAY_MODES, default="ADD",
                               update=_changed, description="What the viewport overlay shows")
    overlay_exposure: FloatProperty(
        name="Overlay Exposure", default=0.0, soft_min=-8.0, soft_max=8.0,
        description="Overlay brightness in stops (display only, not the GI itself)",
    )
    # Batch and comparison
    batch_directory: StringProperty(
        name="Output", subtype="DIR_PATH", default="", options=PATH_OPTIONS,
        description="Folder for batch-rendered EXR frames and stats.json (empty: the scene's "
                    "render output path)",
    )
    compare_resolution: IntProperty(
        name="Compare Resolution", default=64, min=8, max=1024,
        description="Width of the Cycles comparison render (height follows the aspect)",
    )
    compare_samples: IntProperty(name="Compare Samples", default=64, min=1, max=65536,
                                 description="Cycles samples for the comparison render")
    compare_summary: StringProperty(name="Last Comparison", default="",
                                    description="Result of the last Cycles comparison")
    # UI list state
    active_light_index: IntProperty(name="Active Light", default=0, min=0)
    active_area_index: IntProperty(name="Active Area", default=0, min=0)


class LPVLightSettings(bpy.types.PropertyGroup):
    """Per-light GI controls."""

    gi_intensity: FloatProperty(
        name="GI Intensity", default=1.0, soft_min=-2.0, soft_max=4.0, min=-100.0, max=100.0,
        update=_changed,
        description="Multiplier of this light's bounce (0: no GI; negative: subtracts light)",
    )
    gi_color: FloatVectorProperty(
        name="GI Color", subtype="COLOR", size=3, default=(1.0, 1.0, 1.0), min=0.0,
        soft_max=1.0, update=_changed, description="Tint of this light's bounced light",
    )


class LPVObjectSettings(bpy.types.PropertyGroup):
    """Per-object GI flags, and GI area settings for Empties."""

    gi_caster: BoolProperty(name="Caster", default=True, update=_changed,
                            description="Bounces light into GI (off: still casts shadows)")
    gi_occluder: BoolProperty(name="Occluder", default=True, update=_changed,
                              description="Blocks light propagation (with occlusion on)")
    gi_receiver: BoolProperty(name="Receiver", default=True, update=_changed,
                              description="Receives indirect light")
    area_type: EnumProperty(name="GI Area", items=AREA_TYPES, default="NONE", update=_changed,
                            description="Use this Empty's box as a GI area")
    area_falloff: FloatProperty(
        name="Falloff", default=0.5, min=0.0, soft_max=10.0, subtype="DISTANCE", unit="LENGTH",
        update=_changed, description="Distance over which a transition area blends out",
    )
    area_intensity: FloatProperty(name="Intensity", default=1.0, min=0.0, soft_max=4.0,
                                  update=_changed,
                                  description="GI multiplier inside a transition area")
    area_tint: FloatVectorProperty(
        name="Tint", subtype="COLOR", size=3, default=(1.0, 1.0, 1.0), min=0.0, soft_max=1.0,
        update=_changed, description="GI tint inside a transition area",
    )


class LPVMaterialSettings(bpy.types.PropertyGroup):
    """What a material bounces into GI, without touching its shading."""

    use_bleed_color: BoolProperty(
        name="Use Bleed Color", default=False, update=_changed,
        description="Bounce this colour into GI instead of the material's albedo",
    )
    bleed_color: FloatVectorProperty(
        name="Bleed Color", subtype="COLOR", size=3, default=(0.8, 0.8, 0.8), min=0.0,
        soft_max=1.0, update=_changed, description="Colour this material bounces into GI",
    )
    bleed_intensity: FloatProperty(
        name="Bleed Intensity", default=1.0, min=0.0, soft_max=4.0, update=_changed,
        description="Strength of this material's bounce (multiplies albedo or bleed colour)",
    )


CLASSES = (LPVSceneSettings, LPVLightSettings, LPVObjectSettings, LPVMaterialSettings)
POINTERS = (
    (bpy.types.Scene, LPVSceneSettings),
    (bpy.types.Light, LPVLightSettings),
    (bpy.types.Object, LPVObjectSettings),
    (bpy.types.Material, LPVMaterialSettings),
)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    for owner, cls in POINTERS:
        owner.lpv = PointerProperty(type=cls)


def unregister() -> None:
    for owner, _ in reversed(POINTERS):
        if hasattr(owner, "lpv"):
            del owner.lpv
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
