"""Build the team's scenes and render their Cycles references (multi-layer EXR).

    python tools/make_references.py --out DIR [--samples N] [--bounces B]
        [--scenes cornell_spot,cornell_point,cornell_sun,point_room,sun_yard] [--resolution WxH]

writes DIR/<scene>.blend and DIR/<scene>_ref_b<B>.exr per scene (progress on stderr).

``ensure_reference()`` is the cached form for tests and reports: it returns (blend, exr) paths
in a cache folder and builds/renders only on a miss. The work runs in a SUBPROCESS of the
Python interpreter (default: sys.executable, the venv's), so the caller's bpy state (its open
file, scenes, settings) is never touched and a caller without bpy works too. The key of the
cache is the scene *content* hash (tools/scene_hash.py) plus samples and bounces,
computed in the child after building; a small manifest (references.json) maps (scene,
resolution, samples, bounces, source digest of the scene/render code, bpy version) to that
hash, so a warm cache answers without starting a child at all.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENES = ("cornell_spot", "cornell_point", "cornell_sun", "point_room", "sun_yard")
DEFAULT_SAMPLES = 1024
MANIFEST = "references.json"
_SOURCES = ("tools/scenes.py", "lpv_addon/scene_io/demo.py", "lpv_addon/render/cycles.py",
            "tools/scene_hash.py", "tools/make_references.py")


def _log(msg: str) -> None:
    print(f"[make_references] {msg}", file=sys.stderr, flush=True)


def _parse_resolution(text: str | None) -> tuple[int, int] | None:
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like 128x96, not {text!r}")
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"resolution must be positive: {text!r}")
    return w, h


def _import_bpy_side():
    """Import bpy and our bpy modules (isolated Blender user config unless one is set)."""
    os.environ.setdefault(
        "BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_make_refs_blender_")
    )
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from lpv_addon.render import cycles
    from tools import scene_hash, scenes

    return scenes, cycles, scene_hash


def make(
    out: Path, names: list[str], samples: int, bounces: int,
    resolution: tuple[int, int] | None,
) -> list[dict]:
    """Build, save and render each named scene into ``out`` (the CLI's plain mode)."""
    scenes, cycles, _ = _import_bpy_side()
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for i, name in enumerate(names, 1):
        kw = {} if resolution is None else {"resolution": resolution}
        _log(f"[{i}/{len(names)}] {name}: building")
        facts = scenes.save_scene(name, out / f"{name}.blend", **kw)
        w, h = facts["resolution"]
        _log(f"[{i}/{len(names)}] {name}: rendering {w}x{h}, {samples} samples, "
             f"{bounces} diffuse bounce(s)")
        info = cycles.render_cycles_passes(
            out / f"{name}_ref_b{bounces}.exr", samples=samples, diffuse_bounces=bounces
        )
        _log(f"[{i}/{len(names)}] {name}: {info['seconds']:.1f} s -> {info['path']}")
        results.append({"scene": name, "blend": facts["path"], **info})
    return results


def _cached_one(
    out: Path, name: str, samples: int, bounces: int, resolution: tuple[int, int] | None
) -> dict:
    """Child side of ensure_reference: build, hash, save and render only what is missing."""
    scenes, cycles, scene_hash = _import_bpy_side()
    import bpy

    out.mkdir(parents=True, exist_ok=True)
    kw = {} if resolution is None else {"resolution": resolution}
    facts = scenes.build(name, **kw)
    digest = scene_hash.scene_hash()
    exr = scene_hash.reference_path(out, digest, samples, bounces)
    blend = out / f"{name}_{digest[:20]}.blend"
    if not blend.is_file():
        tmp = blend.with_name(f".{blend.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.blend")
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True, check_existing=False)
        os.replace(tmp, blend)
    seconds = None
    if exr.is_file():
        _log(f"{name}: cached reference {exr.name}")
    else:
        _log(f"{name}: rendering {facts['resolution']}, {samples} samples, b{bounces}")
        seconds = cycles.render_cycles_passes(exr, samples=samples,
                                              diffuse_bounces=bounces)["seconds"]
        _log(f"{name}: {seconds:.1f} s -> {exr}")
    return {"scene": name, "hash": digest, "blend": str(blend), "exr": str(exr),
            "seconds": seconds, "resolution": list(facts["resolution"])}


# ---------------------------------------------------------------------------------------------
# Parent side (no bpy import here)
# ---------------------------------------------------------------------------------------------


def _source_digest() -> str:
    h = hashlib.sha256()
    for rel in _SOURCES:
        h.update(rel.encode())
        h.update((ROOT / rel).read_bytes())
    from importlib.metadata import PackageNotFoundError, version

    try:
        h.update(version("bpy").encode())
    except PackageNotFoundError:  # bpy not installed as a distribution (e.g. inside Blender)
        h.update(b"no-bpy-dist")
    return h.hexdigest()


def _manifest_key(name: str, samples: int, bounces: int,
                  resolution: tuple[int, int] | None) -> str:
    res = "default" if resolution is None else f"{resolution[0]}x{resolution[1]}"
    return f"{name}|{res}|s{samples}|b{bounces}|{_source_digest()[:16]}"


def _read_manifest(cache_dir: Path) -> dict:
    try:
        return json.loads((cache_dir / MANIFEST).read_text())
    except (FileNotFoundError, ValueError):
        return {}


def _write_manifest(cache_dir: Path, key: str, entry: dict) -> None:
    data = _read_manifest(cache_dir)
    data[key] = entry
    tmp = cache_dir / f".{MANIFEST}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True))
    os.replace(tmp, cache_dir / MANIFEST)


def ensure_reference(
    scene_name: str, cache_dir: str | os.PathLike, samples: int = DEFAULT_SAMPLES,
    bounces: int = 1, resolution: tuple[int, int] | None = None,
    python: str | None = None, timeout: float | None = None,
) -> tuple[Path, Path]:
    """(blend_path, exr_path) of a cached Cycles reference, rendered only on a cache miss.

    Runs the build/render in a child process of ``python`` (default sys.executable), so the
    calling process's bpy state stays untouched. Raises RuntimeError with the child's output
    tail when it fails.
    """
    cache_dir = Path(cache_dir).resolve()
    cache_dir.mkdir(parents=True, exist_ok=True)
    res = None if resolution is None else (int(resolution[0]), int(resolution[1]))
    key = _manifest_key(scene_name, samples, bounces, res)
    entry = _read_manifest(cache_dir).get(key)
    if entry:
        blend, exr = cache_dir / entry["blend"], cache_dir / entry["exr"]
        if blend.is_file() and exr.is_file():
            return blend, exr

    result_file = cache_dir / f".result.{os.getpid()}.{uuid.uuid4().hex[:8]}.json"
    cmd = [
        python or sys.executable, str(Path(__file__).resolve()), "--out", str(cache_dir),
        "--scenes", scene_name, "--samples", str(samples), "--bounces", str(bounces),
        "--cached", "--result-json", str(result_file),
    ]
    if res is not None:
        cmd += ["--resolution", f"{res[0]}x{res[1]}"]
    try:
        proc = subprocess.run(
            cmd, check=False, capture_output=True, text=True, timeout=timeout, cwd=ROOT
        )
        if proc.returncode != 0 or not result_file.is_file():
            tail = (proc.stdout[-2000:] + "\n" + proc.stderr[-4000:]).strip()
            raise RuntimeError(
                f"reference for {scene_name!r} failed (exit {proc.returncode}):\n{tail}"
            )
        result = json.loads(result_file.read_text())[0]
    finally:
        result_file.unlink(missing_ok=True)
    blend, exr = Path(result["blend"]), Path(result["exr"])
    _write_manifest(cache_dir, key, {"blend": blend.name, "exr": exr.name,
                                     "hash": result["hash"], "seconds": result["seconds"]})
    return blend, exr


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--samples", type=int, default=DEFAULT_SAMPLES)
    p.add_argument("--bounces", type=int, default=1, help="diffuse (and max) bounces")
    p.add_argument("--scenes", default=",".join(DEFAULT_SCENES),
                   help="comma-separated scene names (see tools.scenes.SCENES)")
    p.add_argument("--resolution", type=_parse_resolution, default=None,
                   help="WxH (default: each scene's own, 128x128)")
    p.add_argument("--cached", action="store_true",
                   help="cache mode: content-hashed names, render only what is missing")
    p.add_argument("--result-json", type=Path, default=None,
                   help="write a JSON list of results here")
    args = p.parse_args(argv)
    names = [n.strip() for n in args.scenes.split(",") if n.strip()]
    if not names:
        p.error("no scenes given")
    if args.samples < 1 or args.bounces < 0:
        p.error("need --samples >= 1 and --bounces >= 0")
    scenes, _, _ = _import_bpy_side()
    known = set(scenes.SCENES) | set(scenes.BUILDERS)
    unknown = [n for n in names if n not in known]
    if unknown:
        p.error(f"unknown scene(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    t0 = time.perf_counter()
    if args.cached:
        results = [_cached_one(args.out, n, args.samples, args.bounces, args.resolution)
                   for n in names]
    else:
        results = make(args.out, names, args.samples, args.bounces, args.resolution)
    _log(f"done: {len(results)} scene(s) in {time.perf_counter() - t0:.1f} s")
    if args.result_json is not None:
        tmp = args.result_json.with_name(args.result_json.name + ".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        os.replace(tmp, args.result_json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
