"""LPV GI core: Cascaded Light Propagation Volumes over numpy arrays (and moderngl).

Never imports bpy, so it runs in tests, scripts and the worker process alike.
Kaplanyan & Dachsbacher, "Cascaded Light Propagation Volumes for Real-Time Indirect
Illumination", I3D 2010 [KD10].

The folders are the pipeline: ``scene`` (the model), the stages (``rsm``, ``injection``,
``geometry_volume``, ``propagation``, ``lookup``, ``cascades``, ``planner``, ``areas``),
``render`` (raster, deferred, direct, exr), ``runtime`` (compiled kernels' switch, heap,
BLAS), ``gl`` (the GL compute backend), ``engine`` and ``worker``.
"""

from . import areas, engine, grid, injection, lookup, propagation, rsm, scene, sh
from .render import deferred, direct, exr, raster

__all__ = ["areas", "deferred", "direct", "engine", "exr", "grid", "injection", "lookup",
           "propagation", "raster", "rsm", "scene", "sh"]
