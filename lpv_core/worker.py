"""Long-running LPV worker for Blender's UI: ``python -m lpv_core.worker``.

moderngl inside Blender's process breaks Blender's drawing (measured: the wrong context, then an abort on release), so the live viewport
and the UI's batch/compare operators run the whole engine here, in a child process that keeps
its GL context, rasteriser and shader cache warm between requests.

Protocol: one JSON object per line on stdin, one JSON reply per line on stdout (library prints
go to stderr). Bulk arrays travel as .npz files in a folder the client owns:

    {"id": 1, "cmd": "update", "scene": "in.npz", "reply": "out.npz"}
        -> {"id": 1, "ok": true, "stats": {...}, "has_gi": true}
           out.npz: grid origin/cell_size/resolution, values (R,R,R,3,K) float32 (K = 9 SH
           coefficients for angular="dom", else 4), per-light and inner-cascade grids of
           the same K, a VPL sample, the propagation visibility (occlusion, clip areas) and
           the occluders' cell gaps (geometry_volume.cell_gaps, lookup.gap_corrected) if any
    {"id": 2, "cmd": "render", "scene": "in.npz", "exr": "f.exr", "passes": "p.npz"}
        -> deferred render of the scene's camera: EXR (atomic) and/or passes npz
    {"id": 3, "cmd": "ping"} -> {"id": 3, "ok": true, "pid": ...}
    {"id": 4, "cmd": "quit"}
Every reply carries "kernels" (runtime/warmup.py: "state" off, waiting, compiling, ready or
failed; "compiled" of "of" kernels; "seconds"): on a cold kernel cache the numpy reference
serves while a child compiles. Errors, a line that is not a JSON object or an unknown command
included, reply {"id": n, "ok": false, "error": "one line"}; the worker keeps serving. It exits
on "quit" or when stdin closes (the parent went away).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import sys
import traceback

import numpy as np

from .runtime import warmup
from .scene import textures
from .scene.model import LIGHT_TYPES, Area, Camera, GISettings, Light, Material, Scene
from .scene.world import World

# ------------------------------------------------------------------------ scene <-> npz


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, tuple):
        return list(value)
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def _as_json(obj) -> dict:
    return {k: _plain(v) for k, v in dataclasses.asdict(obj).items()}


TEXTURE_FOLDER = "textures"  # beside the scene file: one <digest>.npy per texture
TEXTURE_KEYS = ("texture", "alpha_texture", "normal_texture")  # Material's images


def _material_json(material: Material, folder: str) -> dict:
    """A material's fields as JSON, its texture by digest: the pixels go to ``folder`` as
    <digest>.npy, written only when that file is not there yet (each texture sent once)."""
    out = _as_json(dataclasses.replace(material, **dict.fromkeys(TEXTURE_KEYS)))
    for key in TEXTURE_KEYS:
        tex = getattr(material, key)
        if tex is None:
            continue
        digest = textures.digest_of(tex)
        out[key] = {"name": tex.name, "interpolation": tex.interpolation,
                    "extension": tex.extension, "digest": digest}
        file = os.path.join(folder, digest + ".npy")
        if not os.path.exists(file):
            os.makedirs(folder, exist_ok=True)
            tmp = file + ".tmp.npy"
            np.save(tmp, np.ascontiguousarray(tex.pixels, np.float32))
            os.replace(tmp, file)
    return out


def _world_json(world, folder: str) -> dict | None:
    """The World's fields as JSON, its radiance map by digest in ``folder`` like a texture's
    (written once per digest)."""
    if world is None:
        return None
    radiance = np.ascontiguousarray(world.radiance, np.float32)
    digest = world.digest or hashlib.blake2b(radiance.tobytes(), digest_size=16).hexdigest()
    file = os.path.join(folder, digest + ".npy")
    if not os.path.exists(file):
        os.makedirs(folder, exist_ok=True)
        np.save(file + ".tmp.npy", radiance)
        os.replace(file + ".tmp.npy", file)
    return {"name": world.name, "gi_intensity": float(world.gi_intensity),
            "enabled": bool(world.enabled), "digest": digest}


TEXTURE_FILES_BYTES = 4 * textures.BUDGET_BYTES  # the texture folder's size before pruning


def _prune_textures(folder: str, used: set) -> None:
    """Remove the oldest texture files this scene does not use while the folder holds more
    than TEXTURE_FILES_BYTES (a texture painted on writes a file per change)."""
    try:
        entries = [e for e in os.scandir(folder) if e.name.endswith(".npy")]
    except FileNotFoundError:
        return
    total = sum(e.stat().st_size for e in entries)
    for e in sorted(entries, key=lambda e: e.stat().st_mtime):
        if total <= TEXTURE_FILES_BYTES:
            break
        if e.name[:-4] not in used:
            size = e.stat().st_size
            try:
                os.unlink(e.path)
            except OSError:  # Windows: still mapped by the worker; the next save retries
                continue
            total -= size


def save_scene(path: str, scene: Scene) -> None:
    """Write a core Scene (everything the engine and the deferred renderer use) to ``path``;
    texture pixels and the World's map to TEXTURE_FOLDER beside it, once per digest
    (_material_json, _world_json)."""
    arrays = {
        "positions": scene.positions, "normals": scene.normals,
        "material_index": scene.material_index,
    }
    for name in ("caster", "occluder", "receiver", "object_index", "uvs", "corner_colors",
                 "tangents", "ray_hidden"):
        value = getattr(scene, name)
        if value is not None:
            arrays[name] = np.asarray(value)
    folder = os.path.join(os.path.dirname(os.path.abspath(path)), TEXTURE_FOLDER)
    meta = {
        "materials": [_material_json(m, folder) for m in scene.materials],
        "lights": [_as_json(li) for li in scene.lights],
        "areas": [_as_json(a) for a in scene.areas],
        "settings": scene.settings.as_dict(),
        "object_names": list(scene.object_names),
        "dropped": dict(scene.dropped),
        "approximated": list(scene.approximated),
        "film_transparent": bool(scene.film_transparent),
        "camera": None if scene.camera is None else _as_json(scene.camera),
        "world": _world_json(scene.world, folder),
    }
    arrays["meta"] = np.array(json.dumps(meta))
    used = {m[k]["digest"] for m in meta["materials"] for k in TEXTURE_KEYS if m.get(k)}
    used |= {meta["world"]["digest"]} if meta["world"] else set()
    if used:
        _prune_textures(folder, used)
    tmp = path + ".tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def _dataclass(cls, data: dict, arrays: dict):
    names = {f.name for f in dataclasses.fields(cls)}
    kw = {k: v for k, v in data.items() if k in names}
    for key, dtype in arrays.items():
        if kw.get(key) is not None:
            kw[key] = np.asarray(kw[key], dtype)
    return cls(**kw)


def load_scene(path: str, held: dict | None = None) -> Scene:
    """The Scene save_scene wrote. ``held``: digest -> texture pixels this process already
    has (read from the texture folder only when missing; left holding this scene's)."""
    data = np.load(path)
    meta = json.loads(str(data["meta"]))
    folder = os.path.join(os.path.dirname(os.path.abspath(path)), TEXTURE_FOLDER)
    known = dict(held or {})
    materials = []
    for m in meta["materials"]:
        texs = {key: m.pop(key, None) for key in TEXTURE_KEYS}
        material = _dataclass(Material, m, {"albedo": np.float32, "bleed_color": np.float32,
                                            "emission": np.float32, "specular": np.float32,
                                            "diffuse_share": np.float32})
        for key, tex in texs.items():
            if tex is None:
                continue
            pixels = known.get(tex["digest"])
            if pixels is None:  # mapped, not read: the engine's fitted copy is what it holds
                pixels = np.load(os.path.join(folder, tex["digest"] + ".npy"), mmap_mode="r")
                known[tex["digest"]] = pixels
            setattr(material, key, textures.Texture(tex["name"], pixels, tex["interpolation"],
                                                    tex["extension"], tex["digest"]))
        materials.append(material)
    world = meta.get("world")
    if world is not None:
        radiance = known.get(world["digest"])
        if radiance is None:
            radiance = np.load(os.path.join(folder, world["digest"] + ".npy"))
        world = World(world["name"], radiance, world["gi_intensity"], world["enabled"],
                      world["digest"])
    if held is not None:
        held.clear()
        held.update({t.digest: t.pixels for m in materials
                     for t in (getattr(m, k) for k in TEXTURE_KEYS) if t is not None})
        if world is not None:
            held[world.digest] = world.radiance
    lights = []
    for d in meta["lights"]:
        light = _dataclass(Light, d, {"matrix": np.float64, "color": np.float32,
                                      "gi_color": np.float32})
        light.size = tuple(light.size)
        lights.append(light)
    areas = [_dataclass(Area, a, {"matrix": np.float64, "tint": np.float32})
             for a in meta["areas"]]
    camera = None
    if meta["camera"] is not None:
        camera = _dataclass(Camera, meta["camera"], {"view": np.float64,
                                                     "projection": np.float64})
        camera.resolution = tuple(int(v) for v in camera.resolution)
    settings = GISettings().updated(**{k: v for k, v in meta["settings"].items()
                                       if k in GISettings.__dataclass_fields__})
    opt = {k: (data[k] if k in data.files else None)
           for k in ("caster", "occluder", "receiver", "object_index", "uvs", "corner_colors",
                     "tangents", "ray_hidden")}
    return Scene(
        positions=data["positions"], normals=data["normals"],
        material_index=data["material_index"], materials=materials, lights=lights,
        camera=camera, settings=settings, object_names=meta["object_names"],
        dropped=meta["dropped"], areas=areas, approximated=meta.get("approximated", []),
        film_transparent=bool(meta.get("film_transparent", False)),
        world=world,
        **opt,
    )


# ----------------------------------------------------------------------------- replies


def save_result(path: str, result, scene: Scene) -> None:
    """Write an LPVResult for the viewport: combined, per-light and inner-cascade grids
    ((R,R,R,3,K) float32, K = 4 or 9 coefficients, written as they are), VPLs, visibility,
    the cell gaps of each cascade ("gaps", "fine_{i}_gaps": (6,R,R,R) float32) where not None."""
    out = {}
    if result.grid is not None:
        out["origin"] = np.asarray(result.grid.origin, np.float64)
        out["cell_size"] = np.float64(result.grid.cell_size)
        out["resolution"] = np.int64(result.grid.resolution)
    if result.values is not None:
        out["values"] = result.values.astype(np.float32)
    names = sorted(result.per_light)
    out["light_names"] = np.array(json.dumps(names))
    for i, name in enumerate(names):
        out[f"light_{i}"] = result.per_light[name].astype(np.float32)
    vp = [result.vpls[n] for n in sorted(getattr(result, "vpls", {}) or {})]
    if vp:
        out["vpl_position"] = np.concatenate([p for p, _ in vp]).astype(np.float32)
        out["vpl_flux"] = np.concatenate([f for _, f in vp]).astype(np.float32)
    visibility = getattr(result, "visibility", None)
    if isinstance(visibility, np.ndarray):
        out["visibility"] = visibility.astype(np.float32)  # (6, R, R, R): lookups use it
    gaps = getattr(result, "gaps", None) or {}
    if result.grid is not None and gaps.get(result.grid) is not None:
        out["gaps"] = np.asarray(gaps[result.grid], np.float32)  # (6, R, R, R)
    fine = list(getattr(result, "fine", None) or [])  # inner cascades, finest first
    out["fine_count"] = np.int64(len(fine))
    for i, (grid, values, vis) in enumerate(fine):
        out[f"fine_{i}_origin"] = np.asarray(grid.origin, np.float64)
        out[f"fine_{i}_cell_size"] = np.float64(grid.cell_size)
        out[f"fine_{i}_resolution"] = np.int64(grid.resolution)
        out[f"fine_{i}_values"] = np.asarray(values, np.float32)
        if vis is not None:
            out[f"fine_{i}_visibility"] = np.asarray(vis, np.float32)
        if gaps.get(grid) is not None:
            out[f"fine_{i}_gaps"] = np.asarray(gaps[grid], np.float32)
    for i, values in enumerate(getattr(result, "whole", None) or []):
        out[f"whole_{i}"] = np.asarray(values, np.float32)  # cascades.whole, past the finest
    tmp = path + ".tmp.npz"
    np.savez(tmp, **out)
    os.replace(tmp, path)


class Server:
    """Serves requests with one Engine (GL context and rasteriser stay warm)."""

    def __init__(self):
        from .engine import Engine

        self.warm = warmup.Warmup()  # before the engine's first stage: kernels off if cold
        self.engine = Engine()
        self.textures: dict = {}  # digest -> pixels of the last scene's textures (load_scene)

    def handle(self, req: dict) -> dict:
        from .engine import Stats
        from .render import deferred, exr

        cmd = req.get("cmd")
        self.warm.poll()  # the compiled kernels take over between requests
        if cmd == "ping":
            return {"pid": os.getpid()}
        if cmd not in ("update", "render"):
            raise ValueError(f"unknown command {cmd!r} (update, render, ping, quit)")
        scene = load_scene(req["scene"], self.textures)
        stats = Stats()
        # Interactive updates may shift cascades for a camera move and refresh afterwards.
        result = self.engine.update(scene, stats, reproject=cmd == "update")
        self.warm.start(req["scene"], scene)  # after this scene's result: the CPU is ours first
        if cmd == "update":
            save_result(req["reply"], result, scene)
            return {"stats": stats.as_dict(), "has_gi": result.values is not None,
                    "refresh_pending": bool(stats.info.get("refresh_pending"))}
        if cmd == "render":
            passes = deferred.render(self.engine, scene, result, stats)
            if req.get("exr"):
                exr.write_multilayer(req["exr"], passes)
            if req.get("passes"):
                tmp = req["passes"] + ".tmp.npz"
                np.savez(tmp, **{k.replace(" ", "_"): v for k, v in passes.items()})
                os.replace(tmp, req["passes"])
        return {"stats": stats.as_dict(), "has_gi": result.values is not None}


def warm_up(path: str) -> int:
    """The warm-up child (runtime/warmup.py): the engine on the worker's first scene, with every
    light type, one and two cascades and a camera, so that the kernels a later scene needs are
    compiled too."""
    import dataclasses
    import threading
    import time

    from .engine import Engine, Stats
    from .render import deferred

    proto = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1, encoding="utf-8")
    sys.stdout = sys.stderr
    if hasattr(os, "nice"):
        os.nice(10)  # the worker's numpy reference first
    # The worker went away (its pipe closed): stop compiling for nobody.
    threading.Thread(target=lambda: (sys.stdin.read(), os._exit(3)), daemon=True).start()

    def report():
        while True:
            proto.write(json.dumps({"compiled": warmup.compiled()}) + "\n")
            time.sleep(0.5)

    threading.Thread(target=report, daemon=True).start()
    t0 = time.monotonic()
    try:
        scene = load_scene(path)
        os.unlink(path)
        points = scene.positions.reshape(-1, 3)
        lo, hi = points.min(0), points.max(0)
        at = np.eye(4)
        at[:3, 3] = (lo + hi) / 2
        # a scene lit only by the World or emitters still compiles the lamps' kernels
        template = scene.lights[0] if scene.lights else Light("warm-up", "POINT", at)
        scene.lights += [dataclasses.replace(template, name=f"warm-up {t}", type=t)
                         for t in LIGHT_TYPES if t not in {li.type for li in scene.lights}]
        if scene.world is None:  # and the sky's kernel
            scene.world = World("warm-up", np.full((1, 1, 3), 0.05, np.float32))
        scene.camera = Camera.look_at(hi + (hi - lo), (lo + hi) / 2, resolution=(16, 16))
        engine = Engine()
        engine.update(scene, Stats())
        scene.settings = scene.settings.updated(cascades_auto=False, cascades=2)  # hand-on too
        deferred.render(engine, scene, engine.update(scene, Stats()), Stats())
    except Exception as exc:  # noqa: BLE001 - the worker reports it and stays on numpy
        traceback.print_exc(file=sys.stderr)
        proto.write(json.dumps({"error": f"{type(exc).__name__}: {exc}"[:300]}) + "\n")
        return 1
    warmup.mark_ready(round(time.monotonic() - t0, 1))
    proto.write(json.dumps({"compiled": warmup.compiled()}) + "\n")
    return 0


def _request(line: str) -> dict:
    """One request line as a JSON object, else ValueError or TypeError saying why not."""
    try:
        req = json.loads(line)
    except json.JSONDecodeError as exc:
        raise ValueError(f"bad request: not JSON ({exc})") from None
    if not isinstance(req, dict):
        raise TypeError(f"bad request: a JSON object per line, not {type(req).__name__}")
    return req


def main() -> int:
    if sys.argv[1:2] == ["--warm-up"]:
        return warm_up(sys.argv[2])
    # Replies go to the real stdout; anything a library prints goes to stderr.
    proto = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1, encoding="utf-8")
    sys.stdout = sys.stderr
    server = None
    for line in sys.stdin:
        if not line.strip():
            continue
        rid = None
        try:
            req = _request(line)
            rid = req.get("id") if isinstance(req.get("id"), (int, str)) else None
            if req.get("cmd") == "quit":
                proto.write(json.dumps({"id": rid, "ok": True}) + "\n")
                break
            if server is None:
                server = Server()
            reply = {"id": rid, "ok": True, **server.handle(req)}
        except Exception as exc:  # noqa: BLE001 - every failure becomes a one-line reply
            traceback.print_exc(file=sys.stderr)
            msg = str(exc).strip().splitlines()
            reply = {"id": rid, "ok": False,
                     "error": f"{type(exc).__name__}: {msg[-1] if msg else ''}"}
        if server is not None:
            reply["kernels"] = server.warm.status()
        proto.write(json.dumps(reply) + "\n")
    if server is not None:
        server.warm.stop()
        if server.engine._raster is not None:
            server.engine._raster.release()
    return 0


if __name__ == "__main__":
    sys.exit(main())
