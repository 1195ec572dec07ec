"""The scene model the core computes on: triangles, materials, lights, camera, areas and the GI
settings, in Blender units (model.py); light views and intensities (lights.py)."""

from .model import (
    AREA_TYPES,
    LIGHT_TYPES,
    Area,
    Camera,
    GISettings,
    Light,
    Material,
    Scene,
    cross3,
    look_at_matrix,
    make_scene,
    orthographic_matrix,
    perspective_matrix,
)
from .textures import Texture
from .world import World

__all__ = [
    "AREA_TYPES",
    "LIGHT_TYPES",
    "Area",
    "Camera",
    "GISettings",
    "Light",
    "Material",
    "Scene",
    "Texture",
    "World",
    "cross3",
    "look_at_matrix",
    "make_scene",
    "orthographic_matrix",
    "perspective_matrix",
]
