"""Rendered viewport shading of the LPV GI engine: the view's passes (direct light with shadow
maps plus LPV indirect: the F12 frame's pipeline for the view's matrices, one sample per pixel)
come from the live worker and are drawn as an image with Blender's ``gpu`` module. Edits and
view changes send the next request; the last image stays on screen until its answer."""

from __future__ import annotations

import bpy
import gpu
import numpy as np
from gpu_extras.presets import draw_texture_2d

from .._core import core
from ..render.passes import receive, send
from ..worker_client import WorkerError
from . import live

VIEW_SETTINGS = {"antialias": 1}  # one sample per pixel: the viewport redraws often


def view_scene(depsgraph, view_matrix, window_matrix, size) -> core.scene.Scene:
    """The core scene as the viewport shows it (viewport visibility) through the view's
    world-to-view and projection matrices, ``size`` = (width, height) pixels."""
    scene = live.extract(depsgraph.scene, depsgraph, VIEW_SETTINGS)
    scene.camera = core.scene.Camera(np.array(view_matrix, np.float64),
                                     np.array(window_matrix, np.float64), tuple(size))
    return scene


def image_texture(image: np.ndarray):
    """An (H, W, 4) linear image, rows top-first, as a float texture (GL rows bottom-first)."""
    h, w = image.shape[:2]
    data = np.ascontiguousarray(image[::-1], np.float32).ravel()
    return gpu.types.GPUTexture((w, h), format="RGBA32F",
                                data=gpu.types.Buffer("FLOAT", data.size, data))


def _redraw() -> None:
    """One-shot timer while a view waits for the worker: its next draw takes the answer."""
    live.tag_redraw()


class View:
    """One Rendered viewport: the request in flight, the last image and its texture."""

    def __init__(self):
        self.dirty = True
        self.key = None
        self.pending = None  # (worker, request handle)
        self.image = None
        self.texture = None
        self.error = ""

    def free(self) -> None:
        self.texture = self.image = self.pending = None

    def poll(self) -> None:
        client, handle = self.pending
        try:
            got = receive(client, handle)
        except (WorkerError, OSError, ValueError) as exc:
            self.pending, self.error = None, str(exc)
            return
        if got is not None:
            self.pending, self.error = None, ""
            self.image, self.texture = got[0]["Combined"], None

    def draw(self, engine, context, depsgraph) -> None:
        region, rv3d = context.region, context.region_data
        px = max(1, engine.get_preview_pixel_size(depsgraph.scene))
        size = (max(1, region.width // px), max(1, region.height // px))
        key = (str(rv3d.view_matrix), str(rv3d.window_matrix), size)
        if self.pending is not None:
            self.poll()
        if self.pending is None and (self.dirty or key != self.key):
            self.dirty, self.key = False, key
            try:
                client = live.client()
                scene = view_scene(depsgraph, rv3d.view_matrix, rv3d.window_matrix, size)
                self.pending = (client, send(client, scene, f"view_{id(self)}"))
            except (ValueError, WorkerError, OSError) as exc:
                self.error = str(exc)
        if self.pending is not None and not bpy.app.timers.is_registered(_redraw):
            bpy.app.timers.register(_redraw, first_interval=0.05)
        engine.update_stats("", f"LPV GI: {self.error}" if self.error else
                            "LPV GI: updating" if self.pending else "")
        if self.image is not None:
            self.texture = self.texture or image_texture(self.image)
            gpu.state.blend_set("ALPHA_PREMULT")
            draw_texture_2d(self.texture, (0, 0), region.width, region.height)
            gpu.state.blend_set("NONE")


def unregister() -> None:
    if bpy.app.timers.is_registered(_redraw):
        bpy.app.timers.unregister(_redraw)
