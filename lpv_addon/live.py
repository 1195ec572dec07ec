"""The live LPV engine behind the viewport overlay, the batch operator and the comparison.

Blender's process never runs moderngl (it broke Blender's drawing, design.md): the engine
runs in one long-lived child process (``python -m lpv_core.worker``, see that module for
the protocol) that keeps its GL context warm. This side extracts the scene with bpy, writes it
as arrays, and reads back the LPV grids; the overlay uploads them as 3D textures.

Planning (what is recomputed, what is skipped and why):
- depsgraph/frame handlers and property updates call :func:`mark_dirty` with what changed;
- a timer calls :func:`tick` every ``Scene.lpv.refresh_interval`` seconds: while a request is
  in flight nothing new is sent (the newest state goes next); when only art-direction values
  changed (light GI intensity/tint, global intensity) the cached per-light grids are
  re-combined here in numpy (propagation is linear), no RSM, injection or propagation;
- a new result fades in over ``Scene.lpv.fade_time`` (the overlay blends old and new).
No bpy object is stored: results hold arrays and names only (undo and file loads are safe).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

from ._core import core

live_worker = importlib.import_module(core.__name__ + ".worker")
PACKAGE_PARENT = str(Path(core.__file__).resolve().parents[1])
WORKER_MODULE = "lpv_core.worker"
MAX_REASONS = 12


class WorkerError(RuntimeError):
    """The worker process failed, died or did not answer in time."""


class WorkerClient:
    """A ``lpv_core.worker`` child process with a line-based JSON protocol."""

    def __init__(self, python: str | None = None):
        self.dir = tempfile.mkdtemp(prefix="lpv_live_")
        self.log_path = os.path.join(self.dir, "worker.log")
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - lives as long as the process
        env = dict(os.environ)
        paths = [PACKAGE_PARENT] + [p for p in sys.path if p and os.path.isdir(p)]
        env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
        env.setdefault("PYTHONNOUSERSITE", "1")
        flags = getattr(subprocess, "CREATE_NO_WINDOW", 0) if os.name == "nt" else 0
        self.proc = subprocess.Popen(
            [python or sys.executable, "-m", WORKER_MODULE],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._log, env=env,
            cwd=self.dir, text=True, encoding="utf-8", bufsize=1, creationflags=flags,
        )
        self._next = 0
        self._replies: dict = {}
        self._lock = threading.Lock()
        self._arrived = queue.Queue()
        self._reader = threading.Thread(target=self._read, name="lpv-worker-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            try:
                reply = json.loads(line)
            except json.JSONDecodeError:
                continue
            with self._lock:
                self._replies[reply.get("id")] = reply
            self._arrived.put(reply.get("id"))

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def path(self, name: str) -> str:
        return os.path.join(self.dir, name)

    def send(self, cmd: str, **kw) -> int:
        if not self.alive:
            raise WorkerError(f"LPV worker exited ({self.proc.returncode}): {self.log_tail()}")
        self._next += 1
        try:
            self.proc.stdin.write(json.dumps({"id": self._next, "cmd": cmd, **kw}) + "\n")
            self.proc.stdin.flush()
        except OSError as exc:
            raise WorkerError(f"LPV worker is gone ({exc}): {self.log_tail()}") from None
        return self._next

    def reply(self, rid: int) -> dict | None:
        """The reply to request ``rid`` if it arrived (non-blocking), else None."""
        with self._lock:
            reply = self._replies.pop(rid, None)
        if reply is None and not self.alive and not self._reader.is_alive():
            with self._lock:
                reply = self._replies.pop(rid, None)
            if reply is None:
                raise WorkerError(f"LPV worker exited ({self.proc.returncode}): "
                                  f"{self.log_tail()}")
        return reply

    def wait(self, rid: int, timeout: float = 300.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            reply = self.reply(rid)
            if reply is not None:
                return reply
            left = deadline - time.monotonic()
            if left <= 0:
                raise WorkerError(f"LPV worker did not answer within {timeout:.0f} s")
            try:
                self._arrived.get(timeout=min(left, 0.2))
            except queue.Empty:
                pass

    def log_tail(self, lines: int = 3) -> str:
        try:
            self._log.flush()
            text = Path(self.log_path).read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(text[-lines:])

    def close(self, timeout: float = 3.0) -> None:
        """Ask the worker to quit, kill it if it does not, and remove its folder."""
        if self.alive:
            try:
                self.proc.stdin.write(json.dumps({"id": 0, "cmd": "quit"}) + "\n")
                self.proc.stdin.flush()
            except OSError:
                pass
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        for stream in (self.proc.stdin, self.proc.stdout):
            try:
                stream.close()
            except OSError:
                pass
        self._reader.join(timeout)
        self._log.close()
        shutil.rmtree(self.dir, ignore_errors=True)

    def kill(self) -> None:
        if self.alive:
            self.proc.kill()
        self.close(timeout=3.0)


# --------------------------------------------------------------------------- live state


@dataclass
class LiveResult:
    """One LPV result as the overlay draws it (arrays only, no bpy data)."""

    serial: int
    grid: object  # core.grid.Grid or None
    values: np.ndarray | None  # combined (R,R,R,3,K): K = 9 for angular "dom", else 4
    per_light: dict  # light name -> (R,R,R,3,K)
    lights: list
    settings: object
    areas: list
    geometry: dict  # positions (T,3,3) f32, normals (T,3,3) f32, albedo (T,3), receiver (T,)
    vpl_position: np.ndarray | None = None
    vpl_flux: np.ndarray | None = None
    visibility: np.ndarray | None = None  # (6, R, R, R) propagation visibility
    fine: list = field(default_factory=list)  # inner cascades: (Grid, values, visibility)
    # Grid (``grid`` or one of ``fine``) -> geometry_volume.cell_gaps (6, R, R, R) or None:
    # where lookups move their sample point (lookup.gap_corrected)
    gaps: dict = field(default_factory=dict)
    cosine_table: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    arrived: float = 0.0  # time.monotonic() when it arrived (fade-in start)
    recombine_key: str = ""


class LiveState:
    def __init__(self):
        self.client: WorkerClient | None = None
        self.dirty = True
        self.reasons: list[str] = ["start"]
        self.pending: tuple | None = None  # (request id, key, core scene, t_sent, reasons)
        self.current: LiveResult | None = None
        self.previous: LiveResult | None = None
        self.serial = 0
        self.error = ""
        self.last_sent = 0.0
        self.updates = 0
        self.paused = False  # a batch render owns the frame: no live updates meanwhile
        self.requests = 0


STATE = LiveState()


def mark_dirty(reason: str = "edit") -> None:
    """Something the GI depends on changed: the next tick refreshes the LPV."""
    STATE.dirty = True
    if reason not in STATE.reasons:
        STATE.reasons.append(reason)
        del STATE.reasons[:-MAX_REASONS]


def client() -> WorkerClient:
    if STATE.client is None or not STATE.client.alive:
        if STATE.client is not None:
            STATE.client.close()
        STATE.client = WorkerClient()
    return STATE.client


def shutdown() -> None:
    """Stop the worker and drop every result (unregister, file load)."""
    if STATE.client is not None:
        STATE.client.close()
    STATE.client = None
    STATE.pending = None
    STATE.current = STATE.previous = None
    STATE.dirty = True
    STATE.reasons = ["reset"]
    STATE.error = ""
    from . import overlay

    overlay.free_resources()


# ------------------------------------------------------------------------------ planning


def _hash(*arrays) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        if a is None:
            h.update(b"-")
        elif isinstance(a, np.ndarray):
            h.update(str(a.dtype).encode() + str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
        else:
            h.update(json.dumps(a, sort_keys=True, default=str).encode())
    return h.hexdigest()


ART_DIRECTION = ("gi_intensity", "gi_color")


def recombine_key(scene) -> str:
    """Hash of everything but the art direction (light GI intensity and tint, the global
    intensity): equal keys let the add-on re-combine the worker's per-light grids itself.
    Broader than the engine's cache keys (engine.content_key / light_key), which leave the
    GI reflectance to the re-rendered RSMs: the add-on cannot render RSMs, so any material
    change goes to the worker."""
    settings = scene.settings.as_dict()
    settings.pop("intensity", None)
    lights = []
    for li in scene.lights:
        d = {k: v for k, v in li.__dict__.items() if k not in ART_DIRECTION}
        lights.append({k: (np.asarray(v).tolist() if isinstance(v, (np.ndarray, tuple)) else v)
                       for k, v in d.items()})
    mats = [(m.name, np.asarray(m.gi_reflectance()).tolist()) for m in scene.materials]
    clips = [(a.name, np.asarray(a.matrix).tolist()) for a in scene.areas if a.type == "CLIP"]
    return _hash(scene.positions, scene.normals, scene.material_index, scene.caster,
                 scene.occluder, settings, lights, mats, clips)


def extract(scene: bpy.types.Scene, depsgraph=None, overrides: dict | None = None):
    """The scene as the live viewport sees it (viewport visibility, no camera needed);
    ``overrides`` replace GI settings (GISettings names) on top of Scene.lpv."""
    from .extract import extract_scene

    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    return extract_scene(depsgraph, scene, settings_overrides=overrides, require_camera=False,
                         render_visibility=False)


def _geometry(scene) -> dict:
    return {
        "positions": scene.positions.astype(np.float32),
        "normals": scene.normals.astype(np.float32),
        "albedo": scene.albedo_per_triangle().astype(np.float32),
        "receiver": scene.flag("receiver"),
    }


def _recombine(scene, key: str, reasons: list[str], t0: float) -> LiveResult | None:
    """Re-weight the cached per-light grids when only art direction changed, else None."""
    cur = STATE.current
    if cur is None or cur.recombine_key != key or cur.grid is None or cur.fine:
        return None  # (inner cascades keep no per-light grids: those need the worker)
    weights = {li.name: li for li in scene.lights}
    needed = [li for li in scene.lights
              if li.gi_intensity != 0 and scene.settings.intensity != 0 and li.power > 0]
    if any(li.name not in cur.per_light for li in needed):
        return None  # a light that had no grid (GI intensity was 0) now needs one
    values = core.engine.combine(cur.grid, cur.per_light, list(weights.values()),
                                 scene.settings.intensity)
    if not needed:
        values = None
    stats = {"ms": {"combine": (time.perf_counter() - t0) * 1000.0}, "skipped": [
        {"stage": s, "what": "all lights",
         "reason": "only GI intensity or tint changed: re-combined cached per-light grids"}
        for s in ("rsm", "injection", "propagation")], "dropped": dict(scene.dropped),
        "info": dict(cur.stats.get("info", {})), "changed": list(reasons)}
    return _new_result(cur.grid, values, cur.per_light, scene, stats, key,
                       vpl=(cur.vpl_position, cur.vpl_flux), visibility=cur.visibility,
                       cosine_table=cur.cosine_table, gaps=cur.gaps)


def _new_result(grid, values, per_light, scene, stats, key, vpl=(None, None), visibility=None,
                cosine_table=None, fine=None, gaps=None) -> LiveResult:
    STATE.serial += 1
    return LiveResult(
        serial=STATE.serial, grid=grid, values=values, per_light=per_light,
        lights=list(scene.lights), settings=scene.settings, areas=list(scene.areas),
        geometry=_geometry(scene), vpl_position=vpl[0], vpl_flux=vpl[1], visibility=visibility,
        cosine_table=cosine_table, stats=stats, arrived=time.monotonic(), recombine_key=key,
        fine=list(fine or []), gaps=dict(gaps or {}),
    )


def _accept(result: LiveResult) -> None:
    STATE.previous = STATE.current
    STATE.current = result
    STATE.updates += 1
    STATE.error = ""


def _read_reply(reply: dict, scene, key: str, reasons: list[str], t_sent: float,
                path: str, t_extract: float) -> LiveResult:
    if not reply.get("ok"):
        raise WorkerError(reply.get("error", "unknown worker error"))
    data = np.load(path)
    grid = None
    if "origin" in data.files:
        grid = core.grid.Grid(tuple(float(v) for v in data["origin"]),
                              float(data["cell_size"]), int(data["resolution"]))
    names = json.loads(str(data["light_names"]))
    per_light = {n: data[f"light_{i}"] for i, n in enumerate(names)}
    values = data["values"] if "values" in data.files else None
    stats = dict(reply.get("stats", {}))
    stats.setdefault("ms", {})
    stats["ms"]["extract"] = t_extract
    stats["ms"]["round_trip"] = (time.perf_counter() - t_sent) * 1000.0
    stats["changed"] = list(reasons)
    opt = {k: (data[k] if k in data.files else None)
           for k in ("vpl_position", "vpl_flux", "visibility", "cosine_table")}
    gaps = {}  # keyed by the very Grid objects of the result
    if grid is not None and "gaps" in data.files:
        gaps[grid] = data["gaps"]
    fine = []
    for i in range(int(data["fine_count"]) if "fine_count" in data.files else 0):
        g = core.grid.Grid(tuple(float(v) for v in data[f"fine_{i}_origin"]),
                           float(data[f"fine_{i}_cell_size"]), int(data[f"fine_{i}_resolution"]))
        vis = data[f"fine_{i}_visibility"] if f"fine_{i}_visibility" in data.files else None
        fine.append((g, data[f"fine_{i}_values"], vis))
        if f"fine_{i}_gaps" in data.files:
            gaps[g] = data[f"fine_{i}_gaps"]
    return _new_result(grid, values, per_light, scene, stats, key,
                       vpl=(opt["vpl_position"], opt["vpl_flux"]), visibility=opt["visibility"],
                       cosine_table=opt["cosine_table"], fine=fine, gaps=gaps)


def refresh(scene: bpy.types.Scene, depsgraph=None, wait: bool = False,
            timeout: float = 300.0, overrides: dict | None = None) -> bool:
    """Start an LPV update for ``scene`` (or re-combine at once); with ``wait``, block until
    the new result is in. Returns True when a new result was accepted now. ``overrides``:
    GI settings on top of Scene.lpv (e.g. {"angular": "sh"})."""
    if STATE.pending is not None:
        if not wait:
            mark_dirty("edit while computing")
            return False  # the next tick sends the newest state
        wait_pending(timeout)
    reasons = list(STATE.reasons)
    STATE.dirty = False
    STATE.reasons = []
    t0 = time.perf_counter()
    core_scene = extract(scene, depsgraph, overrides)
    t_extract = (time.perf_counter() - t0) * 1000.0
    key = recombine_key(core_scene)
    quick = _recombine(core_scene, key, reasons, t0)
    if quick is not None:
        quick.stats["ms"]["extract"] = t_extract
        _accept(quick)
        return True
    worker = client()
    STATE.requests += 1
    name = f"scene_{STATE.requests}.npz"
    request = worker.path(name)
    reply_path = worker.path("reply_" + name)
    live_worker.save_scene(request, core_scene)
    rid = worker.send("update", scene=request, reply=reply_path)
    STATE.pending = (rid, key, core_scene, time.perf_counter(), reasons, reply_path, t_extract)
    STATE.last_sent = time.monotonic()
    if wait:
        return poll(worker.wait(rid, timeout))
    return False


def poll(reply: dict | None = None) -> bool:
    """Accept the pending result if it arrived (or is given). Returns True when a new result
    was accepted."""
    if STATE.pending is None or STATE.client is None:
        return False
    rid, key, core_scene, t_sent, reasons, reply_path, t_extract = STATE.pending
    try:
        reply = reply or STATE.client.reply(rid)
    except WorkerError as exc:
        STATE.pending = None
        STATE.error = str(exc)
        return False
    if reply is None:
        return False
    STATE.pending = None
    try:
        result = _read_reply(reply, core_scene, key, reasons, t_sent, reply_path, t_extract)
    except (WorkerError, OSError, KeyError, ValueError) as exc:
        STATE.error = str(exc)
        return False
    finally:
        for p in (reply_path, reply_path.replace("reply_", "")):
            try:
                os.unlink(p)
            except OSError:
                pass
    _accept(result)
    if reply.get("refresh_pending"):  # cascades were shifted for a camera move: refresh them
        mark_dirty("refresh after the cascades moved with the camera")
    return True


def wait_pending(timeout: float = 300.0) -> bool:
    """Block until the request in flight is answered and accept its result."""
    if STATE.pending is None or STATE.client is None:
        return False
    return poll(STATE.client.wait(STATE.pending[0], timeout))


def fade(props=None, now: float | None = None) -> float:
    """How far the current result has faded in, 0..1."""
    cur = STATE.current
    if cur is None:
        return 0.0
    t = float(getattr(props, "fade_time", 0.0)) if props is not None else 0.0
    if t <= 0 or STATE.previous is None:
        return 1.0
    now = time.monotonic() if now is None else now
    return float(min(1.0, max(0.0, (now - cur.arrived) / t)))


def viewports() -> list:
    return [area for _, area in _window_viewports()]


def _window_viewports() -> list:
    wm = getattr(bpy.context, "window_manager", None)
    out = []
    for win in getattr(wm, "windows", []) or []:
        screen = win.screen
        if screen is not None:
            out.extend((win, a) for a in screen.areas if a.type == "VIEW_3D")
    return out


def _target(require_viewport: bool):
    """(window or None, scene) the live engine follows: the scene of the first window with a
    3D viewport (timers run without a window context), else the context scene."""
    found = _window_viewports()
    if found:
        win = found[0][0]
        return win, win.scene
    if require_viewport:
        return None, None
    return None, getattr(bpy.context, "scene", None)


def tag_redraw() -> None:
    for area in viewports():
        area.tag_redraw()


def tick(require_viewport: bool = True) -> float:
    """One timer step: accept arrived results, start the next update, drive the fade-in.
    Returns the seconds until the next step."""
    win, scene = _target(require_viewport)
    props = getattr(scene, "lpv", None) if scene is not None else None
    if props is None:
        poll()
        return 1.0
    interval = float(props.refresh_interval)
    if not props.enabled or STATE.paused:
        return max(interval, 0.5)
    got = poll()
    if (props.live_update and STATE.dirty and STATE.pending is None
            and time.monotonic() - STATE.last_sent >= interval * 0.999):
        try:
            # The window's context gives the evaluated depsgraph of what it shows.
            ctx = bpy.context.temp_override(window=win) if win is not None \
                else contextlib.nullcontext()
            with ctx:
                got = refresh(scene) or got
        except (WorkerError, ValueError, OSError) as exc:
            STATE.error = str(exc)
    if got:
        tag_redraw()
    if STATE.current is not None and fade(props) < 1.0:
        tag_redraw()
        return min(1.0 / 30.0, interval)
    if STATE.pending is not None:
        return min(0.05, interval)
    return interval


def stats_lines(result: LiveResult | None = None) -> list[str]:
    """Human-readable statistics of a result: ms per stage, what changed, what was skipped."""
    result = result or STATE.current
    lines = []
    if STATE.error:
        lines.append(f"error: {STATE.error}")
    if result is None:
        lines.append("no LPV yet" + (" (updating...)" if STATE.pending else ""))
        return lines
    ms = result.stats.get("ms", {})
    order = ["extract", "upload", "rsm", "geometry_volume", "injection", "propagation", "combine",
             "lpv_update", "round_trip"]
    for key in order + sorted(k for k in ms if k not in order):
        if key in ms:
            lines.append(f"{key}: {ms[key]:.1f} ms")
    info = result.stats.get("info", {})
    if "vpls" in info:
        lines.append(f"VPLs: {info['vpls']}")
    if result.grid is not None:
        lines.append(f"grid: {result.grid.resolution}^3, cell {result.grid.cell_size:.3f} m")
    if result.stats.get("changed"):
        lines.append("changed: " + ", ".join(result.stats["changed"]))
    for s in result.stats.get("skipped", []):
        lines.append(f"skipped {s['stage']} ({s['what']}): {s['reason']}")
    return lines


# ---------------------------------------------------------------------------- batch job


class BatchJob:
    """Renders a frame range through the worker, one frame in flight at a time.

    Each frame: ``frame_set`` (animated values, e.g. a keyframed ``Scene.lpv.intensity``),
    extraction here, deferred render + EXR in the worker (files appear atomically), stats.json
    rewritten after every frame (same shape as the batch CLI's). Cancelling keeps every
    finished frame and removes the unfinished one.
    """

    def __init__(self, scene: bpy.types.Scene, out_dir, frames=None, resolution=None):
        self.scene_name = scene.name
        self.out = Path(bpy.path.abspath(str(out_dir)))
        first, last = frames or (scene.frame_start, scene.frame_end)
        if last < first:
            raise ValueError(f"frame range {first}-{last} is empty")
        self.frames = list(range(int(first), int(last) + 1))
        self.resolution = resolution
        self.done: list[int] = []
        self.record = {"scene": scene.name, "settings": None, "frames": []}
        self.original_frame = scene.frame_current
        self.worker: WorkerClient | None = None
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
        self.worker = WorkerClient()

    def _send(self, frame: int) -> None:
        from .extract import extract_scene

        scene = self.scene
        scene.frame_set(frame)
        t0 = time.perf_counter()
        depsgraph = bpy.context.evaluated_depsgraph_get()
        core_scene = extract_scene(depsgraph, scene, self.resolution)
        t_ex = (time.perf_counter() - t0) * 1000.0
        if self.record["settings"] is None:
            self.record["settings"] = core_scene.settings.as_dict()
        request = self.worker.path(f"frame_{frame}.npz")
        live_worker.save_scene(request, core_scene)
        rid = self.worker.send("render", scene=request, exr=str(self.out / f"{frame:04d}.exr"))
        self.pending = (rid, frame, t0, t_ex, core_scene.settings.intensity, request)

    def step(self, block: bool = False) -> bool:
        """Advance: collect a finished frame, send the next. Returns True while running."""
        if self.worker is None:
            self.start()
        if self.pending is not None:
            rid, frame, t0, t_ex, intensity, request = self.pending
            reply = self.worker.wait(rid) if block else self.worker.reply(rid)
            if reply is None:
                return True
            self.pending = None
            os.unlink(request)
            if not reply.get("ok"):
                self.error = f"frame {frame}: {reply.get('error')}"
                return False
            stats = reply.get("stats", {})
            stats.setdefault("ms", {})["extract"] = t_ex
            stats["ms"]["total"] = (time.perf_counter() - t0) * 1000.0
            self.record["frames"].append({"frame": frame, **stats, "intensity": intensity})
            self.done.append(frame)
            self._write_stats()
        if self.cancelled or self.error or len(self.done) == self.total:
            return False
        try:
            self._send(self.frames[len(self.done)])
        except (ValueError, WorkerError) as exc:
            self.error = str(exc)
            return False
        return True

    def _write_stats(self) -> None:
        from .batch import _write_json_atomic

        self.record["cancelled"] = self.cancelled
        _write_json_atomic(self.out / "stats.json", self.record)

    def cancel(self) -> None:
        """Stop now: the frame in flight is dropped, finished frames stay."""
        self.cancelled = True
        if self.pending is not None and self.worker is not None:
            self.worker.kill()
            self.worker = None
            self.pending = None
            for tmp in self.out.glob(".*.tmp"):
                tmp.unlink(missing_ok=True)
        self._write_stats()

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
            self.worker = None
        try:
            self.scene.frame_set(self.original_frame)
        except ValueError:
            pass

    def run(self) -> None:
        """Render every frame, blocking (scripts, headless)."""
        try:
            while self.step(block=True):
                pass
        finally:
            self.close()
        if self.error:
            raise ValueError(self.error)


def render_passes(scene: bpy.types.Scene, resolution, worker: WorkerClient | None = None,
                  timeout: float = 600.0, overrides: dict | None = None) -> tuple[dict, dict]:
    """LPV passes ({Cycles pass name: (H, W, C)}) and stats of ``scene``'s camera view."""
    from .extract import extract_scene

    own = worker is None
    worker = worker or WorkerClient()
    try:
        core_scene = extract_scene(bpy.context.evaluated_depsgraph_get(), scene, resolution,
                                   overrides)
        request, out = worker.path("compare.npz"), worker.path("compare_passes.npz")
        live_worker.save_scene(request, core_scene)
        reply = worker.wait(worker.send("render", scene=request, passes=out), timeout)
        if not reply.get("ok"):
            raise WorkerError(reply.get("error", "unknown worker error"))
        data = np.load(out)
        passes = {k.replace("_", " "): data[k] for k in data.files}
        return passes, reply.get("stats", {})
    finally:
        if own:
            worker.close()
