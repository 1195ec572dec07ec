"""Operators under ``bpy.ops.lpv``: update, add_area, render_batch, compare_cycles.

Every operator has a poll (with a message saying what is missing) and reports failures in one
clear line. The engine always runs in the worker process (worker_client.py): Blender's own
process never creates a moderngl context.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import bpy
import numpy as np
from bpy.props import EnumProperty, FloatProperty, IntProperty, StringProperty

from ._core import core
from .properties import PATH_OPTIONS
from .render import compare
from .render.frames import BatchJob, animation_frames
from .viewport import live
from .worker_client import WorkerError


def _scene_poll(cls, context, need_camera: bool = False) -> bool:
    scene = getattr(context, "scene", None)
    if scene is None or not hasattr(scene, "lpv"):
        cls.poll_message_set("No scene with LPV GI settings")
        return False
    if need_camera and scene.camera is None:
        cls.poll_message_set("The scene needs an active camera")
        return False
    return True


class LPV_OT_update(bpy.types.Operator):
    """Recompute the bounced light of this scene now and show it in the viewport"""

    bl_idname = "lpv.update"
    bl_label = "Update LPV"
    bl_options = {"REGISTER"}  # noqa: RUF012 - Blender reads a set

    @classmethod
    def poll(cls, context):
        return _scene_poll(cls, context)

    def execute(self, context):
        scene = context.scene
        if not scene.lpv.enabled:
            self.report({"WARNING"}, "LPV GI is disabled for this scene (Scene > LPV > Enabled)")
            return {"CANCELLED"}
        live.mark_dirty("update operator")
        try:
            live.refresh(scene, context.evaluated_depsgraph_get(), wait=True)
        except (WorkerError, ValueError, OSError) as exc:
            self.report({"ERROR"}, f"LPV update failed: {exc}")
            return {"CANCELLED"}
        if live.STATE.error:
            self.report({"ERROR"}, f"LPV update failed: {live.STATE.error}")
            return {"CANCELLED"}
        result = live.STATE.current
        ms = result.stats.get("ms", {}) if result else {}
        if result is None or result.values is None:
            why = "; ".join(s["reason"] for s in (result.stats.get("skipped", []) if result
                                                  else [])) or "no GI"
            self.report({"WARNING"}, f"LPV updated: no indirect light ({why})")
        else:
            self.report({"INFO"}, f"LPV updated in {ms.get('lpv_update', 0):.0f} ms "
                                  f"({result.stats.get('info', {}).get('vpls', 0)} VPLs)")
        live.tag_redraw()
        return {"FINISHED"}


class LPV_OT_add_area(bpy.types.Operator):
    """Add a GI area: a box that keeps bounced light in or out, or scales and tints it"""

    bl_idname = "lpv.add_area"
    bl_label = "Add GI Area"
    bl_options = {"REGISTER", "UNDO"}  # noqa: RUF012 - Blender reads a set

    type: EnumProperty(name="Type", items=[
        ("CLIP", "Clip", "Light does not propagate across the box's boundary"),
        ("TRANSITION", "Transition", "GI inside the box is scaled and tinted")],
        default="CLIP")
    size: FloatProperty(name="Size", default=1.0, min=0.001, soft_max=100.0, subtype="DISTANCE",
                        unit="LENGTH", description="Half the box's edge length")

    @classmethod
    def poll(cls, context):
        if not _scene_poll(cls, context):
            return False
        if getattr(context, "mode", "OBJECT") != "OBJECT":
            cls.poll_message_set("Switch to Object Mode to add a GI area")
            return False
        return True

    def execute(self, context):
        scene = context.scene
        label = "Clip" if self.type == "CLIP" else "Transition"
        ob = bpy.data.objects.new(f"LPV {label} Area", None)
        ob.empty_display_type = "CUBE"
        ob.empty_display_size = self.size
        ob.location = scene.cursor.location
        ob.lpv.area_type = self.type
        collection = getattr(context, "collection", None) or scene.collection
        collection.objects.link(ob)
        view_layer = getattr(context, "view_layer", None)
        if view_layer is not None:
            for other in context.selected_objects or []:
                other.select_set(False)
            ob.select_set(True)
            view_layer.objects.active = ob
        live.mark_dirty(f"area added: {ob.name}")
        self.report({"INFO"}, f"Added {label.lower()} area '{ob.name}'")
        return {"FINISHED"}


def _frame_range(op, scene) -> tuple[int, ...]:
    if op.frames == "ANIMATION":
        return animation_frames(scene)
    if op.frames == "RANGE":
        return op.frame_start, op.frame_end
    return scene.frame_current, scene.frame_current


class LPV_OT_render_batch(bpy.types.Operator):
    """Render frames with LPV GI into multi-layer EXR files; Esc stops, keeping those done"""

    bl_idname = "lpv.render_batch"
    bl_label = "Render Batch"
    bl_options = {"REGISTER"}  # noqa: RUF012 - Blender reads a set

    directory: StringProperty(name="Output", subtype="DIR_PATH", default="",
                              options=PATH_OPTIONS | {"SKIP_SAVE"},
                              description="Output folder (empty: Scene > LPV > Output, else the "
                                          "render output path)")
    frames: EnumProperty(name="Frames", default="CURRENT", items=[
        ("CURRENT", "Current Frame", "Render the scene's current frame, as Render Image"),
        ("ANIMATION", "Animation", "Render the scene's frame range and step, as Render Animation"),
        ("RANGE", "Range", "Render the frames from Start to End")])
    frame_start: IntProperty(name="Start", default=1, description="First frame (Frames: Range)")
    frame_end: IntProperty(name="End", default=1, description="Last frame (Frames: Range)")

    _job = None
    _timer = None

    @classmethod
    def poll(cls, context):
        if not _scene_poll(cls, context, need_camera=True):
            return False
        if live.STATE.paused:
            cls.poll_message_set("A batch render is already running")
            return False
        return True

    def _make_job(self, context):
        scene = context.scene  # no folder given: the render output path, as F12 renders
        return BatchJob(scene, self.directory or scene.lpv.batch_directory or None,
                        _frame_range(self, scene))

    def execute(self, context):
        try:
            job = self._make_job(context)
        except ValueError as exc:
            self.report({"ERROR"}, f"Render Batch: {exc}")
            return {"CANCELLED"}
        live.STATE.paused = True
        try:
            job.run()
        except (ValueError, WorkerError, OSError) as exc:
            self.report({"ERROR"}, f"Render Batch failed after {len(job.done)} frame(s): {exc}")
            return {"CANCELLED"}
        finally:
            live.STATE.paused = False
        self.report({"INFO"}, f"Rendered {len(job.done)} frame(s) to {job.out}")
        return {"FINISHED"}

    def invoke(self, context, event):
        try:
            self._job = self._make_job(context)
            self._job.start()
        except (ValueError, WorkerError, OSError) as exc:
            self.report({"ERROR"}, f"Render Batch: {exc}")
            return {"CANCELLED"}
        wm = context.window_manager
        live.STATE.paused = True
        wm.progress_begin(0, self._job.total)
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.modal_handler_add(self)
        self.report({"INFO"}, f"Rendering {self._job.total} frame(s) to {self._job.out} "
                              "(Esc cancels)")
        return {"RUNNING_MODAL"}

    def _finish(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        self._job.close()
        live.STATE.paused = False
        live.mark_dirty("batch finished")

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC":
            job.cancel()
            self._finish(context)
            self.report({"WARNING"}, f"Render Batch cancelled: {len(job.done)} of {job.total} "
                                     f"frame(s) kept in {job.out}")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            running = job.step()
        except (ValueError, WorkerError, OSError) as exc:
            job.error = str(exc)
            running = False
        context.window_manager.progress_update(len(job.done))
        if running:
            return {"RUNNING_MODAL"}
        self._finish(context)
        if job.error:
            self.report({"ERROR"}, f"Render Batch failed after {len(job.done)} frame(s): "
                                   f"{job.error}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Rendered {len(job.done)} frame(s) to {job.out}")
        return {"FINISHED"}


# ---------------------------------------------------------------------- Cycles comparison

IMAGE_ERROR = "LPV vs Cycles"
IMAGE_OURS = "LPV Indirect"
IMAGE_CYCLES = "Cycles Indirect"


def store_image(name: str, rgba: np.ndarray) -> bpy.types.Image:
    """A float image (rows top-first in, Blender's bottom-first stored) replacing any old one."""
    h, w = rgba.shape[:2]
    img = bpy.data.images.get(name)
    if img is not None and (img.size[0] != w or img.size[1] != h or not img.is_float):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=True)
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], np.float32).ravel())
    img.update()
    return img


def _show_image(context, img) -> bool:
    shown = False
    for win in getattr(context.window_manager, "windows", []):
        for area in win.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = img
                area.tag_redraw()
                shown = True
    return shown


class LPV_OT_compare_cycles(bpy.types.Operator):
    """Render a small Cycles image and show where LPV GI is too bright (red) or dark (green)"""

    bl_idname = "lpv.compare_cycles"
    bl_label = "Compare with Cycles"
    bl_options = {"REGISTER"}  # noqa: RUF012 - Blender reads a set

    resolution: IntProperty(name="Resolution", default=0, min=0, max=1024,
                            description="Width in pixels (0: Scene > LPV > Compare Resolution)")
    samples: IntProperty(name="Samples", default=0, min=0, max=65536,
                         description="Cycles samples (0: Scene > LPV > Compare Samples)")

    @classmethod
    def poll(cls, context):
        if not _scene_poll(cls, context, need_camera=True):
            return False
        if not hasattr(bpy.types.Scene, "cycles") and "cycles" not in \
                bpy.context.preferences.addons:
            cls.poll_message_set("Cycles is not available")
            return False
        return True

    def execute(self, context):
        from .render import cycles
        from .scene_io.extract import render_resolution

        scene = context.scene
        props = scene.lpv
        rx, ry = render_resolution(scene)
        w = self.resolution or props.compare_resolution
        h = max(1, round(w * ry / rx))
        samples = self.samples or props.compare_samples
        try:
            t0 = time.perf_counter()
            ours, _ = compare.render_passes(scene, (w, h))
            t_ours = time.perf_counter() - t0
            with tempfile.TemporaryDirectory(prefix="lpv_compare_") as tmp:
                info = cycles.render_cycles_passes(Path(tmp) / "ref.exr", samples=samples,
                                                      diffuse_bounces=1, resolution=(w, h),
                                                      scene=scene)
                ref = core.render.exr.read_multilayer(Path(tmp) / "ref.exr")
        except (WorkerError, ValueError, OSError, RuntimeError, KeyError) as exc:
            self.report({"ERROR"}, f"Compare with Cycles failed: {exc}")
            return {"CANCELLED"}
        a, b = compare.error.indirect_term(ours), compare.error.indirect_term(ref)
        heat, metrics = compare.error_heatmap(a, b)
        img = store_image(IMAGE_ERROR, heat)
        for name, arr in ((IMAGE_OURS, a), (IMAGE_CYCLES, b)):
            rgba = np.ones(arr.shape[:2] + (4,), np.float32)
            rgba[..., :3] = arr
            store_image(name, rgba)
        summary = (f"indirect rel. RMSE {metrics['relative_rmse']:.2f}, mean LPV/Cycles "
                   f"{metrics['mean_ratio']:.2f}; {w}x{h}: LPV {t_ours:.1f} s, Cycles "
                   f"{info['seconds']:.1f} s ({samples} spp)")
        props.compare_summary = summary
        shown = _show_image(context, img)
        where = "" if shown else f" (open image '{IMAGE_ERROR}' in an Image Editor)"
        self.report({"INFO"}, summary + where)
        return {"FINISHED"}


CLASSES = (LPV_OT_update, LPV_OT_add_area, LPV_OT_render_batch, LPV_OT_compare_cycles)


def menu_add_area(self, context) -> None:
    self.layout.separator()
    self.layout.operator_menu_enum("lpv.add_area", "type", text="LPV GI Area", icon="CUBE")


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.VIEW3D_MT_add.append(menu_add_area)


def unregister() -> None:
    bpy.types.VIEW3D_MT_add.remove(menu_add_area)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
