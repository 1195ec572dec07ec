"""Compatibility smoke test, run inside the Blender (bpy module) under test.

    BLENDER_USER_RESOURCES=TMP  PYTHON tools/compat_smoke.py EXTENSION.zip OUT_DIR

Installs the extension zip into the (fresh, temporary) Blender user folder the way Blender's
"Install from Disk" does, checks it registered, builds the demo scene (the Cornell box of
`python -m lpv_addon.batch --demo`), runs one LPV update (`bpy.ops.lpv.update`) and renders one
batch frame (`bpy.ops.lpv.render_batch`) to OUT_DIR/0001.exr, and one F12 frame with the
LPV_GI render engine (`bpy.ops.render.render`). Prints one line
`RESULT={json}` with what it saw; tests/test_compat_smoke.py judges it and compares the frame.

Only public entry points of the installed extension are used: `bl_ext.user_default.<id>`
(register), `scene.lpv`, `bpy.ops.lpv.*`, and the shipped demo scene builder (`demo_builder`).
Never import this file from the test process: it imports bpy.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import sys
import time
import traceback
from pathlib import Path

# Packages the extension bundles as wheels: where each is imported from is recorded, so the
# test can tell whether the bundled wheels (Blender's extension site-packages) were exercised.
BUNDLED = ("moderngl", "glcontext", "OpenEXR", "numba", "llvmlite")


def demo_builder(package: str):
    """The installed extension's demo scene builder, `cornell_box(light, resolution=...)`: the
    scene `python -m lpv_addon.batch --demo` renders (lpv_addon/scene_io/demo.py)."""
    return importlib.import_module(f"{package}.lpv_addon.scene_io.demo").cornell_box


def origin(name: str) -> str | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    return spec.origin if spec else None


def run(zip_path: str, out_dir: str) -> dict:
    import bpy

    addon_utils = importlib.import_module("addon_utils")  # on sys.path once bpy is imported

    with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..",
                           "blender_manifest.toml"), "rb") as fh:
        ext_id = next(ln.split("=", 1)[1].strip().strip('"') for ln in fh.read().decode()
                      .splitlines() if ln.startswith("id "))
    module = f"bl_ext.user_default.{ext_id}"
    out: dict = {
        "blender": list(bpy.app.version),
        "python": list(sys.version_info[:3]),
        "executable": sys.executable,
        "module": module,
    }
    ret = bpy.ops.extensions.package_install_files(
        filepath=zip_path, repo="user_default", enable_on_install=True)
    out["install"] = sorted(ret)
    out["enabled"] = module in bpy.context.preferences.addons
    out["loaded"] = bool(addon_utils.check(module)[1])
    out["extension_site_packages"] = os.path.join(
        bpy.utils.user_resource("EXTENSIONS"), ".local", "lib",
        "python{}.{}".format(*sys.version_info[:2]), "site-packages")
    out["origins"] = {name: origin(name) for name in (*BUNDLED, "numpy")}
    if not (out["enabled"] and out["loaded"]):
        return out

    cornell_box = demo_builder(module)
    cornell_box("SPOT", resolution=(256, 256))  # as `python -m lpv_addon.batch --demo`
    scene = bpy.context.scene
    scene.frame_start = scene.frame_end = 1
    out["has_lpv"] = hasattr(scene, "lpv")
    if not out["has_lpv"]:
        return out
    scene.lpv.enabled = True
    out["update"] = sorted(bpy.ops.lpv.update())
    # The first update is served by the numpy reference while the bundled numba compiles the
    # kernels in the background: wait for that (the viewport's timer step, headless) so the
    # batch frame below shows whether the compiled kernels run on this Blender line.
    live = sys.modules[f"{module}.lpv_addon.viewport.live"]
    deadline = time.monotonic() + 900.0
    while live.STATE.kernels.get("state") in ("waiting", "compiling") and (
            time.monotonic() < deadline):
        live.tick(require_viewport=False)
        time.sleep(0.5)
    out["kernels"] = dict(live.STATE.kernels)
    out["render_batch"] = sorted(bpy.ops.lpv.render_batch(directory=out_dir))
    out["frames"] = sorted(p.name for p in Path(out_dir).glob("*.exr"))
    stats = Path(out_dir) / "stats.json"
    out["stats"] = json.loads(stats.read_text()) if stats.is_file() else None
    scene.render.engine = "LPV_GI"  # the render engine registered: one F12 frame
    out["f12"] = sorted(bpy.ops.render.render(write_still=False))
    addon_utils.disable(module, default_set=True)
    out["disabled"] = module not in bpy.context.preferences.addons
    return out


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    try:
        out = run(os.path.abspath(argv[0]), os.path.abspath(argv[1]))
    except Exception as exc:  # noqa: BLE001 - reported to the test, which fails on it
        out = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
    print("RESULT=" + json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
