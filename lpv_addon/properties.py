"""Our own Blender properties (Scene.lpv): GI settings saved in the .blend."""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty


class LPVSceneSettings(bpy.types.PropertyGroup):
    """Scene-wide LPV GI settings."""

    enabled: BoolProperty(name="Enabled", default=True, description="Compute LPV GI")
    intensity: FloatProperty(
        name="Intensity", default=1.0, min=0.0, soft_max=4.0,
        description="Global GI multiplier (keyframable)",
    )
    grid_resolution: IntProperty(name="Grid Resolution", default=32, min=4, max=128)
    cascades: IntProperty(name="Cascades", default=1, min=1, max=4)
    iterations: IntProperty(
        name="Iterations", default=0, min=0, max=1000,
        description="Propagation steps (0: automatic)",
    )
    rsm_resolution: IntProperty(name="RSM Resolution", default=256, min=16, max=2048)
    occlusion: BoolProperty(name="Occlusion", default=False)
    bounces: IntProperty(name="Bounces", default=1, min=1, max=8)
    backend: EnumProperty(
        name="Backend",
        items=[("numpy", "NumPy", "CPU arrays"), ("gl", "OpenGL", "moderngl compute")],
        default="numpy",
    )


CLASSES = (LPVSceneSettings,)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.lpv = PointerProperty(type=LPVSceneSettings)


def unregister() -> None:
    del bpy.types.Scene.lpv
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
