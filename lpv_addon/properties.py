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

# Quality presets: name -> (label, description, settings). Figures only where the report
# (docs/report/README.md) measured the preset: Preview is its "LPV defaults" column.
PRESETS = {
    "DRAFT": ("Draft", "16^3 grid, 128^2 light maps: the fastest, coarsest bounced light",
              PRESET_SETTINGS["DRAFT"]),
    "PREVIEW": ("Preview", ("The default, 32^3 grid and 256^2 light maps: indirect error 0.14 "
                            "to 0.458 on the report's scenes"),
                PRESET_SETTINGS["PREVIEW"]),
    "HIGH": ("High", ("48^3 grid, 512^2 light maps: finer bounced light in large open scenes, "
                       "slower than Preview"),
             PRESET_SETTINGS["HIGH"]),
}
_APPLYING_PRESET = [False]
# Defaults follow the core's GISettings, so the add-on and scripts start from the same place.
_CORE = core.scene.GISettings()
_DEFAULT_QUALITY = next((k for k, v in PRESETS.items()
                         if all(getattr(_CORE, n) == x for n, x in v[2].items())), "CUSTOM")


def _limits(key: str) -> dict:
    """min/max of a GI setting's property: the core's range (only what can run)."""
    lo, hi = core.scene.model.setting_range(key)
    return {"min": lo, "max": hi}


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
        name="Enabled", default=False, update=_changed,
        description="Turn LPV GI on for this scene (off in every file until you turn it on)",
    )
    intensity: FloatProperty(
        name="GI Intensity", default=1.0, soft_max=4.0, update=_changed, **_limits("intensity"),
        description="Brightness of all bounced light in the scene (keyframe it to fade GI)",
    )
    world_gi: BoolProperty(
        name="World GI", default=True, update=_changed,
        description="Light the scene with the World (colour, sky or HDRI); off: the camera "
                    "still sees it",
    )
    world_gi_intensity: FloatProperty(
        name="World GI Intensity", default=1.0, soft_max=4.0, update=_changed,
        **_limits("intensity"),
        description="Brightness of the World's light on the scene (keyframe it to fade the "
                    "sky)",
    )
    quality: EnumProperty(
        name="Quality", update=_quality_changed, default=_DEFAULT_QUALITY,
        items=[(k, v[0], v[1]) for k, v in PRESETS.items()]
        + [("CUSTOM", "Custom", "Grid and light map resolution set by hand")],
        description="Quality preset: sets the grid and light map resolution",
    )
    grid_resolution: IntProperty(
        name="Grid Resolution", default=_CORE.grid_resolution, update=_setting_changed,
        **_limits("grid_resolution"),
        description="Cells along each side of the GI grid: finer is sharper but much slower")
    cascades: IntProperty(
        name="Cascades", default=_CORE.cascades, update=_setting_changed, **_limits("cascades"),
        description="Nested GI grids, each with cells half the size: finer light near the view")
    cascades_auto: BoolProperty(
        name="Auto Cascades", default=_CORE.cascades_auto, update=_setting_changed,
        description="Use only the cascades the view needs: one inside a room, more for open views")
    rsm_resolution: IntProperty(
        name="RSM Resolution", default=_CORE.rsm_resolution, update=_setting_changed,
        **_limits("rsm_resolution"),
        description="Size of the light map each light sees the scene with: finer lit detail")
    antialias: IntProperty(
        name="Anti-Aliasing", default=_CORE.antialias, update=_changed, **_limits("antialias"),
        description="Samples per pixel side of rendered frames: smoother edges and sky light, "
                    "longer renders")
    contact_light: BoolProperty(
        name="Contact Light", default=_CORE.contact_light, update=_changed,
        description="Renders add the bounce from surfaces nearer than a cell (not the overlay)")
    occlusion: BoolProperty(name="Occlusion", default=_CORE.occlusion, update=_changed,
                            description="Let objects block bounced light (no light through walls)")
    bounces: IntProperty(name="Bounces", default=_CORE.bounces, update=_changed,
                         **_limits("bounces"),
                         description="Times light bounces between surfaces: each adds time")
    backend: EnumProperty(
        name="Backend", update=_changed, default=_CORE.backend,
        items=[("auto", "Auto", "The faster of processor and graphics card on this computer"),
               ("numpy", "CPU", "Compute on the processor"),
               ("gl", "GPU (OpenGL)", "Compute on the graphics card")],
        description="Where LPV GI is computed",
    )
    # Live viewport
    live_update: BoolProperty(name="Live Update", default=True, update=_changed,
                              description="Recompute bounced light while you edit the scene")
    refresh_interval: FloatProperty(
        name="Refresh Interval", default=0.25, min=0.02, max=10.0, subtype="TIME_ABSOLUTE",
        unit="TIME_ABSOLUTE", description="Seconds between updates of the viewport's GI",
    )
    fade_time: FloatProperty(
        name="Fade-in Time", default=0.3, min=0.0, max=10.0, subtype="TIME_ABSOLUTE",
        unit="TIME_ABSOLUTE", description="Seconds over which new GI fades in in the viewport",
    )
    show_overlay: BoolProperty(name="Show Overlay", default=True, update=_changed,
                               description="Draw LPV GI in the 3D viewport")
    overlay_mode: EnumProperty(name="Overlay", items=OVERLAY_MODES, default="ADD",
                               update=_changed, description="What the viewport shows of the GI")
    overlay_exposure: FloatProperty(
        name="Overlay Exposure", default=0.0, soft_min=-8.0, soft_max=8.0,
        description="Brightness of the viewport's GI in stops (display only, not renders)",
    )
    # Batch and comparison
    batch_directory: StringProperty(
        name="Output", subtype="DIR_PATH", default="", options=PATH_OPTIONS,
        description="Folder for rendered EXR frames (empty: the scene's render output path)",
    )
    compare_resolution: IntProperty(
        name="Compare Resolution", default=64, min=8, max=1024,
        description="Width of the Cycles comparison render (height follows the camera)",
    )
    compare_samples: IntProperty(name="Compare Samples", default=64, min=1, max=65536,
                                 description="Cycles samples per pixel for the comparison")
    compare_summary: StringProperty(name="Last Comparison", default="",
                                    description="Result of the last comparison with Cycles")
    # UI list state
    active_light_index: IntProperty(name="Active Light", default=0, min=0,
                                    description="The light selected in the Lights list")
    active_area_index: IntProperty(name="Active Area", default=0, min=0,
                                   description="The area selected in the Areas list")


class LPVLightSettings(bpy.types.PropertyGroup):
    """Per-light GI controls."""

    gi_intensity: FloatProperty(
        name="Light GI Intensity", default=1.0, soft_min=-2.0, soft_max=4.0, min=-100.0,
        max=100.0, update=_changed,
        description="How much of this light bounces (0: none; negative takes light away)",
    )
    gi_color: FloatVectorProperty(
        name="Light GI Color", subtype="COLOR", size=3, default=(1.0, 1.0, 1.0), min=0.0,
        soft_max=1.0, update=_changed, description="Tint of this light's bounced light",
    )


class LPVObjectSettings(bpy.types.PropertyGroup):
    """Per-object GI flags, and GI area settings for Empties."""

    gi_caster: BoolProperty(name="Caster", default=True, update=_changed,
                            description="Bounces light onto other surfaces (off: still shadows)")
    gi_occluder: BoolProperty(name="Occluder", default=True, update=_changed,
                              description="Blocks bounced light (when Occlusion is on)")
    gi_receiver: BoolProperty(name="Receiver", default=True, update=_changed,
                              description="Receives bounced light")
    area_type: EnumProperty(name="GI Area", items=AREA_TYPES, default="NONE", update=_changed,
                            description="Use this Empty's cube as a GI area")
    area_falloff: FloatProperty(
        name="Area Falloff", default=0.5, min=0.0, soft_max=10.0, subtype="DISTANCE",
        unit="LENGTH", update=_changed,
        description="Distance over which a transition area blends into its surroundings",
    )
    area_intensity: FloatProperty(name="Area Intensity", default=1.0, min=0.0, soft_max=4.0,
                                  update=_changed,
                                  description="Brightness of bounced light inside this area")
    area_tint: FloatVectorProperty(
        name="Area Tint", subtype="COLOR", size=3, default=(1.0, 1.0, 1.0), min=0.0,
        soft_max=1.0, update=_changed, description="Tint of bounced light inside this area",
    )


class LPVMaterialSettings(bpy.types.PropertyGroup):
    """What a material bounces into GI, without touching its shading."""

    use_bleed_color: BoolProperty(
        name="Use Bleed Color", default=False, update=_changed,
        description="Bounce the Bleed Color instead of the material's own (its look unchanged)",
    )
    bleed_color: FloatVectorProperty(
        name="Bleed Color", subtype="COLOR", size=3, default=(0.8, 0.8, 0.8), min=0.0,
        soft_max=1.0, update=_changed, description="Colour this material bounces onto others",
    )
    bleed_intensity: FloatProperty(
        name="Bleed Intensity", default=1.0, min=0.0, soft_max=4.0, update=_changed,
        description="How much light this material bounces (scales its colour or Bleed Color)",
    )
    emission_gi_intensity: FloatProperty(
        name="Emission GI Intensity", default=1.0, soft_min=0.0, soft_max=4.0, min=-100.0,
        max=100.0, update=_changed,
        description="How much of this material's emitted light reaches GI (0: none; its "
                    "look unchanged)",
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
        owner.lpv = PointerProperty(type=cls, name="LPV GI", description=cls.__doc__)


def unregister() -> None:
    for owner, _ in reversed(POINTERS):
        if hasattr(owner, "lpv"):
            del owner.lpv
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
