"""LPV GI core: Cascaded Light Propagation Volumes over numpy arrays (and moderngl).

Never imports bpy, so it runs in tests, scripts and the worker process alike.
Kaplanyan & Dachsbacher, "Cascaded Light Propagation Volumes for Real-Time Indirect
Illumination", I3D 2010 [KD10].
"""

from . import (
    areas,
    deferred,
    direct,
    engine,
    exr,
    grid,
    injection,
    lights,
    lookup,
    propagation,
    raster,
    rsm,
    scene,
    sh,
)

__all__ = ["areas", "deferred", "direct", "engine", "exr", "grid", "injection", "lights", "lookup",
           "propagation", "raster", "rsm", "scene", "sh"]
