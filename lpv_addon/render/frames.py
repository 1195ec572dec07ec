"""Renders a frame range to multi-layer EXRs (Cycles' pass names) and stats.json: the one loop
behind ``python -m lpv_addon.batch`` and the Render Batch operator.

Each frame: ``frame_set`` (animated values, e.g. a keyframed ``Scene.lpv.intensity``),
extraction here, the engine's update and deferred render, the EXR written atomically, and
stats.json rewritten after every frame, so a cancelled or failed batch keeps its finished
frames. Where the engine runs is the only difference between the two callers:
:class:`InProcess` for the CLI (no Blender drawing happens there), :class:`InWorker` inside
Blender, whose process must never run moderngl (it breaks Blender's drawing).
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import bpy

from .._core import core
from ..scene_io.extract import extract_scene
from ..worker_client import WorkerClient, WorkerError


def write_json_atomic(path: Path, data: dict) -> None:
    """``path`` holds either its old content or all of ``data``, never a part."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


class InProcess:
    """The engine in this process, one frame at a time (collect returns at once)."""

    def __init__(self):
        self.engine = core.engine.Engine()

    def submit(self, scene, exr_path: Path) -> dict:
        stats = core.engine.Stats()
        result = self.engine.update(scene, stats)
        passes = core.render.deferred.render(self.engine, scene, result, stats)
        t_w = time.perf_counter()
        core.render.exr.write_multilayer(exr_path, passes)
        stats.add_ms("write", time.perf_counter() - t_w)
        return stats.as_dict()

    def collect(self, handle: dict, block: bool) -> dict:
        return handle

    def cancel(self) -> None:
        pass

    def close(self) -> None:
        pass


class InWorker:
    """The engine in the ``lpv_core.worker`` process; collect polls for the reply."""

    def __init__(self):
        self.worker = WorkerClient()

    def submit(self, scene, exr_path: Path) -> tuple[int, str]:
        return self.worker.send_scene("render", scene, f"{exr_path.stem}.npz", exr=str(exr_path))

    def collect(self, handle: tuple[int, str], block: bool) -> dict | None:
        rid, request = handle
        reply = self.worker.wait(rid) if block else self.worker.reply(rid)
        if reply is None:
            return None
        os.unlink(request)
        if not reply.get("ok"):
            raise WorkerError(reply.get("error", "unknown worker error"))
        return dict(reply.get("stats", {}))

    def cancel(self) -> None:
        """Drop the frame in flight: the worker is killed (its EXR never appears)."""
        self.worker.kill()

    def close(self) -> None:
        self.worker.close()


def unmodelled_warnings(dropped: dict) -> list[str]:
    """One line per light source LPV GI does not model (also in stats.json)."""
    out = []
    if dropped.get("world_lighting_ignored"):
        out.append("the world (background) lights this scene; LPV GI models lamps only, so "
                   "world light is missing from Diffuse Direct and Indirect")
    n = dropped.get("emissive_materials_ignored", 0)
    if n:
        out.append(f"{n} emissive material(s) ignored; LPV GI models lamps only")
    return out


class BatchJob:
    """Renders ``frames`` (default: the scene's range) of ``scene`` into ``out_dir``, one frame
    in flight at a time. ``run`` renders them all (blocking); ``step`` advances without
    blocking, as the modal operator's timer drives it; ``cancel`` keeps every finished frame
    and removes the unfinished one. ``log(message)`` hears one line per finished frame and the
    warnings about unmodelled light."""

    def __init__(self, scene: bpy.types.Scene, out_dir, frames=None, resolution=None,
                 overrides: dict | None = None, in_process: bool = False,
                 log: Callable[[str], None] | None = None):
        self.scene_name = scene.name
        self.out = Path(bpy.path.abspath(str(out_dir)))
        first, last = frames or (scene.frame_start, scene.frame_end)
        if last < first:
            raise ValueError(f"frame range {first}-{last} is empty")
        self.frames = list(range(int(first), int(last) + 1))
        self.resolution = resolution
        self.overrides = dict(overrides or {})
        self.in_process = in_process
        self.log = log
        self.done: list[int] = []
        self.record = {"scene": scene.name, "settings": None, "frames": [], "cancelled": False}
        self.original_frame = scene.frame_current
        self.renderer: InProcess | InWorker | None = None
        self.pending = None
        self.cancelled = False
        self.error = ""

    @property
    def scene(self) -> bpy.types.Scene:
        scene = bpy.data.scenes.get(self.scene_name)
        if scene is None:
            raise ValueError(f"scene '{self.scene_name}' is gone")
        return scene

    @property
    def total(self) -> int:
        return len(self.frames)

    @property
    def finished(self) -> bool:
        return self.pending is None and (len(self.done) == self.total or self.cancelled
                                         or bool(self.error))

    def start(self) -> None:
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"cannot create '{self.out}': {exc.strerror}") from None
        self.renderer = InProcess() if self.in_process else InWorker()

    def _send(self, frame: int) -> None:
        t0 = time.perf_counter()
        scene = self.scene
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        timings: dict = {}
        t_ex = time.perf_counter()
        core_scene = extract_scene(depsgraph, scene, self.resolution, self.overrides,
                                   timings=timings)
        t_ex = (time.perf_counter() - t_ex) * 1000.0
        if self.record["settings"] is None:
            self.record["settings"] = core_scene.settings.as_dict()
            for line in unmodelled_warnings(core_scene.dropped):
                self._log(f"warning: {line}")
        entry = {"frame": frame, "t0": t0, "extract": t_ex, "timings": timings,
                 "intensity": core_scene.settings.intensity}
        self.pending = (entry, self.renderer.submit(core_scene, self.out / f"{frame:04d}.exr"))

    def _collect(self, block: bool) -> bool:
        """Take the frame in flight if it is done; False while it is not."""
        entry, handle = self.pending
        stats = self.renderer.collect(handle, block)
        if stats is None:
            return False
        self.pending = None
        frame = entry["frame"]
        stats.setdefault("ms", {})["extract"] = entry["extract"]
        stats["ms"]["total"] = (time.perf_counter() - entry["t0"]) * 1000.0
        self.record["frames"].append({"frame": frame, **stats, "intensity": entry["intensity"],
                                      "extract_ms": entry["timings"]})
        self.done.append(frame)
        self._write_stats()
        ms = stats["ms"]
        self._log(f"frame {frame} ({len(self.done)}/{self.total}): {ms['total']:.0f} ms, "
                  f"LPV {ms.get('lpv_update', 0):.0f} ms -> {self.out / f'{frame:04d}.exr'}")
        return True

    def step(self, block: bool = False) -> bool:
        """Advance: collect a finished frame, send the next. Returns True while running."""
        if self.renderer is None:
            self.start()
        frame = self.pending[0]["frame"] if self.pending is not None else None
        try:
            if self.pending is not None and not self._collect(block):
                return True
            if self.cancelled or self.error or len(self.done) == self.total:
                return False
            frame = self.frames[len(self.done)]
            self._send(frame)
        except (ValueError, WorkerError) as exc:
            self.pending = None
            self.error = f"frame {frame}: {exc}"
            return False
        return True

    def _log(self, message: str) -> None:
        if self.log is not None:
            self.log(message)

    def _write_stats(self) -> None:
        self.record["cancelled"] = self.cancelled
        write_json_atomic(self.out / "stats.json", self.record)

    def cancel(self) -> None:
        """Stop now: the frame in flight is dropped, finished frames stay."""
        self.cancelled = True
        if self.pending is not None and self.renderer is not None:
            self.renderer.cancel()
            self.renderer = None
            self.pending = None
            for tmp in self.out.glob(".*.tmp"):
                tmp.unlink(missing_ok=True)
        self._write_stats()

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
        try:
            self.scene.frame_set(self.original_frame)
        except ValueError:
            pass

    def run(self) -> None:
        """Render every frame, blocking (the CLI, scripts, the operator's execute)."""
        try:
            while self.step(block=True):
                pass
        finally:
            self.close()
        if self.error:
            raise ValueError(self.error)
