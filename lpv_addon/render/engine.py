"""The LPV GI render engine (``LPV_GI``): F12, ``blender -b file.blend -E LPV_GI -f N / -a``,
the compositor and farms, through Blender's own pipeline.

A frame is the batch's frame: the scene extracted from the render depsgraph, rendered by the
worker's "render" command (the engine's update, then the deferred passes), so the passes equal
the batch CLI's. Blender's process never runs moderngl: one worker process serves every frame
and render. Blender does the rest: output path and format, frame range and step, the
compositor, the view transform. Esc (``test_break``) or Ctrl-C stop the frame in flight (the
worker is killed); Blender keeps the finished frames and writes no file for the stopped one.
"""

from __future__ import annotations

import time

import bpy
import numpy as np

from ..scene_io.extract import extract_scene
from ..viewport import live, rendered
from ..worker_client import WorkerClient, WorkerError
from .frames import approximation_warnings
from .passes import receive, send

# Cycles' names of the passes besides Combined, and the view layer toggles that add them.
PASSES = (("Diffuse Direct", "use_pass_diffuse_direct"),
          ("Diffuse Indirect", "use_pass_diffuse_indirect"),
          ("Diffuse Color", "use_pass_diffuse_color"))
_WORKER: list[WorkerClient] = []  # the render worker, started by the first frame


class Cancelled(Exception):
    """The user stopped the render (Esc, Ctrl-C): the frame in flight is dropped."""


def worker() -> WorkerClient:
    if not (_WORKER and _WORKER[0].alive):
        shutdown()
        _WORKER.append(WorkerClient())
    return _WORKER[0]


def shutdown() -> None:
    """Stop the render worker (unregister, a cancelled frame)."""
    while _WORKER:
        _WORKER.pop().close()


def render_passes(scene, stop=lambda: False) -> tuple[dict, dict]:
    """The passes and stats of a frame from the render worker; raises Cancelled (the worker
    killed) as soon as ``stop()`` says so or Ctrl-C arrives."""
    try:
        client = worker()
        handle = send(client, scene, "frame")
        while (got := receive(client, handle)) is None:
            if stop():
                raise Cancelled
            time.sleep(0.02)
        return got
    except (Cancelled, KeyboardInterrupt):
        if _WORKER:
            _WORKER.pop().kill()
        raise Cancelled from None


def result_pixels(name: str, passes: dict, region: tuple[int, int, int, int] | None = None
                  ) -> np.ndarray | None:
    """A pass as Blender's render result holds it (bottom row first, flat), only the render
    region ``region`` (x, y from the bottom left, width, height; None: the whole frame).
    Film > Transparent is the core's (Scene.film_transparent: Combined's alpha is the
    coverage and no World behind it)."""
    arr = passes.get(name)
    if arr is None:
        return None
    arr = arr[::-1]
    if region is not None:
        x, y, w, h = region
        arr = arr[y:y + h, x:x + w]
    return np.ascontiguousarray(arr, np.float32).ravel()


def result_region(render, width: int, height: int, result) -> tuple[int, int, int, int]:
    """Where Blender's render result lies in the frame: the whole frame, or with a Render
    Region (Output > Render Region) the region it was clipped to, its corner as Blender
    places it (border x frame size, truncated)."""
    rw, rh = int(result.resolution_x), int(result.resolution_y)
    if (rw, rh) == (width, height) or not render.use_border:
        return 0, 0, rw, rh
    x = min(max(int(render.border_min_x * width), 0), width - rw)
    y = min(max(int(render.border_min_y * height), 0), height - rh)
    return x, y, rw, rh


class LPVRenderEngine(bpy.types.RenderEngine):
    """Direct light with shadows plus LPV GI, passes named and meant as Cycles'."""

    bl_idname = "LPV_GI"
    bl_label = "LPV GI"
    bl_use_postprocess = True
    bl_use_shading_nodes_custom = False  # material nodes show in the properties
    bl_use_eevee_viewport = True  # Material Preview shading draws with EEVEE

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.view = rendered.View()

    def update_render_passes(self, scene=None, renderlayer=None):
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        for name, toggle in PASSES:
            if getattr(renderlayer, toggle):
                self.register_pass(scene, renderlayer, name, 3, "RGB", "COLOR")

    def render(self, depsgraph):
        paused, live.STATE.paused = live.STATE.paused, True  # the live viewport waits
        try:
            self._render(depsgraph)
        except (Cancelled, KeyboardInterrupt):
            if not self.test_break():  # Ctrl-C: an error is what stops Blender's frame loop
                self.report({"ERROR"}, "LPV GI: render cancelled")
        except (ValueError, WorkerError, OSError) as exc:
            self.report({"ERROR"}, f"LPV GI: {exc}")
        finally:
            live.STATE.paused = paused

    def _render(self, depsgraph) -> None:
        scene = depsgraph.scene_eval  # this frame's animated values
        w, h = self.resolution_x, self.resolution_y
        self.update_stats("", "LPV GI: reading the scene")
        core_scene = extract_scene(depsgraph, scene, (w, h))
        for line in approximation_warnings(core_scene.approximated):
            self.report({"WARNING"}, f"LPV GI: {line}")
        self.update_progress(0.1)
        self.update_stats("", "LPV GI: light propagation and passes")
        passes, _ = render_passes(core_scene, self.test_break)
        if self.test_break():
            return
        result = self.begin_result(0, 0, w, h, layer=depsgraph.view_layer.name)
        try:  # the result always ended: an unended one takes Blender down
            region = result_region(scene.render, w, h, result)
            for rpass in result.layers[0].passes:
                pixels = result_pixels(rpass.name, passes, region)
                if pixels is not None:
                    rpass.rect.foreach_set(pixels)
        except BaseException:
            self.end_result(result, cancel=True)
            raise
        self.end_result(result)
        self.update_progress(1.0)

    def view_update(self, context, depsgraph):
        self.view.dirty = True

    def view_draw(self, context, depsgraph):
        self.view.draw(self, context, depsgraph)


def register() -> None:
    bpy.utils.register_class(LPVRenderEngine)


def unregister() -> None:
    bpy.utils.unregister_class(LPVRenderEngine)
    rendered.unregister()
    shutdown()
