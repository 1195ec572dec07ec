"""The live LPV behind the viewport overlay: what changed, requests to the worker, results.

The engine runs in one long-lived worker process (:mod:`..worker_client`) that keeps its GL
context warm. This side extracts the scene with bpy, sends it, and keeps the LPV grids that
come back as plain data (:class:`LiveResult`); the overlay (``overlay.py``) reads them and owns
every GPU resource made from them.

Planning (what is recomputed, what is skipped and why):
- depsgraph/frame handlers and property updates call :func:`mark_dirty` with what changed;
- a timer calls :func:`tick` every ``Scene.lpv.refresh_interval`` seconds: while a request is
  in flight nothing new is sent (the newest state goes next); when only art-direction values
  changed (light GI intensity/tint, global intensity) the cached per-light grids are
  re-combined here in numpy (propagation is linear), no RSM, injection or propagation;
- a new result fades in over ``Scene.lpv.fade_time`` (the overlay blends old and new);
- a worker that stopped, or has not answered within :func:`deadline`, is said so in the stats
  lines, replaced by a new one and sent the scene again (MAX_RESTARTS in a row at most);
- while the worker's CPU kernels compile (its numpy reference serves meanwhile) pings follow the
  progress, shown in the stats lines and Blender's status bar.
No bpy object is stored: results hold arrays and names only (undo and file loads are safe).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from dataclasses import dataclass, field

import bpy
import numpy as np

from .._core import core
from ..scene_io.extract import extract_scene
from ..worker_client import WorkerClient, WorkerError

MAX_REASONS = 12
# A reply later than this (x the grid's cells / 64^3, numpy's reference takes 24 s at 64^3 on
# two cores) means the worker is stuck: the kernels compile in another process, never here.
DEADLINE_S = 120.0
MAX_RESTARTS = 3


# --------------------------------------------------------------------------- live state


@dataclass
class LiveResult:
    """One LPV result as the overlay draws it (arrays only, no bpy data)."""

    serial: int
    grid: object  # core.grid.Grid or None
    values: np.ndarray | None  # combined (R, R, R, 3, 9): SH bands 0-2 per colour
    per_light: dict  # light name -> (R, R, R, 3, 9)
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
    whole: list = field(default_factory=list)  # cascades.whole past the finest (finest first)
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
        self.kernels: dict = {}  # the worker's last kernel status (lpv_core.runtime.warmup)
        self.ping = None  # request id of a kernel status ping in flight
        self.restarts = 0  # worker restarts since the last accepted result
        self.status = None  # our text in Blender's status bar (None: Blender's own)


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
    """Stop the worker and drop every result (unregister, file load); the GPU resources made
    from them are the overlay's to free (``handlers.reset``)."""
    if STATE.client is not None:
        STATE.client.close()
    STATE.client = None
    STATE.pending = None
    STATE.current = STATE.previous = None
    STATE.dirty = True
    STATE.reasons = ["reset"]
    STATE.error = ""
    STATE.kernels, STATE.ping, STATE.restarts = {}, None, 0
    status_bar(None)


def deadline(settings) -> float:
    """Seconds a reply may take before the worker counts as stuck (DEADLINE_S)."""
    return DEADLINE_S * max(1.0, (int(getattr(settings, "grid_resolution", 16)) / 64) ** 3)


def restart(reason: str) -> None:
    """The worker stopped or hangs: say so in the UI, stop it, and (MAX_RESTARTS in a row at
    most) let the next tick send the scene to a new one."""
    if STATE.client is not None:
        STATE.client.kill()
    STATE.client, STATE.pending, STATE.ping = None, None, None
    STATE.restarts += 1
    again = STATE.restarts <= MAX_RESTARTS
    STATE.error = reason + ("; restarted it" if again else
                            f"; gave up after {MAX_RESTARTS} restarts: Update to retry")
    if again:
        mark_dirty("worker restarted")


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
    mats = [(m.name, np.asarray(m.gi_reflectance()).tolist(),
             *([np.asarray(m.specular).tolist()] if np.any(m.specular) else []))
            for m in scene.materials]
    clips = [(a.name, np.asarray(a.matrix).tolist()) for a in scene.areas if a.type == "CLIP"]
    return _hash(scene.positions, scene.normals, scene.material_index, scene.caster,
                 scene.occluder, settings, lights, mats, clips)


def extract(scene: bpy.types.Scene, depsgraph=None, overrides: dict | None = None):
    """The scene as the live viewport sees it (viewport visibility, no camera needed);
    ``overrides`` replace GI settings (GISettings names) on top of Scene.lpv."""
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    return extract_scene(depsgraph, scene, settings_overrides=overrides, require_camera=False,
                         render_visibility=False)


_TEXTURES = core.scene.textures.Store()  # the overlay's textures, fitted once per digest


def _geometry(scene) -> dict:
    """What the overlay draws: triangles, albedo (per corner with corner colours), receiver
    flags and, where materials have textures, each triangle's texture, the UVs and the
    textures fitted to the budget (the same textures.sample rules as the render's); where
    materials have a view-angle share, each triangle's row (-1 none) of the stacked tables
    (textures.view_shares, as the render applies them)."""
    geo = {
        "positions": scene.positions.astype(np.float32),
        "normals": scene.normals.astype(np.float32),
        "albedo": scene.albedo_per_triangle().astype(np.float32),
        "receiver": scene.flag("receiver"),
    }
    lay = core.scene.textures.layout(scene.materials, scene.material_index, scene.uvs,
                                     scene.corner_colors)
    if lay is not None:
        if lay.corner_colors is not None:
            geo["albedo"] = geo["albedo"][:, None, :] * lay.corner_colors
        if lay.textures:
            geo["texture"], geo["uvs"] = lay.albedo_texture, lay.uvs
            geo["textures"] = _TEXTURES.fitted(lay)
    shares = core.scene.textures.view_shares(scene.materials, scene.material_index)
    if shares is not None:
        geo["share"], geo["shares"] = shares
    return geo


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
                       gaps=cur.gaps)


def _new_result(grid, values, per_light, scene, stats, key, vpl=(None, None), visibility=None,
                fine=None, gaps=None, whole=None) -> LiveResult:
    STATE.serial += 1
    return LiveResult(
        serial=STATE.serial, grid=grid, values=values, per_light=per_light,
        lights=list(scene.lights), settings=scene.settings, areas=list(scene.areas),
        geometry=_geometry(scene), vpl_position=vpl[0], vpl_flux=vpl[1], visibility=visibility,
        stats=stats, arrived=time.monotonic(), recombine_key=key,
        fine=list(fine or []), gaps=dict(gaps or {}), whole=list(whole or []),
    )


def _accept(result: LiveResult) -> None:
    STATE.previous = STATE.current
    STATE.current = result
    STATE.updates += 1
    STATE.error = ""
    STATE.restarts = 0


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
           for k in ("vpl_position", "vpl_flux", "visibility")}
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
    whole = [data[f"whole_{i}"] for i in range(len(fine)) if f"whole_{i}" in data.files]
    return _new_result(grid, values, per_light, scene, stats, key,
                       vpl=(opt["vpl_position"], opt["vpl_flux"]), visibility=opt["visibility"],
                       fine=fine, gaps=gaps, whole=whole)


def refresh(scene: bpy.types.Scene, depsgraph=None, wait: bool = False,
            timeout: float = 300.0, overrides: dict | None = None) -> bool:
    """Start an LPV update for ``scene`` (or re-combine at once); with ``wait``, block until
    the new result is in. Returns True when a new result was accepted now. ``overrides``:
    GI settings on top of Scene.lpv (e.g. {"grid_resolution": 24})."""
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
    reply_path = worker.path("reply_" + name)
    rid, _ = worker.send_scene("update", core_scene, name, reply=reply_path)
    STATE.pending = (rid, key, core_scene, time.perf_counter(), reasons, reply_path, t_extract)
    STATE.last_sent = time.monotonic()
    return _wait(rid, timeout) if wait else False


def _wait(rid: int, timeout: float) -> bool:
    try:
        reply = STATE.client.wait(rid, timeout)
    except WorkerError as exc:
        restart(str(exc))
        raise
    return poll(reply)


def poll(reply: dict | None = None) -> bool:
    """Accept the pending result if it arrived (or is given). Returns True when a new result
    was accepted."""
    if STATE.pending is None or STATE.client is None:
        return False
    rid, key, core_scene, t_sent, reasons, reply_path, t_extract = STATE.pending
    try:
        reply = reply or STATE.client.reply(rid)
    except WorkerError as exc:
        restart(f"the LPV worker stopped ({exc})")
        return False
    if reply is None:
        late = time.perf_counter() - t_sent
        if late > deadline(core_scene.settings):
            restart(f"the LPV worker did not answer within {late:.0f} s")
        return False
    STATE.pending = None
    STATE.kernels = reply.get("kernels", STATE.kernels)
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
    return _wait(STATE.pending[0], timeout)


def _follow_kernels() -> bool:
    """While the worker's kernels compile, ping it about once a second for their progress.
    True when new progress arrived."""
    if STATE.client is None or STATE.kernels.get("state") != "compiling":
        return False
    try:
        if STATE.ping is None and STATE.pending is None:
            STATE.ping = STATE.client.send("ping")
            return False
        reply = STATE.client.reply(STATE.ping) if STATE.ping is not None else None
    except WorkerError:  # gone: the next refresh starts a new one
        STATE.ping = None
        return False
    if reply is not None:
        STATE.kernels, STATE.ping = reply.get("kernels", {}), None
    return reply is not None


def kernel_text() -> str | None:
    """One line on the worker's compiled kernels while they are not running, else None."""
    k = STATE.kernels
    if k.get("state") == "compiling":
        return (f"LPV GI: compiling CPU kernels ({k['compiled']} of {k['of']}, "
                f"{k['seconds']:.0f} s); the numpy reference serves meanwhile")
    if k.get("state") == "failed":
        return f"LPV GI: CPU kernels failed ({k.get('error')}); the numpy reference serves"
    return None


def status_bar(text: str | None) -> None:
    """Show ``text`` in Blender's status bar (None: give it back to Blender)."""
    if text == STATE.status:
        return
    for win, _area in _window_viewports():
        with contextlib.suppress(AttributeError, RuntimeError, ReferenceError):
            win.workspace.status_text_set(text)
    STATE.status = text


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
        status_bar(None)
        return max(interval, 0.5)
    got = poll()
    if _follow_kernels():
        tag_redraw()
    status_bar(kernel_text() if STATE.kernels.get("state") == "compiling" else None)
    if (props.live_update and STATE.dirty and STATE.pending is None
            and time.monotonic() - STATE.last_sent >= interval * 0.999):
        try:
            # The window's context gives the evaluated depsgraph of what it shows.
            ctx = bpy.context.temp_override(window=win) if win is not None \
                else contextlib.nullcontext()
            with ctx:
                got = refresh(scene) or got
        except WorkerError as exc:
            restart(str(exc))
        except (ValueError, OSError) as exc:
            STATE.error = str(exc)
    if got:
        tag_redraw()
    if STATE.current is not None and fade(props) < 1.0:
        tag_redraw()
        return min(1.0 / 30.0, interval)
    if STATE.pending is not None or STATE.ping is not None:
        return min(0.05, interval)
    return min(1.0, interval) if STATE.status else interval


def stats_lines(result: LiveResult | None = None) -> list[str]:
    """Human-readable statistics of a result: ms per stage, what changed, what was skipped."""
    result = result or STATE.current
    lines = []
    if STATE.error:
        lines.append(f"error: {STATE.error}")
    if kernel_text():
        lines.append(kernel_text().removeprefix("LPV GI: "))
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


